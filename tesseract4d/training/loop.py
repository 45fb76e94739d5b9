"""The training loop every trainer plugs into: the trainer supplies its step and its export, the loop the rest.

A trainer (``model/trainer.py``, ``model/reflow.py``, ``model/autoencoder_trainer.py``,
``policy/idm_trainer.py``) has ``cfg`` (a ``TrainingLoopConfig``), ``out`` (its run folder), ``step``, and:

- ``train_step() -> dict``: one optimiser step at ``learning_rate(trainer)``, its logs (with ``loss``);
  it calls :func:`check_finite` before the optimiser step;
- ``save_checkpoint() -> Path``: the checkpoint of the current step (``checkpoints.write_checkpoint``);
- ``export()``: what the run delivers (an inference checkpoint, an autoencoder, an IDM), returned by
  :func:`run_loop`;

and optionally ``after_step() -> dict`` (validation logs), ``write_config()`` (called when ``--max-steps
auto`` has fitted the schedule), ``agree_max_steps(n) -> int`` (processes of a distributed run agree
on the fitted schedule), ``is_main_process`` and ``elapsed_s``.

The loop stops at ``max_steps`` (or ``stop_at_step``), after ``max_minutes``, or on Ctrl-C / SIGTERM
(tesseract4d/stopping.py): the current step finishes, then the checkpoint and the export are written
(a second signal meanwhile changes nothing) and ``trainer.stopped_by`` names the signal, so the command
ends 130 / 143 with ``raise_for_stop``. It logs every step's scalars to TensorBoard (RUN/logs) and
shows one progress bar (none with ``quiet``).
"""

from __future__ import annotations

import json
import math
import signal
import time
from pathlib import Path

from tesseract4d.dataset_format import atomic_write_text
from tesseract4d.errors import UserError
from tesseract4d.stopping import StopSignals
from tesseract4d.training.checkpoints import checkpoint_dir, list_checkpoints
from tesseract4d.training.schedule import AUTO, UNFITTED_MAX_STEPS, StepBudget, lr_at, resumed_max_steps

LOG_DIR = "logs"
SIGNAL_NAMES = {signal.SIGTERM: "SIGTERM", signal.SIGINT: "Ctrl-C"}


def learning_rate(trainer) -> float:
    """The learning rate of the trainer's next step (warm-up, then the cosine to ``max_steps``)."""
    return lr_at(trainer.step, trainer.cfg)


def set_learning_rate(optimizer, lr: float) -> None:
    for group in optimizer.param_groups:
        group["lr"] = lr


def check_finite(loss: float, grad_norm: float, *, step: int, run: Path) -> None:
    """The non-finite-loss guard, called between the backward pass and the optimiser step: a NaN or
    infinite loss or gradient norm stops the run before it touches the weights, so they and the
    checkpoints on disk stay good. ``step``: the step being taken (1-based)."""
    if math.isfinite(float(loss)) and math.isfinite(float(grad_norm)):
        return
    last = list_checkpoints(run)
    raise UserError(f"training diverged at step {step}: loss {float(loss)}, gradient norm {float(grad_norm)}; "
                    f"nothing was saved from this step (last good checkpoint: {last[-1] if last else 'none'}); "
                    f"lower --lr, or check the data and the loss weights")


class RunLog:
    """The run's TensorBoard scalars (RUN/logs, main process only) and its one-line messages, which
    go above the progress bar."""

    def __init__(self, out: Path, main: bool, bar=None):
        self.writer = None
        if main:
            from torch.utils.tensorboard import SummaryWriter  # lazy: pulls TensorBoard in

            self.writer = SummaryWriter(str(Path(out) / LOG_DIR))
        self.bar = bar

    def scalars(self, logs: dict, step: int) -> None:
        if self.writer is None:
            return
        for name, value in logs.items():
            if isinstance(value, (int, float)) and not isinstance(value, bool):
                self.writer.add_scalar(name if "/" in name else f"train/{name}", value, step)

    def say(self, text: str) -> None:
        (self.bar.write if self.bar is not None else print)(text)

    def close(self) -> None:
        if self.writer is not None:
            self.writer.close()


