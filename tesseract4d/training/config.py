"""The training loop's options, once: every trainer's config extends ``TrainingLoopConfig``.

Each field carries its default and a one-line help (``metadata["help"]``), from which the command
line derives its flags. A trainer may give a field another default by declaring it again (the
autoencoder trains 20,000 steps by default, the IDM 2,000); ``None`` for ``lr`` and ``warmup_steps``
means "the model preset's" where a trainer has presets.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from tesseract4d.configs import config_dict, knob
from tesseract4d.errors import UserError
from tesseract4d.training.schedule import AUTO, check_max_steps


def option(default, help: str, *, default_factory=None, internal: bool = False):
    """A config field with its default (or ``default_factory``) and its one-line ``--help`` text;
    ``internal``: set by the program, not an option a user gives."""
    extra = {"internal": True} if internal else {}
    if default_factory is not None:
        return knob(help=help, default_factory=default_factory, **extra)
    return knob(default, help, **extra)


@dataclass
class TrainingLoopConfig:
    """Options of the loop that every trainer shares (``training/loop.py``)."""

    max_steps: int | str = option(5000, "optimiser steps; the cosine learning-rate decay ends here; 'auto' (with "
                                        "max_minutes) fits it to the time budget from the first steps' rate")
    max_minutes: float | None = option(None, "stop with a checkpoint and the export after this many minutes of "
                                             "this invocation")
    stop_at_step: int | None = option(None, "stop with a checkpoint at this step while the learning-rate schedule "
                                            "still ends at max_steps (resume goes on from there)")
    ckpt_every: int = option(500, "write a checkpoint every N optimiser steps (0: only at the end)")
    keep_checkpoints: int = option(2, "checkpoints kept in the run folder, the newest ones")
    lr: float | None = option(None, "peak learning rate")
    warmup_steps: int | None = option(None, "linear learning-rate warm-up steps")
    min_lr_ratio: float = option(0.1, "the learning rate at max_steps, as a share of the peak")
    seed: int = option(0, "seed of everything the run draws (a resumed run draws what it would have)")
    resume: bool = option(False, "continue the run in the output folder from its newest intact checkpoint")
    quiet: bool = option(False, "no progress bars")
    max_steps_fit: dict | None = option(None, "set by the loop: how max_steps 'auto' was fitted", internal=True)

    def to_dict(self) -> dict:
        return config_dict(self)

    def check_loop(self) -> None:
        """One-line UserErrors for loop options that cannot run (call on the resolved config, before
        anything is written)."""
        check_max_steps(self.max_steps, self.max_minutes, self.stop_at_step, resume=self.resume)
        if self.lr is not None and not (math.isfinite(self.lr) and self.lr > 0):
            raise UserError(f"--lr must be a finite number > 0, got {self.lr}")
        if self.warmup_steps is not None and self.warmup_steps < 0:
            raise UserError(f"--warmup-steps must be >= 0, got {self.warmup_steps}")
        if not (math.isfinite(self.min_lr_ratio) and 0 <= self.min_lr_ratio <= 1):
            raise UserError(f"--set min_lr_ratio=R must be between 0 and 1, got {self.min_lr_ratio}")
        if self.max_minutes is not None and not (math.isfinite(self.max_minutes) and self.max_minutes >= 0):
            raise UserError(f"--max-minutes must be a finite number >= 0, got {self.max_minutes}")
        if self.stop_at_step is not None and self.max_steps != AUTO and not 1 <= self.stop_at_step <= self.max_steps:
            raise UserError(f"--stop-at-step must be between 1 and --max-steps ({self.max_steps}), got {self.stop_at_step}")
        if self.ckpt_every < 0:
            raise UserError(f"--ckpt-every must be >= 0 (0: only at the end), got {self.ckpt_every}")
        if self.keep_checkpoints < 1:
            raise UserError(f"--set keep_checkpoints=N must be at least 1, got {self.keep_checkpoints}")
