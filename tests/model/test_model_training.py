"""Training of the RGB-D-N model: exact resume, checkpoint format, export, time limit, overfitting."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch
from tesseract4d.testing.model_fixtures import MICRO, register_preset, short_step_budget, sigterm_after_step
from tesseract4d.testing.synthetic_scene import write_synthetic_dataset

from tesseract4d import cli
from tesseract4d.errors import UserError
from tesseract4d.model.trainer import TrainConfig, Trainer, list_checkpoints
from tesseract4d.psnr import rgb_psnr


@pytest.fixture(scope="module")
def dataset(tmp_path_factory) -> Path:
    return write_synthetic_dataset(tmp_path_factory.mktemp("model_train") / "data", episodes=4)


pytestmark = pytest.mark.usefixtures("micro_preset")


def _config(data: Path, out: Path, **kw) -> TrainConfig:
    base = dict(data=data, out=out, preset=MICRO.name, max_steps=4, val_every=0, ckpt_every=0, quiet=True)
    base.update(kw)
    return TrainConfig(**base)


def _weights(trainer: Trainer) -> dict[str, torch.Tensor]:
    return {k: v.detach().clone() for k, v in trainer.accelerator.unwrap_model(trainer.model).state_dict().items()}


def test_two_steps_then_resume_equals_four_steps(dataset, tmp_path):
    straight = Trainer(_config(dataset, tmp_path / "a"))
    losses_a = [straight.train_step()["loss"] for _ in range(4)]

    first = Trainer(_config(dataset, tmp_path / "b"))
    losses_b = [first.train_step()["loss"] for _ in range(2)]
    first.save_checkpoint()
    del first
    resumed = Trainer(_config(dataset, tmp_path / "b", resume=True))
    assert resumed.step == 2
    losses_b += [resumed.train_step()["loss"] for _ in range(2)]

    assert losses_b == losses_a
    wa, wb = _weights(straight), _weights(resumed)
    assert all(torch.equal(wa[k], wb[k]) for k in wa)
    ema_a, ema_b = straight.ema.model.state_dict(), resumed.ema.model.state_dict()
    assert all(torch.equal(ema_a[k], ema_b[k]) for k in ema_a)


def test_time_limit_stops_with_checkpoint_and_export(dataset, tmp_path):
    run = tmp_path / "run"
    final = Trainer(_config(dataset, run, max_steps=1000, max_minutes=0.0, val_every=1)).train()
    ckpts = list_checkpoints(run)
    assert [c.name for c in ckpts] == ["checkpoint-000001"]
    ckpt = ckpts[0]
    for name in ("transformer/config.json", "transformer/diffusion_pytorch_model.safetensors",
                 "transformer_ema/diffusion_pytorch_model.safetensors", "optimizer.safetensors", "optimizer.json",
                 "rng_state.safetensors", "trainer_state.json"):
        assert (ckpt / name).is_file(), name
    # No pickle anywhere in a run folder.
    assert not [p for p in run.rglob("*") if p.suffix in (".bin", ".pt", ".pth", ".pkl", ".ckpt")]
    assert final == run / "final"
    assert sorted(p.relative_to(final).as_posix() for p in final.rglob("*") if p.is_file()) == [
        ".tesseract4d-output.json", "scheduler/scheduler_config.json", "tesseract4d_config.json", "transformer/config.json",
        "transformer/diffusion_pytorch_model.safetensors"]
    info = json.loads((final / "tesseract4d_config.json").read_text())
    assert info["preset"]["name"] == MICRO.name and info["resolution"] == [32, 32] and info["num_frames"] == 8
    assert info["depth_range_m"] == [MICRO.near_m, MICRO.far_m] and info["text_encoder"]["kind"] == "minilm"
    assert info["training"]["steps"] == 1 and info["camera_name"] == "close"
    assert list((run / "validation").rglob("*.mp4")), "validation video written"
    assert (run / "logs").is_dir() and (run / "train_config.json").is_file()


def test_stop_at_step_keeps_the_schedule_and_resume_goes_on(dataset, tmp_path):
    # A run cut short of its schedule: it stops with a checkpoint at step 3 of a 6-step cosine schedule;
    # --resume without the stop then ends with exactly the weights of an uninterrupted 6-step run (so the
    # first 3 steps used the 6-step schedule's learning rates).
    straight = Trainer(_config(dataset, tmp_path / "a", max_steps=6))
    straight.train()
    run = tmp_path / "b"
    Trainer(_config(dataset, run, max_steps=6, stop_at_step=3)).train()
    assert [c.name for c in list_checkpoints(run)] == ["checkpoint-000003"]
    resumed = Trainer(_config(dataset, run, max_steps=6, resume=True))
    assert resumed.step == 3
    resumed.train()
    assert resumed.step == 6
    wa, wb = _weights(straight), _weights(resumed)
    assert all(torch.equal(wa[k], wb[k]) for k in wa)
    with pytest.raises(UserError, match="--stop-at-step must be between 1 and --max-steps"):
        Trainer(_config(dataset, tmp_path / "c", max_steps=6, stop_at_step=7))


def test_resume_refuses_other_preset_and_existing_run(dataset, tmp_path, monkeypatch):
    import dataclasses

    run = tmp_path / "run"
    trainer = Trainer(_config(dataset, run, max_steps=1))
    trainer.train_step()
    trainer.save_checkpoint()
    with pytest.raises(UserError, match="--resume"):
        Trainer(_config(dataset, run))
    register_preset(monkeypatch, dataclasses.replace(MICRO, backbone={**MICRO.backbone, "num_layers": 3}))
    with pytest.raises(UserError, match="differs from --preset"):
        Trainer(_config(dataset, run, resume=True))


def test_bad_training_inputs(dataset, tmp_path):
    with pytest.raises(UserError, match="no info.json|does not exist"):
        Trainer(_config(tmp_path / "nowhere", tmp_path / "r1"))
    with pytest.raises(UserError, match="preset trains on 64x64"):
        Trainer(_config(dataset, tmp_path / "r2", preset="tiny"))


def test_train_cli_and_export(dataset, tmp_path, capsys):
    run = tmp_path / "run"
    assert cli.main(["train", "--preset", MICRO.name, "--data", str(dataset), "--out", str(run), "--max-steps", "2",
                     "--val-every", "0", "--quiet"]) == 0
    assert (run / "final" / "transformer" / "diffusion_pytorch_model.safetensors").is_file()
    assert cli.main(["checkpoint", "export", str(run), "--to", str(tmp_path / "exported")]) == 0
    assert (tmp_path / "exported" / "tesseract4d_config.json").is_file()
    assert cli.main(["checkpoint", "export", str(tmp_path / "empty")]) == 2
    assert "holds no checkpoint" in capsys.readouterr().err


def test_several_datasets_train_as_one_set(dataset, tmp_path):
    from tesseract4d.testing.synthetic_scene import synthetic_episode

    from tesseract4d import dataset_format as df

    other = tmp_path / "other"
    df.init_dataset(other, df.DatasetInfo(height=32, width=32, cameras=["close"]))
    for seed in (10, 11, 12):
        df.write_episode(other, synthetic_episode(seed, 8, 32))
    trainer = Trainer(_config([dataset, other], tmp_path / "run"))
    ids = {s.episode_id for s in trainer.data.sources}
    assert len(ids) == 4 + 3
    assert any("000010" in i for i in ids) and any("000000" in i for i in ids)
    assert trainer.train_step()["loss"] > 0
    saved = json.loads((tmp_path / "run" / "train_config.json").read_text())
    assert saved["data"] == [str(dataset), str(other)]
    with pytest.raises(UserError, match="in two of the training datasets"):
        Trainer(_config([dataset, dataset], tmp_path / "twice"))


@pytest.mark.slow
def test_overfit_one_clip(tmp_path):
    """300 steps on one clip: the loss falls and a sample reproduces the clip far better than the
    static world (first frame repeated) and noise."""
    data = write_synthetic_dataset(tmp_path / "one", episodes=1)
    trainer = Trainer(_config(data, tmp_path / "run", max_steps=300, batch_size=4, text_dropout=0.0,
                              image_dropout=0.0))
    losses = [trainer.train_step()["loss"] for _ in range(300)]
    assert sum(losses[-10:]) / 10 < 0.1 * losses[0]

    from tesseract4d.model.pipeline import RGBDNPipeline, make_scheduler

    pipe = RGBDNPipeline(trainer.ema.model, make_scheduler(), trainer.codec, trainer.text_encoder, trainer.preset,
                         trainer.model_space)
    clip, text = trainer.data.clip(0)
    pred = pipe(clip[None, 0], [text], num_inference_steps=4, generator=torch.Generator().manual_seed(0))[0]
    gt = (clip + 1) / 2
    psnr = rgb_psnr(((pred + 1) / 2).clamp(0, 1), gt)
    static = rgb_psnr(gt[:1].expand_as(gt), gt)
    noise = rgb_psnr(torch.rand(gt.shape, generator=torch.Generator().manual_seed(0)), gt)
    # Measured: 35.5 dB vs 21.1 dB static world vs 8.5 dB noise.
    assert psnr > 28.0 and psnr > static + 6.0 and psnr > noise + 15.0, (psnr, static, noise)


def test_max_steps_auto_fits_the_schedule_and_trains_as_that_number(dataset, tmp_path, monkeypatch, capsys):
    # Clock reads: start 1, after steps 1/2/3: 2, 3, 4 -> 2 timed steps in 2 s = 1 step/s, 0.5 min - 3 s left.
    short_step_budget(monkeypatch, "tesseract4d.training.loop")
    fitted = 3 + int(1.0 * (30.0 - 3.0) * 0.93)
    run = tmp_path / "auto"
    auto = Trainer(_config(dataset, run, max_steps="auto", max_minutes=0.5, warmup_steps=3))
    auto.train()
    printed = capsys.readouterr()
    assert f"schedule ends at step {fitted}" in printed.out + printed.err
    assert auto.step == fitted == auto.cfg.max_steps
    saved = json.loads((run / "train_config.json").read_text())
    assert saved["max_steps"] == fitted and saved["max_steps_fit"]["steps_per_s"] == pytest.approx(1.0)
    state = json.loads((list_checkpoints(run)[-1] / "trainer_state.json").read_text())
    assert state["config"]["max_steps"] == fitted
    # The probe's steps are warm-up steps, so the run is step for step a run given that number.
    given = Trainer(_config(dataset, tmp_path / "given", max_steps=fitted, warmup_steps=3))
    given.train()
    wa, wb = _weights(auto), _weights(given)
    assert all(torch.equal(wa[k], wb[k]) for k in wa)
    # --resume with auto (no budget needed) goes on along the recorded schedule.
    resumed = Trainer(_config(dataset, run, max_steps="auto", resume=True, warmup_steps=3))
    assert resumed.cfg.max_steps == fitted and resumed.cfg.max_steps_fit == saved["max_steps_fit"]
    with pytest.raises(UserError, match="--max-minutes"):
        Trainer(_config(dataset, tmp_path / "nobudget", max_steps="auto"))


def test_sigterm_stops_training_with_a_checkpoint_an_export_and_a_word(dataset, tmp_path, capsys, monkeypatch):
    """A scheduler's stop (SIGTERM) during step 2 of 1,000 ends the run after that step as --max-minutes
    would: a checkpoint of step 2, the export, and a line saying why it stopped."""
    import signal

    run = tmp_path / "run"
    trainer = Trainer(_config(dataset, run, max_steps=1000, quiet=False))
    sigterm_after_step(monkeypatch, trainer, 2)
    before = signal.getsignal(signal.SIGTERM)
    final = trainer.train()
    assert signal.getsignal(signal.SIGTERM) == before
    assert [c.name for c in list_checkpoints(run)] == ["checkpoint-000002"]
    assert final == run / "final" and (final / "transformer" / "diffusion_pytorch_model.safetensors").is_file()
    assert "stopped by SIGTERM at step 2; saving a checkpoint and the export" in capsys.readouterr().out
    assert trainer.stopped_by == signal.SIGTERM  # the command line then ends 143 (raise_for_stop)


def test_a_train_command_stopped_by_sigterm_ends_143_with_its_checkpoint_and_export(dataset, tmp_path, capsys,
                                                                                    monkeypatch):
    """A scheduler can tell a stopped run from a finished one: exit 143, yet final/ is written."""
    sigterm_after_step(monkeypatch, Trainer, 2)
    run = tmp_path / "run"
    assert cli.main(["train", "--preset", MICRO.name, "--data", str(dataset), "--out", str(run), "--max-steps", "100",
                     "--val-every", "0", "--quiet"]) == 143
    assert [c.name for c in list_checkpoints(run)] == ["checkpoint-000002"]
    assert (run / "final" / "transformer" / "diffusion_pytorch_model.safetensors").is_file()
    assert "terminated; finished work is kept on disk" in capsys.readouterr().err


def test_weights_are_as_readable_as_the_users_other_files(dataset, tmp_path):
    """safetensors writes its files 0600; checkpoints and exports get the mode a plain create gives
    under the user's umask (0644 under 022), so a shared checkpoint folder can be read by others."""
    import os

    previous = os.umask(0o022)
    try:
        final = Trainer(_config(dataset, tmp_path / "run", max_steps=1)).train()
        assert cli.main(["checkpoint", "export", str(tmp_path / "run"), "--to", str(tmp_path / "exported")]) == 0
    finally:
        os.umask(previous)
    written = [p for root in (tmp_path / "run", tmp_path / "exported") for p in root.rglob("*.safetensors")]
    assert len(written) >= 6 and final in [p.parents[1] for p in written]
    assert {oct(p.stat().st_mode & 0o777) for p in written} == {"0o644"}