def run_loop(trainer, desc: str):
    """Train ``trainer`` until its config says stop (or a signal does); always end with its checkpoint of
    the last step and its export, and return the export. Sets ``trainer.stopped_by`` (None, or the signal)."""
    from tqdm import tqdm

    cfg = trainer.cfg
    main = getattr(trainer, "is_main_process", True)
    start, start_step = time.monotonic(), trainer.step
    elapsed_before = getattr(trainer, "elapsed_s", 0.0)
    # "auto": the cosine is fitted to max_minutes after the first steps (the config says "auto" until then).
    budget = StepBudget(cfg.max_minutes, trainer.step) if cfg.max_steps == AUTO else None
    last_step = UNFITTED_MAX_STEPS if budget else cfg.max_steps if cfg.stop_at_step is None else cfg.stop_at_step
    bar = tqdm(total=None if budget else cfg.max_steps, initial=trainer.step, desc=desc, unit="step",
               disable=cfg.quiet or not main, dynamic_ncols=True)
    log = trainer.run_log = RunLog(trainer.out, main, bar)
    smooth = None
    try:
        with StopSignals() as stop:
            try:
                while trainer.step < last_step and not stop.requested:
                    logs = trainer.train_step()
                    if budget is not None and budget.after_step(trainer.step) is not None:
                        agree = getattr(trainer, "agree_max_steps", lambda n: n)
                        budget.fitted = cfg.max_steps = last_step = agree(budget.fitted)
                        cfg.max_steps_fit = budget.record()
                        bar.total = cfg.max_steps
                        log.say(budget.describe())
                        if hasattr(trainer, "write_config"):
                            trainer.write_config()
                    trainer.elapsed_s = elapsed_before + time.monotonic() - start
                    smooth = logs["loss"] if smooth is None else 0.95 * smooth + 0.05 * logs["loss"]
                    rate = (trainer.step - start_step) / max(1e-6, time.monotonic() - start)
                    bar.update(1)
                    bar.set_postfix(loss=f"{smooth:.4f}", steps_per_s=f"{rate:.2f}", refresh=False)
                    log.scalars({**logs, "steps_per_s": rate}, trainer.step)
                    if hasattr(trainer, "after_step"):
                        log.scalars(trainer.after_step() or {}, trainer.step)
                    if cfg.ckpt_every and trainer.step % cfg.ckpt_every == 0:
                        trainer.save_checkpoint()
                    if cfg.max_minutes is not None and time.monotonic() - start >= cfg.max_minutes * 60:
                        log.say(f"stopping after {cfg.max_minutes:g} min at step {trainer.step}")
                        break
            finally:
                bar.close()
                log.bar = None
            if stop.requested:
                print(f"stopped by {SIGNAL_NAMES.get(stop.signum, stop.signum)} at step {trainer.step}; "
                      f"saving a checkpoint and the export", flush=True)
            saved = list_checkpoints(trainer.out)
            if not saved or saved[-1] != checkpoint_dir(trainer.out, trainer.step):
                trainer.save_checkpoint()
            result = trainer.export()
        trainer.stopped_by = stop.signum
        return result
    finally:
        log.close()


def loop_state(trainer) -> dict:
    """What every checkpoint's STATE_FILE records of the loop (a trainer adds its own)."""
    return {"step": trainer.step, "elapsed_s": getattr(trainer, "elapsed_s", 0.0),
            "last_loss": getattr(trainer, "last_loss", None), "max_steps": trainer.cfg.max_steps,
            "max_steps_fit": trainer.cfg.max_steps_fit}


def restore_loop_state(trainer, state: dict) -> None:
    """Put a checkpoint's loop state back: its step, time and last loss, and with ``--max-steps auto``
    (or a checkpoint of a fitted run) the schedule the run was on (``schedule.resumed_max_steps``)."""
    cfg = trainer.cfg
    saved_steps = state.get("max_steps", (state.get("config") or {}).get("max_steps"))
    saved_fit = state.get("max_steps_fit", (state.get("config") or {}).get("max_steps_fit"))
    requested = cfg.max_steps
    cfg.max_steps = resumed_max_steps(requested, saved_steps, cfg.max_minutes)
    if requested == AUTO and cfg.max_steps != AUTO:  # the schedule of the run, and how it was fitted
        cfg.max_steps_fit = saved_fit
    trainer.step = int(state["step"])
    trainer.elapsed_s = float(state.get("elapsed_s", 0.0))
    trainer.last_loss = state.get("last_loss")


def write_config_file(path: Path, config) -> None:
    """A run's resolved config as JSON (written whole)."""
    atomic_write_text(Path(path), json.dumps(config.to_dict(), indent=2))
