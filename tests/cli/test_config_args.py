"""Flags derived from config dataclasses (tesseract4d/configs.py, tesseract4d/cli/config_args.py): each
option written once, as a field with its default and help; ``--set`` typed from the field; recipes under
flags; old spellings that still work with one deprecation line."""

from __future__ import annotations

import argparse
from dataclasses import dataclass, field
from pathlib import Path

import pytest

from tesseract4d.cli.config_args import (
    add_deprecated, add_field_flags, add_recipe_options, add_set_option, config_from_args, recipe_from_args,
)
from tesseract4d.configs import knob, parse_field_value, with_overrides
from tesseract4d.errors import UserError


@dataclass
class Inner:
    height: int = knob(128, "image height")
    cameras: list[str] = knob(help="camera presets", default_factory=lambda: ["close"])


@dataclass
class Options:
    data: list[Path] | None = knob(None, "dataset folders")
    out: Path = knob(Path("runs/x"), "run folder")
    lr: float | None = knob(None, "peak learning rate")
    max_steps: int | str = knob(5000, "optimiser steps, or auto")
    group_batches: bool = knob(False, "batches of whole groups")
    progress: bool = knob(True, "progress bars")
    weights: dict[str, float] = knob(help="loss weights", default_factory=lambda: {"rgb": 1.0})
    precision: str = knob("auto", "precision", choices=("auto", "fp32", "bf16"))
    inner: Inner = field(default_factory=Inner)


RECIPES = {"fast": {"lr": 3e-4, "max_steps": 100, "group_batches": True}}


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="t")
    add_field_flags(p, Options, ["data", "out", "lr", "max_steps", "group_batches", "progress"],
                    flags={"progress": "--quiet"})
    add_set_option(p, Options)
    add_recipe_options(p, RECIPES)
    add_deprecated(p, "--no-progress", use="--quiet", dest="progress", switch=False)
    add_deprecated(p, "--learning-rate", use="--set lr=VALUE", set_field="lr", config_class=Options, type=float)
    return p


def _config(argv, **kw) -> Options:
    args = _parser().parse_args(argv)
    return config_from_args(Options, args, ["data", "out", "lr", "max_steps", "group_batches", "progress"],
                            recipe=recipe_from_args(args, RECIPES, lambda path: {"lr": 7e-4}), **kw)


def test_flags_carry_the_fields_help_and_default():
    text = " ".join(_parser().format_help().split())
    assert "--lr LR peak learning rate" in text
    assert "--max-steps N|auto optimiser steps, or auto (default 5000)" in text
    assert "--group-batches batches of whole groups" in text and "--quiet progress bars" in text
    assert "--no-progress" not in text and "--learning-rate" not in text  # old spellings hidden


def test_defaults_recipe_set_and_flags_stack_in_that_order():
    assert _config([]) == Options()
    assert (_config(["--recipe", "fast"]).lr, _config(["--recipe", "fast"]).max_steps) == (3e-4, 100)
    cfg = _config(["--recipe", "fast", "--set", "lr=1e-3", "--max-steps", "auto", "--quiet"])
    assert (cfg.lr, cfg.max_steps, cfg.group_batches, cfg.progress) == (1e-3, "auto", True, False)
    assert _config(["--recipe", "fast", "--set", "lr=1e-3", "--lr", "2e-3"]).lr == 2e-3
    assert _config(["--recipe-from", "ckpt"]).lr == 7e-4
    assert _config(["--data", "a", "b"]).data == [Path("a"), Path("b")]


def test_set_types_every_kind_of_field():
    cfg = _config(["--set", "weights=rgb=2,depth=0.5", "--set", "height=64", "--set", "inner.cameras=close,side",
                   "--set", "data=none", "--set", "precision=bf16", "--set", "group_batches=yes"])
    assert cfg.weights == {"rgb": 2.0, "depth": 0.5} and cfg.inner == Inner(64, ["close", "side"])
    assert cfg.data is None and cfg.precision == "bf16" and cfg.group_batches is True


@pytest.mark.parametrize("argv, said", [
    (["--set", "lrr=1"], "--set lrr: no such option; valid names: cameras, data, group_batches, height, lr,"),
    (["--set", "lr=fast"], "--set lr=fast: expected float or none"),
    (["--set", "lr=nan"], "--set lr=nan: expected float or none"),
    (["--set", "precision=fp16"], "--set precision=fp16: choose one of auto, fp32, bf16"),
    (["--set", "lr"], "--set takes NAME=VALUE"),
    (["--recipe", "slow"], "argument --recipe: invalid choice: 'slow'"),
])
def test_bad_overrides_end_at_parse_time_with_the_fix(argv, said, capsys):
    with pytest.raises(SystemExit) as ended:
        _parser().parse_args(argv)
    assert ended.value.code == 2 and said in capsys.readouterr().err


def test_set_list_prints_the_fields(capsys):
    with pytest.raises(SystemExit) as ended:
        _parser().parse_args(["--set", "list"])
    out = capsys.readouterr().out
    assert ended.value.code == 0 and "lr = None  (float or none)  peak learning rate" in out and "height = 128" in out


def test_old_spellings_work_with_one_deprecation_line(capsys):
    cfg = _config(["--no-progress", "--learning-rate", "5e-4"])
    assert (cfg.progress, cfg.lr) == (False, 5e-4)
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["tesseract4d: --no-progress is deprecated and goes away in the next release; use --quiet",
                   "tesseract4d: --learning-rate is deprecated and goes away in the next release; use --set lr=VALUE"]


def test_with_overrides_refuses_unknown_names_and_bad_text():
    with pytest.raises(UserError, match="valid names: .*max_steps"):
        with_overrides(Options(), {"max_step": 3})
    with pytest.raises(UserError, match="expected int"):
        parse_field_value(Inner, "height", "tall")
    assert parse_field_value(Options, "max_steps", "12") == 12 and parse_field_value(Options, "max_steps", "auto") == "auto"
