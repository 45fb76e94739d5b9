"""The one training loop (tesseract4d/training/loop.py): the same stop, schedule, guard, checkpoints and
resume for every trainer.

The loop's own semantics are checked on a small real trainer (a linear model fitted with AdamW) that
plugs into it as the project's trainers do; one parametrised test then stops each of the four real
trainers (diffusion, reflow student, autoencoder, IDM) with SIGTERM after step 2 and resumes it.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import signal
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
import torch
from tesseract4d.testing.model_fixtures import MICRO, short_step_budget, sigterm_after_step
from tesseract4d.testing.synthetic_scene import synthetic_episode, write_segmented_dataset, write_synthetic_dataset

from tesseract4d import dataset_format as df
from tesseract4d.errors import Terminated, UserError
from tesseract4d.stopping import raise_for_stop
from tesseract4d.training.checkpoints import (list_checkpoints, load_optimizer, resume_newest, save_optimizer,
                                              write_checkpoint)
from tesseract4d.training.config import TrainingLoopConfig
from tesseract4d.training.loop import (check_finite, learning_rate, loop_state, restore_loop_state, run_loop,
                                       set_learning_rate)


@dataclass
class LineConfig(TrainingLoopConfig):
    max_steps: int | str = 20
    lr: float = 0.2
    warmup_steps: int = 2
    ckpt_every: int = 0
    quiet: bool = True


class LineTrainer:
    """Fits y = 3x - 1 with a linear layer: a trainer of the loop, as small as one can be."""

    def __init__(self, cfg: LineConfig, out: Path, poison_at: int | None = None):
        from safetensors.torch import load_file

        self.cfg, self.out, self.poison_at = cfg, Path(out), poison_at
        self.out.mkdir(parents=True, exist_ok=True)
        torch.manual_seed(cfg.seed)
        self.model = torch.nn.Linear(1, 1)
        self.optimizer = torch.optim.AdamW(self.model.parameters(), lr=cfg.lr)
        self.step, self.elapsed_s, self.last_loss, self.stopped_by = 0, 0.0, None, None
        self.exports = 0
        if cfg.resume:
            def load(ckpt, state):
                self.model.load_state_dict(load_file(str(ckpt / "model.safetensors")))
                load_optimizer(self.optimizer, ckpt)
                restore_loop_state(self, state)

            resume_newest(self.out, load)

    def train_step(self) -> dict:
        g = torch.Generator().manual_seed(self.cfg.seed * 1_000_003 + self.step)
        x = torch.randn(16, 1, generator=g)
        lr = learning_rate(self)
        set_learning_rate(self.optimizer, lr)
        loss = torch.nn.functional.mse_loss(self.model(x), 3 * x - 1)
        if self.poison_at == self.step + 1:
            loss = loss * float("nan")
        self.optimizer.zero_grad()
        loss.backward()
        grad_norm = torch.nn.utils.clip_grad_norm_(self.model.parameters(), 10.0)
        check_finite(float(loss.detach()), float(grad_norm), step=self.step + 1, run=self.out)
        self.optimizer.step()
        self.step += 1
        self.last_loss = float(loss.detach())
        self.first_loss = getattr(self, "first_loss", self.last_loss)
        return {"loss": self.last_loss, "lr": lr}

    def save_checkpoint(self) -> Path:
        from safetensors.torch import save_file

        def write(tmp):
            save_file(self.model.state_dict(), str(tmp / "model.safetensors"))
            save_optimizer(self.optimizer, tmp)

        return write_checkpoint(self.out, self.step, loop_state(self), write, keep=self.cfg.keep_checkpoints)

    def export(self) -> Path:
        self.exports += 1
        (self.out / "final.json").write_text(json.dumps({"step": self.step, "weight": float(self.model.weight.detach())}))
        return self.out / "final.json"

    def weights(self) -> list[torch.Tensor]:
        return [p.detach().clone() for p in self.model.parameters()]


def test_a_run_ends_with_its_checkpoint_and_export_and_resumes_exactly(tmp_path):
    """20 steps in one run equal 8 steps, then a resumed run to 20; the loop writes one checkpoint of
    the last step and the export, and logs to RUN/logs."""
    whole = LineTrainer(LineConfig(), tmp_path / "whole")
    assert run_loop(whole, "line") == tmp_path / "whole" / "final.json" and whole.stopped_by is None
    assert [c.name for c in list_checkpoints(tmp_path / "whole")] == ["checkpoint-000020"]
    assert json.loads((tmp_path / "whole" / "final.json").read_text())["step"] == 20
    assert any((tmp_path / "whole" / "logs").iterdir())
    assert whole.last_loss < 0.5 * whole.first_loss  # it does learn
    part = LineTrainer(LineConfig(stop_at_step=8), tmp_path / "part")
    run_loop(part, "line")
    assert part.step == 8
    resumed = LineTrainer(LineConfig(resume=True), tmp_path / "part")
    assert resumed.step == 8
    run_loop(resumed, "line")
    assert all(torch.equal(a, b) for a, b in zip(whole.weights(), resumed.weights()))


@pytest.mark.parametrize("signum, name", [(signal.SIGTERM, "SIGTERM"), (signal.SIGINT, "Ctrl-C")])
def test_a_stop_signal_finishes_the_step_then_checkpoints_and_exports(tmp_path, monkeypatch, capsys, signum, name):
    """Ctrl-C and SIGTERM alike: the step in flight finishes, the checkpoint and the export are written,
    both handlers are given back, and the command line then ends 130 / 143."""
    trainer = LineTrainer(LineConfig(max_steps=1000), tmp_path / "run")
    train_step = trainer.train_step

    def step_then_signal():
        logs = train_step()
        if trainer.step == 3:
            os.kill(os.getpid(), signum)
        return logs

    monkeypatch.setattr(trainer, "train_step", step_then_signal)
    before = {s: signal.getsignal(s) for s in (signal.SIGTERM, signal.SIGINT)}
    run_loop(trainer, "line")
    assert {s: signal.getsignal(s) for s in before} == before
    assert trainer.step == 3 and trainer.stopped_by == signum and trainer.exports == 1
    assert [c.name for c in list_checkpoints(tmp_path / "run")] == ["checkpoint-000003"]
    assert f"stopped by {name} at step 3; saving a checkpoint and the export" in capsys.readouterr().out
    with pytest.raises(KeyboardInterrupt if signum == signal.SIGINT else Terminated):
        raise_for_stop(trainer.stopped_by)


def test_a_non_finite_loss_stops_before_the_optimiser_step(tmp_path):
    """The guard: a NaN loss at step 5 raises with the step and the last good checkpoint, the weights
    are those after step 4, and nothing of step 5 is saved."""
    trainer = LineTrainer(LineConfig(ckpt_every=2), tmp_path / "run", poison_at=5)
    after = {}
    train_step = trainer.train_step

    def record():
        logs = train_step()
        after[trainer.step] = trainer.weights()
        return logs

    trainer.train_step = record
    with pytest.raises(UserError, match=r"diverged at step 5: loss nan.*checkpoint-000004.*lower --lr"):
        run_loop(trainer, "line")
    assert trainer.step == 4 and all(torch.equal(a, b) for a, b in zip(after[4], trainer.weights()))
    assert [c.name for c in list_checkpoints(tmp_path / "run")] == ["checkpoint-000002", "checkpoint-000004"]
    with pytest.raises(UserError, match="loss 1.0, gradient norm inf"):
        check_finite(1.0, math.inf, step=1, run=tmp_path / "run")


def test_checkpoints_rotate_and_resume_falls_back_to_the_newest_intact_one(tmp_path, capsys):
    run = tmp_path / "run"
    run_loop(LineTrainer(LineConfig(max_steps=9, ckpt_every=2, keep_checkpoints=3), run), "line")
    assert [c.name for c in list_checkpoints(run)] == ["checkpoint-000006", "checkpoint-000008", "checkpoint-000009"]
    newest = run / "checkpoint-000009" / "model.safetensors"
    newest.write_bytes(newest.read_bytes()[:40])  # written by this test, inside its tmp_path
    resumed = LineTrainer(LineConfig(max_steps=9, resume=True), run)
    assert resumed.step == 8
    said = capsys.readouterr().out
    assert "checkpoint-000009 is damaged" in said and "resuming from checkpoint-000008" in said
    for ckpt in list_checkpoints(run):
        (ckpt / "model.safetensors").write_bytes(b"")
    with pytest.raises(UserError, match="every checkpoint .* is damaged"):
        LineTrainer(LineConfig(resume=True), run)
    with pytest.raises(UserError, match="no checkpoint"):
        LineTrainer(LineConfig(resume=True), tmp_path / "empty")


def test_max_steps_auto_fits_the_schedule_and_a_resume_keeps_it(tmp_path, monkeypatch, capsys):
    """--max-steps auto: after the probe (1 untimed, 2 timed steps at 1 step/s) the schedule ends when
    the 0.5 minutes do; the fit is recorded, and a resumed auto run goes on along it."""
    short_step_budget(monkeypatch, "tesseract4d.training.loop")
    fitted = 3 + int(1.0 * (30.0 - 3.0) * 0.93)
    trainer = LineTrainer(LineConfig(max_steps="auto", max_minutes=0.5), tmp_path / "run")
    run_loop(trainer, "line")
    assert f"schedule ends at step {fitted}" in capsys.readouterr().out
    assert trainer.step == trainer.cfg.max_steps == fitted
    state = json.loads((list_checkpoints(tmp_path / "run")[-1] / "trainer_state.json").read_text())
    assert state["max_steps"] == fitted and state["max_steps_fit"]["steps_per_s"] == pytest.approx(1.0)
    resumed = LineTrainer(LineConfig(max_steps="auto", resume=True), tmp_path / "run")
    assert resumed.cfg.max_steps == fitted and resumed.cfg.max_steps_fit == state["max_steps_fit"]


def test_every_loop_option_has_a_default_and_one_line_help():
    """The command line derives its flags from the config dataclasses: each field of the loop's config
    and of every trainer's has a default and a one-line help."""
    from tesseract4d.model.autoencoder_trainer import AutoencoderTrainConfig
    from tesseract4d.model.reflow import ReflowConfig
    from tesseract4d.model.trainer import TrainConfig
    from tesseract4d.policy.idm_trainer import IDMTrainConfig

    for config in (TrainingLoopConfig, TrainConfig, ReflowConfig, AutoencoderTrainConfig, IDMTrainConfig):
        assert issubclass(config, TrainingLoopConfig)
        config()  # every field has a default
        for f in dataclasses.fields(config):
            text = f.metadata.get("help")
            assert text and "\n" not in text and not text.endswith("."), (config.__name__, f.name)
    assert AutoencoderTrainConfig().max_steps == 20000 and IDMTrainConfig().max_steps == 2000
    assert ReflowConfig().max_steps == 1000 and TrainConfig().max_steps == 5000


