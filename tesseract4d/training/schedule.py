"""The learning-rate schedule of the trainers, and fitting its length to a time budget.

Every trainer (``train``, ``distill``, ``train-autoencoder``, ``train-idm``; the loop of
``training/loop.py`` sets it before each step) warms the learning rate up linearly and then decays it
along a cosine that ends at ``max_steps``. A run that has a fixed amount of time rather than a number
of steps (a lent GPU, a fixed slot on a shared machine) should end its decay
when its time ends: ``--max-steps auto --max-minutes M`` times the invocation's first steps and then
fixes ``max_steps`` so that the cosine ends at ``M`` minutes (``StepBudget``). The fitted number is
written into the run's config and checkpoints, so ``--resume`` (with ``auto`` or without a new
``--max-steps``) goes on along the same schedule.
"""

from __future__ import annotations

import argparse
import math
import time

from tesseract4d.errors import UserError

AUTO = "auto"
# Untimed steps first (allocation, kernel selection, the first batches' caches), then timed ones.
PROBE_SKIP_STEPS = 5
PROBE_TIMED_STEPS = 20
# Share of the remaining time the fitted schedule plans for: checkpoints, validation and the final
# export take time the probe does not see; a run that still has time left at its last step ends early.
BUDGET_MARGIN = 0.93
# The schedule's length while the probe runs (max_steps still "auto"): the cosine has not begun to decay.
UNFITTED_MAX_STEPS = 10**9


def lr_factor(step: int, cfg) -> float:
    """The schedule's share of the peak rate at ``step``: linear warm-up over ``cfg.warmup_steps``, then
    cosine decay to ``cfg.min_lr_ratio`` at ``cfg.max_steps`` (``auto`` before it is fitted: no decay yet)."""
    if step < cfg.warmup_steps:
        return (step + 1) / cfg.warmup_steps
    max_steps = UNFITTED_MAX_STEPS if cfg.max_steps == AUTO else cfg.max_steps  # not fitted yet: no decay
    progress = min(1.0, (step - cfg.warmup_steps) / max(1, max_steps - cfg.warmup_steps))
    return cfg.min_lr_ratio + (1 - cfg.min_lr_ratio) * 0.5 * (1 + math.cos(math.pi * progress))


def lr_at(step: int, cfg) -> float:
    """The learning rate at ``step``: ``cfg.lr`` times the schedule's ``lr_factor``."""
    return cfg.lr * lr_factor(step, cfg)


def max_steps_argument(text: str) -> int | str:
    """argparse type of ``--max-steps``: a whole number or ``auto``."""
    if text.strip().lower() == AUTO:
        return AUTO
    try:
        return int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a whole number of steps or 'auto', got {text!r}") from None


def check_max_steps(max_steps: int | str, max_minutes: float | None, stop_at_step: int | None = None,
                    resume: bool = False) -> None:
    """One-line UserErrors for a ``--max-steps`` that cannot plan a schedule. A resumed run may leave
    the budget out: it goes on along the schedule its checkpoint records (``resumed_max_steps``)."""
    if max_steps == AUTO:
        if max_minutes is None and not resume:
            raise UserError("--max-steps auto fits the learning-rate schedule to a time budget; pass --max-minutes M "
                            "too (or a number of steps)")
        if stop_at_step is not None:
            raise UserError("--stop-at-step needs a number for --max-steps (auto fits the schedule to --max-minutes)")
        return
    if not isinstance(max_steps, int) or isinstance(max_steps, bool) or max_steps < 1:
        raise UserError(f"--max-steps must be a whole number >= 1 or 'auto', got {max_steps!r}")


def resumed_max_steps(requested: int | str, saved, max_minutes: float | None) -> int | str:
    """``max_steps`` of a resumed run: ``auto`` takes the schedule the run was on (``saved``, from its
    checkpoint), or is fitted again where the checkpoint has none (one saved before its probe ended)."""
    if requested != AUTO:
        return requested
    if isinstance(saved, int) and not isinstance(saved, bool):
        print(f"--max-steps auto: resuming the run's schedule, which ends at step {saved}", flush=True)
        return saved
    if max_minutes is None:
        raise UserError("--max-steps auto: the run's checkpoint records no fitted schedule; pass --max-minutes M "
                        "to fit one, or --max-steps N")
    return AUTO


class StepBudget:
    """Fits ``max_steps`` to what is left of ``max_minutes`` from the rate of the first steps.

    Make one when the invocation starts (before its first step) and call ``after_step(step)`` after
    each step; it returns None until the probe has timed ``timed_steps`` steps (after ``skip_steps``
    untimed ones) and then, once, the fitted ``max_steps``. ``rate`` and ``fitted`` record the result.
    """

    def __init__(self, max_minutes: float, first_step: int, *, skip_steps: int = PROBE_SKIP_STEPS,
                 timed_steps: int = PROBE_TIMED_STEPS, margin: float = BUDGET_MARGIN, clock=time.monotonic):
        if timed_steps < 1 or skip_steps < 0:
            raise ValueError("the probe needs at least one timed step")
        self.budget_s = float(max_minutes) * 60.0
        self.first_step = int(first_step)
        self.skip_steps = int(skip_steps)
        self.timed_steps = int(timed_steps)
        self.margin = float(margin)
        self.clock = clock
        self.start = clock()
        self._timed_from: float | None = None if skip_steps else self.start
        self.rate: float | None = None  # steps per second over the timed steps
        self.fitted: int | None = None

    def after_step(self, step: int) -> int | None:
        """The fitted ``max_steps`` right after the probe's last timed step; None before and after."""
        if self.fitted is not None:
            return None
        done = step - self.first_step
        now = self.clock()
        if done == self.skip_steps and self._timed_from is None:
            self._timed_from = now
        if done < self.skip_steps + self.timed_steps or self._timed_from is None:
            return None
        self.rate = self.timed_steps / max(1e-9, now - self._timed_from)
        left_s = max(0.0, self.budget_s - (now - self.start))
        self.fitted = step + max(1, int(self.rate * left_s * self.margin))
        return self.fitted

    def describe(self) -> str:
        """One line for the log: the measured rate and the schedule it gave."""
        return (f"--max-steps auto: {self.rate:.3g} steps/s over {self.timed_steps} timed steps; the learning-rate "
                f"schedule ends at step {self.fitted}, about {self.budget_s / 60:g} min after the start "
                f"({self.margin:.0%} of the time left planned for steps)")

    def record(self) -> dict:
        """What the fit measured, for the run's config."""
        return {"steps_per_s": self.rate, "timed_steps": self.timed_steps, "max_minutes": self.budget_s / 60,
                "margin": self.margin, "max_steps": self.fitted}


__all__ = ["AUTO", "StepBudget", "check_max_steps", "lr_at", "lr_factor", "max_steps_argument", "resumed_max_steps"]
