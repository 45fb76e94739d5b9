"""The trainers' learning-rate schedule and `--max-steps auto` (fitting it to a time budget)."""

from __future__ import annotations

import argparse
from types import SimpleNamespace

import pytest

from tesseract4d.errors import UserError
from tesseract4d.training.schedule import (
    AUTO, StepBudget, check_max_steps, lr_at, max_steps_argument, resumed_max_steps)


class FakeClock:
    """A clock that only moves when told to."""

    def __init__(self):
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


def test_lr_warms_up_then_decays_along_the_cosine_to_its_floor():
    cfg = SimpleNamespace(lr=1.0, warmup_steps=4, max_steps=104, min_lr_ratio=0.1)
    assert [lr_at(s, cfg) for s in range(4)] == [0.25, 0.5, 0.75, 1.0]
    assert lr_at(4, cfg) == pytest.approx(1.0)
    assert lr_at(54, cfg) == pytest.approx(0.55)  # half-way down the cosine
    assert lr_at(104, cfg) == pytest.approx(0.1) and lr_at(500, cfg) == pytest.approx(0.1)
    lrs = [lr_at(s, cfg) for s in range(4, 105)]
    assert all(a >= b for a, b in zip(lrs, lrs[1:]))
    # Before "auto" is fitted the warm-up is the same and the decay has not begun.
    unfitted = SimpleNamespace(lr=1.0, warmup_steps=4, max_steps=AUTO, min_lr_ratio=0.1)
    assert [lr_at(s, unfitted) for s in range(4)] == [0.25, 0.5, 0.75, 1.0]
    assert lr_at(1000, unfitted) == pytest.approx(1.0, abs=1e-9)


def test_step_budget_fits_the_schedule_to_the_time_left():
    clock = FakeClock()
    budget = StepBudget(10.0, first_step=50, skip_steps=2, timed_steps=4, margin=0.9, clock=clock)
    fitted = []
    for step in range(51, 60):
        clock.now += 3.0 if step <= 52 else 0.5  # two slow first steps, then 2 steps/s
        fitted.append(budget.after_step(step))
    # Timed from step 52 to step 56: 4 steps in 2 s; the time left is counted from the budget's start.
    elapsed = 3.0 * 2 + 0.5 * 4
    expected = 56 + int(2.0 * (600.0 - elapsed) * 0.9)
    assert fitted == [None] * 5 + [expected] + [None] * 3  # once, right after the last timed step
    assert budget.rate == pytest.approx(2.0) and budget.fitted == expected
    assert budget.record() == {"steps_per_s": 2.0, "timed_steps": 4, "max_minutes": 10.0, "margin": 0.9,
                               "max_steps": expected}
    assert str(expected) in budget.describe() and "steps/s" in budget.describe()


def test_step_budget_plans_at_least_one_more_step_when_the_time_is_spent():
    clock = FakeClock()
    budget = StepBudget(0.01, first_step=0, skip_steps=0, timed_steps=1, clock=clock)
    clock.now += 60.0
    assert budget.after_step(1) == 2


def test_max_steps_argument_and_checks():
    assert max_steps_argument("auto") == AUTO and max_steps_argument(" AUTO ") == AUTO
    assert max_steps_argument("300") == 300
    with pytest.raises(argparse.ArgumentTypeError, match="whole number of steps or 'auto'"):
        max_steps_argument("lots")
    check_max_steps(300, None)
    check_max_steps(AUTO, 8.0)
    check_max_steps(AUTO, None, resume=True)  # a resumed run goes on along its recorded schedule
    with pytest.raises(UserError, match="--max-minutes"):
        check_max_steps(AUTO, None)
    with pytest.raises(UserError, match="--stop-at-step"):
        check_max_steps(AUTO, 8.0, stop_at_step=10)
    for bad in (0, -1, 2.5, True):
        with pytest.raises(UserError, match="--max-steps"):
            check_max_steps(bad, None)


def test_a_resumed_auto_run_takes_its_recorded_schedule():
    assert resumed_max_steps(AUTO, 1234, None) == 1234
    assert resumed_max_steps(500, 1234, None) == 500  # a number given on the resume wins
    assert resumed_max_steps(AUTO, AUTO, 5.0) == AUTO  # saved before its probe ended: fitted again
    with pytest.raises(UserError, match="no fitted schedule"):
        resumed_max_steps(AUTO, AUTO, None)