# --------------------------------------------------------------------------- the four trainers


def _idm_dataset(root: Path) -> Path:
    """Synthetic episodes with actions and joint positions (frame k at step 2k), for the IDM."""
    df.init_dataset(root, df.DatasetInfo(height=32, width=32, cameras=["close"]))
    for seed in range(3):
        ep = synthetic_episode(seed)
        rng = np.random.default_rng(seed)
        df.write_episode(root, dataclasses.replace(
            ep, frame_steps=np.arange(ep.num_frames, dtype=np.int32) * 2,
            actions=rng.normal(size=(2 * ep.num_frames - 1, 8)).astype(np.float32),
            qpos=rng.normal(size=(ep.num_frames, 9)).astype(np.float32), control_mode="pd_joint_pos"))
    return root


def _diffusion(tmp_path, resume=False):
    from tesseract4d.model.trainer import TrainConfig, Trainer

    data = tmp_path / "data"
    if not data.exists():
        write_synthetic_dataset(data, episodes=2)
    return Trainer(TrainConfig(data=data, out=tmp_path / "run", preset=MICRO.name, max_steps=100, val_every=0,
                               ckpt_every=0, quiet=True, resume=resume)), tmp_path / "run" / "final"


def _reflow(tmp_path, resume=False, micro_checkpoint=None):
    from tesseract4d.model.reflow import PairsConfig, ReflowConfig, ReflowTrainer, generate_pairs

    pairs = tmp_path / "pairs"
    if not pairs.exists():
        data = write_synthetic_dataset(tmp_path / "data", episodes=2)
        generate_pairs(PairsConfig(teacher=micro_checkpoint, data=data, out=pairs, num_pairs=4, shard_size=4,
                                   teacher_steps=1), progress=False)
    return ReflowTrainer(ReflowConfig(data=pairs, out=tmp_path / "run", teacher=micro_checkpoint, max_steps=100,
                                      batch_size=2, val_every=0, ckpt_every=0, quiet=True, resume=resume)), \
        tmp_path / "run" / "final"


