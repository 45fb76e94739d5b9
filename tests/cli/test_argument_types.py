"""The shared argument types (tesseract4d/cli/argument_types.py): bad numbers end at parse time."""

from __future__ import annotations

import argparse

import pytest

from tesseract4d.cli.argument_types import MAX_SEED, number, probability, seed, whole


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="t")
    p.add_argument("--steps", type=whole(1))
    p.add_argument("--frac", type=whole(0, 10, hint=" (0 = off)"))
    p.add_argument("--scale", type=number(0))
    p.add_argument("--rate", type=number(0, above=True))
    p.add_argument("--seed", type=seed())
    p.add_argument("--share", type=probability())
    return p


def test_good_values_parse_to_their_numbers():
    a = _parser().parse_args(["--steps", "3", "--frac", "10", "--scale", "0", "--rate", "1e-4", "--seed", str(MAX_SEED)])
    assert (a.steps, a.frac, a.scale, a.rate, a.seed) == (3, 10, 0.0, 1e-4, MAX_SEED)


@pytest.mark.parametrize("argv, said", [
    (["--steps", "0"], "--steps: must be a whole number >= 1, got '0'"),
    (["--steps", "2.5"], "--steps: must be a whole number >= 1"),
    (["--frac", "11"], "--frac: must be a whole number in 0..10 (0 = off), got '11'"),
    (["--scale", "-1"], "--scale: must be a finite number >= 0, got '-1'"),
    (["--scale", "nan"], "--scale: must be a finite number >= 0"),
    (["--rate", "0"], "--rate: must be a finite number > 0"),
    (["--share", "1.5"], "--share: must be a finite number >= 0 and <= 1, got '1.5'"),
    (["--seed", "-5"], f"--seed: must be a whole number in 0..{MAX_SEED}, got '-5'"),
])
def test_bad_values_end_with_the_rule_and_the_value(argv, said, capsys):
    with pytest.raises(SystemExit) as ended:
        _parser().parse_args(argv)
    assert ended.value.code == 2 and said in capsys.readouterr().err
