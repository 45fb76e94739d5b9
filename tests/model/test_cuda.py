"""The model on a CUDA GPU: trained there, sampled there, and the same clips as on the CPU.

These run only where torch sees a CUDA device (CI's machines have none; on a GPU machine run
``pytest tests/model/test_cuda.py``). The rest of the suite also runs on such a machine, where the
trainers pick the GPU by themselves (accelerate), so training, resume and export are exercised there too.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
from tesseract4d.testing.model_fixtures import MICRO
from tesseract4d.testing.synthetic_scene import write_synthetic_dataset

from tesseract4d import cli
from tesseract4d.model.model_space import ModelSpace
from tesseract4d.model.predict import load_pipeline
from tesseract4d.psnr import rgb_psnr

pytestmark = [pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU"),
              pytest.mark.usefixtures("micro_preset")]

SHIPPED = Path(__file__).resolve().parents[2] / "tesseract4d" / "checkpoints" / "v2-2step"


def _first_frame(size: int) -> tuple[torch.Tensor, str]:
    from tesseract4d.testing.synthetic_scene import synthetic_episode

    ep = synthetic_episode(0, 2, size, direction=1)
    cam = ep.cameras["close"]
    return ModelSpace().encode(cam.rgb[:1], cam.depth_m[:1], cam.normal_cam[:1]), ep.instruction


def _sample(pipe, first: torch.Tensor, text: str) -> np.ndarray:
    return pipe(first, [text], generator=torch.Generator().manual_seed(3)).numpy()


def test_shipped_model_samples_the_same_clip_on_gpu_and_cpu():
    # The same first frame, words and initial noise (drawn on the CPU) give the same clip on both
    # devices in fp32, up to kernel rounding; bf16 on the GPU stays close to it.
    first, text = _first_frame(128)
    cpu = _sample(load_pipeline(SHIPPED, device="cpu", precision="fp32"), first, text)
    gpu = _sample(load_pipeline(SHIPPED, device="cuda", precision="fp32"), first, text)
    assert np.abs(gpu - cpu).mean() < 1e-3  # a few pixels (normals near zero length) may differ more
    rgb = [ModelSpace().decode(torch.from_numpy(c[0]))[0] for c in (cpu, gpu)]
    assert rgb_psnr(rgb[1], rgb[0]) > 40
    bf16 = _sample(load_pipeline(SHIPPED, device="cuda", precision="bf16"), first, text)
    assert rgb_psnr(ModelSpace().decode(torch.from_numpy(bf16[0]))[0], rgb[0]) > 30


def test_trained_on_gpu_then_sampled_on_cpu(tmp_path):
    # A run on a GPU machine trains on the GPU, and its export samples on the CPU the clip the GPU samples.
    from tesseract4d.model.trainer import TrainConfig, Trainer

    data = write_synthetic_dataset(tmp_path / "data", episodes=2)
    trainer = Trainer(TrainConfig(data=data, out=tmp_path / "run", preset=MICRO.name, max_steps=6, val_every=0,
                                  ckpt_every=3, quiet=True))
    assert trainer.device.type == "cuda"
    trainer.train()
    assert cli.main(["checkpoint", "export", str(tmp_path / "run"), "--to", str(tmp_path / "export")]) == 0
    first, text = _first_frame(MICRO.height)
    cpu = _sample(load_pipeline(tmp_path / "export", device="cpu", precision="fp32"), first, text)
    gpu = _sample(load_pipeline(tmp_path / "export", device="cuda", precision="fp32"), first, text)
    assert np.isfinite(cpu).all() and np.abs(gpu - cpu).mean() < 1e-3


def test_predict_command_on_gpu(tmp_path):
    # The shipped default predicts on the GPU through the command line, previews included.
    data = write_synthetic_dataset(tmp_path / "data", episodes=1, frames=4, size=128)
    out = tmp_path / "pred"
    assert cli.main(["predict", "--episode", str(data / "Synthetic-v0" / "0"), "--device", "cuda",
                     "--out", str(out)]) == 0
    assert json.loads((out / "predict_config.json").read_text())["device"] == "cuda"
    assert list(out.rglob("*.h5")) and list(out.rglob("*.mp4"))


def test_autoencoder_trains_on_gpu_and_reconstructs_alike_on_cpu(tmp_path):
    from tesseract4d.testing.synthetic_scene import write_segmented_dataset

    from tesseract4d.model.autoencoder_loading import load_autoencoder
    from tesseract4d.model.autoencoder_trainer import AutoencoderTrainConfig, AutoencoderTrainer

    data = write_segmented_dataset(tmp_path / "data", episodes=2, size=32)
    trainer = AutoencoderTrainer(AutoencoderTrainConfig(data=data, out=tmp_path / "ae", preset="ae-test", max_steps=4,
                                                        batch_size=4, quiet=True))
    assert trainer.device.type == "cuda" and next(trainer.model.parameters()).is_cuda
    trainer.train()
    frames = trainer.frames.frames[:4].float()
    cpu, gpu = load_autoencoder(tmp_path / "ae" / "autoencoder"), load_autoencoder(tmp_path / "ae" / "autoencoder").cuda()
    a, b = cpu.decode(cpu.encode(frames)), gpu.decode(gpu.encode(frames)).cpu()
    assert np.abs((a - b).numpy()).mean() < 1e-3


def test_distill_samples_pairs_and_trains_the_student_on_gpu(tmp_path, monkeypatch):
    # On a GPU machine the teacher samples the pairs there (the CPU's clips up to kernel rounding) and the
    # student trains there, its validation (student against teacher clips, decoded) included.
    from tesseract4d.model.reflow import PairsConfig, ReflowPairs, generate_pairs
    from tesseract4d.model.trainer import TrainConfig, Trainer

    data = write_synthetic_dataset(tmp_path / "data", episodes=2)
    teacher = Trainer(TrainConfig(data=data, out=tmp_path / "teacher", preset=MICRO.name, max_steps=4, val_every=0,
                                  ckpt_every=0, quiet=True)).train()
    run = tmp_path / "student"
    assert cli.main(["distill", "--teacher", str(teacher), "--data", str(data), "--pairs", str(tmp_path / "pairs"),
                     "--num-pairs", "4", "--teacher-steps", "2", "--set", "precision=fp32", "--out", str(run),
                     "--max-steps", "4", "--val-every", "2", "--ckpt-every", "0", "--batch-size", "2",
                     "--quiet"]) == 0
    state = json.loads((run / "checkpoint-000004" / "trainer_state.json").read_text())
    assert state["step"] == 4 and state["config"]["val_every"] == 2
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)  # the same pairs sampled on the CPU
    cpu = ReflowPairs(generate_pairs(PairsConfig(teacher=teacher, data=data, out=tmp_path / "cpu_pairs", num_pairs=4,
                                                 teacher_steps=2, precision="fp32"), progress=False))
    gpu = ReflowPairs(tmp_path / "pairs")
    assert gpu.instructions == cpu.instructions and torch.equal(gpu.noise, cpu.noise)
    assert (gpu.x0 - cpu.x0).abs().mean() < 1e-3
