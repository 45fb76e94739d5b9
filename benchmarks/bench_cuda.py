"""Benchmark the latent world model on a CUDA GPU, and check the GPU's samples against the CPU's.

Rows (each with the peak GPU memory the row allocated, torch.cuda.max_memory_allocated):
- latent model (``latent-128``) training steps/s reading a latent cache, at several batch sizes;
- autoencoder (``ae-f8c32``) training steps/s at several batch sizes (frames);
- seconds per sampled 16-frame 128² clip for the shipped ``v2`` (10 guided steps) and
  ``v2-2step`` (2 steps), 1 and 8 scenes per pipeline call;
- agreement: one clip (the same first frame, instruction and initial noise) sampled on the GPU
  and on the CPU in fp32, as RGB PSNR, depth error in mm and normal angle of the GPU clip against
  the CPU's; the same for the GPU in bf16 (the precision ``auto`` picks on a bf16 GPU).
Every timing synchronises the GPU before reading the clock. Training rows use random weights and
synthetic 128² data (speed does not depend on them); sampling rows use the shipped weights.

  python benchmarks/bench_cuda.py [--repeats 5] [--train-steps 20]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

from measure import median_seconds, print_table

ROOT = Path(__file__).resolve().parent.parent
CHECKPOINTS = ROOT / "tesseract4d" / "checkpoints"


def cuda_seconds(fn, repeats: int) -> float:
    """``measure.median_seconds`` of ``fn`` after one untimed call, the GPU synchronised after each
    call, so every clock read finds it idle."""
    import torch

    def synced():
        fn()
        torch.cuda.synchronize()

    return median_seconds(synced, repeats, warmup=True)


def peak_mb(fn) -> float:
    """Peak GPU memory (MB) allocated while ``fn`` runs."""
    import torch

    torch.cuda.synchronize()
    torch.cuda.reset_peak_memory_stats()
    fn()
    torch.cuda.synchronize()
    return torch.cuda.max_memory_allocated() / 2**20


def bench_latent_training(data: Path, ae_dir: Path, batch_size: int, steps: int) -> tuple[float, float]:
    from tesseract4d.model.trainer import TrainConfig, Trainer

    with tempfile.TemporaryDirectory() as out:
        trainer = Trainer(TrainConfig(data=data, out=Path(out) / "run", preset="latent-128", autoencoder=ae_dir,
                                      max_steps=10**6, batch_size=batch_size, val_every=0, ckpt_every=0,
                                      quiet=True))
        s = cuda_seconds(trainer.train_step, steps)
        return s, peak_mb(trainer.train_step)


def bench_autoencoder_training(data: Path, batch_size: int, steps: int) -> tuple[float, float]:
    from tesseract4d.model.autoencoder_trainer import AutoencoderTrainConfig, AutoencoderTrainer

    with tempfile.TemporaryDirectory() as out:
        trainer = AutoencoderTrainer(AutoencoderTrainConfig(data=data, out=Path(out) / "run", preset="ae-f8c32",
                                                            batch_size=batch_size, quiet=True))
        s = cuda_seconds(trainer.train_step, steps)
        return s, peak_mb(trainer.train_step)


def first_frames(data: Path, count: int):
    """(count, 7, 128, 128) model-space first frames of the synthetic episodes, and their instructions."""
    import torch

    from tesseract4d import dataset_format as df
    from tesseract4d.model.model_space import ModelSpace

    frames, texts = [], []
    for path in df.list_episode_files(data)[:count]:
        ep = df.read_episode(path)
        cam = next(iter(ep.cameras.values()))
        frames.append(ModelSpace().encode(cam.rgb[:1], cam.depth_m[:1], cam.normal_cam[:1])[0])
        texts.append(ep.instruction)
    n = len(frames)  # repeat the episodes when there are fewer than asked
    frames += [frames[i % n] for i in range(n, count)]
    texts += [texts[i % n] for i in range(n, count)]
    return torch.stack(frames), texts


def sample(pipe, first, texts, seed: int = 0):
    import torch

    return pipe(first, texts, generator=torch.Generator().manual_seed(seed))


def agreement(gpu_clip, cpu_clip) -> str:
    """RGB PSNR (dB), depth MAE (mm) and mean normal angle (°) of a GPU clip against the CPU's."""
    import numpy as np

    from tesseract4d.model.model_space import ModelSpace
    from tesseract4d.psnr import rgb_psnr

    space = ModelSpace()
    (g_rgb, g_depth, g_n), (c_rgb, c_depth, c_n) = space.decode(gpu_clip[0]), space.decode(cpu_clip[0])
    depth_mm = 1000 * float(np.abs(g_depth - c_depth).mean())
    cos = (g_n.astype(np.float64) * c_n.astype(np.float64)).sum(-1)
    angle = float(np.degrees(np.arccos(np.clip(cos, -1, 1))).mean())
    return f"PSNR {rgb_psnr(g_rgb, c_rgb):.1f} dB, depth {depth_mm:.2f} mm, normals {angle:.2f}°"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--train-steps", type=int, default=20, help="timed training steps per row")
    parser.add_argument("--repeats", type=int, default=5, help="timed clips per sampling row")
    parser.add_argument("--latent-batches", type=int, nargs="+", default=[4, 32, 128],
                        help="batch sizes of the latent-model training rows")
    parser.add_argument("--autoencoder-batches", type=int, nargs="+", default=[8, 64],
                        help="batch sizes (frames) of the autoencoder training rows")
    args = parser.parse_args(argv)

    from tesseract4d import runtime

    runtime.configure()
    import torch

    if not torch.cuda.is_available():
        print("bench_cuda.py: no CUDA device here; run it on a machine with an NVIDIA GPU", file=sys.stderr)
        return 2
    from tesseract4d.testing.synthetic_scene import write_segmented_dataset

    from tesseract4d.model.predict import load_pipeline
    from tesseract4d.precision import resolve_precision

    name = torch.cuda.get_device_name()
    print(f"GPU: {name}; torch {torch.__version__}; precision auto on cuda: {resolve_precision('auto', 'cuda').name}")
    rows = []

    def add(*row):
        rows.append(row)
        print(*row, sep=" | ", flush=True)

    ae_dir = CHECKPOINTS / "v2" / "autoencoder"
    with tempfile.TemporaryDirectory() as tmp:
        data = write_segmented_dataset(Path(tmp) / "data128", episodes=8, frames=16, size=128)
        for b in args.latent_batches:
            s, mb = bench_latent_training(data, ae_dir, b, args.train_steps)
            add("latent-128", "auto", f"train b{b} (latent cache)", f"{1 / s:.1f} steps/s ({b / s:.0f} clips/s)", f"{mb:.0f}")
        for b in args.autoencoder_batches:
            s, mb = bench_autoencoder_training(data, b, args.train_steps)
            add("autoencoder ae-f8c32", "auto", f"train b{b} frames", f"{1 / s:.1f} steps/s ({b / s:.0f} frames/s)", f"{mb:.0f}")
        first, texts = first_frames(data, 8)

    for ckpt in ("v2", "v2-2step"):
        folder = CHECKPOINTS / ckpt
        pipe = load_pipeline(folder, device="cuda", precision="auto")
        what = f"{pipe.preset.num_steps} steps" + (f", guidance {pipe.preset.text_guidance:g}"
                                                  if pipe.preset.text_guidance != 1 else "")
        for n in (1, 8):
            s = cuda_seconds(lambda: sample(pipe, first[:n], texts[:n]), args.repeats)
            mb = peak_mb(lambda: sample(pipe, first[:n], texts[:n]))
            add(ckpt, "bf16" if pipe.bf16 else "fp32", f"sample {what}, {n} scene(s) per call",
                f"{s / n:.3f} s/clip", f"{mb:.0f}")
        cpu = sample(load_pipeline(folder, device="cpu", precision="fp32"), first[:1], texts[:1])
        gpu32 = sample(load_pipeline(folder, device="cuda", precision="fp32"), first[:1], texts[:1])
        add(ckpt, "fp32", "GPU clip against the CPU's (same noise)", agreement(gpu32, cpu), "")
        add(ckpt, "bf16" if pipe.bf16 else "fp32", "GPU clip against the CPU's fp32 (same noise)",
            agreement(sample(pipe, first[:1], texts[:1]), cpu), "")
    print()
    print(f"GPU: {name}")
    print_table(("model", "precision", "what", "result", "peak GPU MB"), rows)
    return 0


if __name__ == "__main__":
    sys.exit(main())