def _autoencoder(tmp_path, resume=False):
    from tesseract4d.model.autoencoder_trainer import AutoencoderTrainConfig, AutoencoderTrainer

    data = tmp_path / "data"
    if not data.exists():
        write_segmented_dataset(data, episodes=1)
    return AutoencoderTrainer(AutoencoderTrainConfig(data=data, out=tmp_path / "run", preset="ae-test", max_steps=100,
                                                     batch_size=2, precision="fp32", quiet=True, resume=resume)), \
        tmp_path / "run" / "autoencoder"


def _idm(tmp_path, resume=False, text_encoder=None):
    from tesseract4d.policy.idm_trainer import IDMTrainConfig, IDMTrainer

    data = tmp_path / "data"
    if not data.exists():
        _idm_dataset(data)
    return IDMTrainer(IDMTrainConfig(data=str(data), out=str(tmp_path / "run"), max_steps=100, batch_size=4,
                                     num_points=32, ckpt_every=0, quiet=True, resume=resume),
                      text_encoder=text_encoder), tmp_path / "run" / "final"


@pytest.fixture(scope="module")
def minilm():
    from tesseract4d.model.text_encoder import TextEncoder

    return TextEncoder("minilm", max_tokens=32)


@pytest.mark.parametrize("kind", ["diffusion", "reflow", "autoencoder", "idm"])
def test_every_trainer_stops_on_sigterm_after_its_step_and_resumes_there(kind, tmp_path, monkeypatch, capsys,
                                                                         micro_checkpoint, minilm):
    """The same semantics in all four: SIGTERM during step 2 of 100 finishes the step, writes
    checkpoint-000002 and the export, says so, names the signal for the exit status (143); --resume
    continues at step 2 from that checkpoint."""
    build = {"diffusion": _diffusion, "autoencoder": _autoencoder,
             "reflow": lambda p, resume=False: _reflow(p, resume, micro_checkpoint),
             "idm": lambda p, resume=False: _idm(p, resume, minilm)}[kind]
    trainer, export = build(tmp_path)
    sigterm_after_step(monkeypatch, trainer, 2)
    trainer.train()
    assert trainer.step == 2 and trainer.stopped_by == signal.SIGTERM
    assert [c.name for c in list_checkpoints(tmp_path / "run")] == ["checkpoint-000002"]
    assert export.is_dir() and any(export.iterdir())
    assert "stopped by SIGTERM at step 2; saving a checkpoint and the export" in capsys.readouterr().out
    assert (tmp_path / "run" / "logs").is_dir()
    resumed, _ = build(tmp_path, resume=True)
    assert resumed.step == 2
