"""The command line's surface (issue 63): few flags, one vocabulary, old spellings deprecated not broken.

The flag count is the one a user sees: the distinct ``--long`` options each subcommand's ``--help``
lists (``--help`` itself not counted), summed over every subcommand, the members of the
``checkpoint`` and ``research`` groups and nested subcommands (``dataset info``) included.
"""

from __future__ import annotations

import argparse
import re
from pathlib import Path

import pytest

from tesseract4d.cli import DEPRECATED_COMMANDS, GROUPS, HIDDEN, SUBCOMMANDS, build_parser, every_subcommand, main

MAX_FLAGS = 160
_OPTION_LINE = re.compile(r"^  (-\S.*?)(?:\s{2,}|$)")


def listed_flags(parser: argparse.ArgumentParser) -> set[str]:
    """The --long options the parser's --help lists (its option lines, not the prose)."""
    flags: set[str] = set()
    for line in parser.format_help().splitlines():
        match = _OPTION_LINE.match(line)
        if match:
            flags |= set(re.findall(r"--[a-z0-9][a-z0-9-]*", match.group(1)))
    flags.discard("--help")
    return flags


def _nested(parser: argparse.ArgumentParser):
    yield parser
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for sub in action.choices.values():
                yield from _nested(sub)


def flag_counts() -> dict[str, int]:
    counts = {}
    for words in every_subcommand():
        parser, _ = build_parser(words)
        for i, p in enumerate(_nested(parser)):
            counts[p.prog.removeprefix("tesseract4d ")] = len(listed_flags(p))
    return counts


def test_flags_over_every_subcommand_help_stay_few():
    counts = flag_counts()
    total = sum(counts.values())
    assert total <= MAX_FLAGS, f"{total} flags over every --help (at most {MAX_FLAGS}): {counts}"


def test_every_group_member_is_counted():
    counted = set(flag_counts())
    for group, members in GROUPS.items():
        assert {f"{group} {m}" for m in members} <= counted


def test_one_meaning_per_flag():
    """--steps is sampler steps, --max-steps optimiser steps, --max-sim-steps simulator steps; --quiet is
    the only progress switch and --ckpt-every the only checkpoint cadence."""
    trainers = {"train", "train-autoencoder", "distill", "train-idm"}
    for words in every_subcommand():
        name = " ".join(words)
        flags = set().union(*(listed_flags(p) for p in _nested(build_parser(words)[0])))
        assert not flags & {"--no-progress", "--ckpt-minutes", "--sample-steps"}, name
        if "--max-steps" in flags:
            assert name in trainers, name
        if name in trainers:
            assert "--steps" not in flags, name
    rollout = listed_flags(build_parser(("rollout",))[0])
    assert {"--max-sim-steps", "--steps", "--quiet"} <= rollout


def test_top_level_help_hides_research_and_old_spellings(capsys):
    assert main(["--help"]) == 0
    out = capsys.readouterr().out
    assert "checkpoint" in out
    for hidden in HIDDEN | set(DEPRECATED_COMMANDS):
        assert not re.search(rf"^\s+{hidden}\s", out, re.M), hidden


def test_no_dated_work_log_in_any_help():
    for words in every_subcommand():
        for p in _nested(build_parser(words)[0]):
            text = p.format_help()
            assert not re.search(r"\b20\d\d-\d\d-\d\d\b|\b(runs|outputs)/s\d\d|\bsession\b|results_history|"
                                 r"\bcommit [0-9a-f]{7}|README \"", text), p.prog


@pytest.mark.parametrize("old, new", sorted(DEPRECATED_COMMANDS.items()))
def test_old_subcommand_names_still_work_with_one_deprecation_line(old, new, capsys):
    with pytest.raises(SystemExit) as ended:
        main([old, "--help"])
    assert ended.value.code == 0
    captured = capsys.readouterr()
    lines = captured.err.strip().splitlines()
    assert len(lines) == 1 and "deprecated" in lines[0] and " ".join(new) in lines[0]
    assert f"tesseract4d {' '.join(new)}" in captured.out


@pytest.mark.parametrize("words, argv, dest, value", [
    (("rollout",), ["--out", "o", "--max-steps", "7"], "max_sim_steps", 7),
    (("rollout",), ["--out", "o", "--sample-steps", "3"], "steps", 3),
    (("rollout",), ["--out", "o", "--no-progress"], "quiet", True),
    (("reconstruct",), ["in", "--out", "o", "--iterations", "5"], "set_overrides", {"iterations": 5}),
    (("datagen",), ["--tasks", "PushCube-v1", "--episodes", "1", "--out", "o", "--randomize-colors"],
     "set_overrides", {"randomize_colors": True}),
    (("evaluate",), ["--heldout", "h", "--start-from-truth", "0.5"], "start_from_truth", 0.5),
    (("train-idm",), ["--data", "d", "--out", "o", "--steps", "7"], "max_steps", 7),
    (("train-idm",), ["--data", "d", "--out", "o", "--no-future"], "set_overrides", {"use_future": False}),
    (("train",), ["--out", "o", "--no-progress"], "quiet", True),
    (("train",), ["--export", "run"], "export", Path("run")),
    (("train",), ["--out", "o", "--lr", "0.1"], "set_overrides", {"lr": 0.1}),
    (("distill",), ["--teacher", "t", "--pairs", "p", "--student-steps", "4"], "set_overrides", {"student_steps": 4}),
    (("train-autoencoder",), ["--data", "d", "--out", "o", "--frame-stride", "4"], "set_overrides",
     {"frame_stride": 4}),
    (("checkpoint", "set-sampler"), ["--checkpoint", "c", "--to", "t", "--static-tolerance", "0.2"], "set_overrides",
     {"static_tolerance": 0.2}),
])
def test_old_flags_still_work_with_one_deprecation_line(words, argv, dest, value, capsys):
    args = build_parser(words)[0].parse_args(argv)
    assert getattr(args, dest) == value
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1 and "deprecated" in lines[0] and argv[-1 if argv[-1].startswith("--") else -2] in lines[0]


def test_set_is_typed_and_refuses_unknown_names_with_the_valid_ones(capsys):
    parser = build_parser(("reconstruct",))[0]
    args = parser.parse_args(["in", "--out", "o", "--set", "static_weight=3", "--set", "mesh=false",
                              "--set", "voxel_size_m=none"])
    assert args.set_overrides == {"static_weight": 3.0, "mesh": False, "voxel_size_m": None}
    with pytest.raises(SystemExit) as ended:
        parser.parse_args(["in", "--out", "o", "--set", "statik_weight=3"])
    err = capsys.readouterr().err
    assert ended.value.code == 2 and "statik_weight" in err and "static_weight" in err and "reg_weight" in err
    with pytest.raises(SystemExit) as ended:
        parser.parse_args(["in", "--out", "o", "--set", "iterations=many"])
    assert ended.value.code == 2 and "expected int" in capsys.readouterr().err


def test_set_list_prints_every_field_with_its_help(capsys):
    with pytest.raises(SystemExit) as ended:
        build_parser(("reconstruct",))[0].parse_args(["in", "--out", "o", "--set", "list"])
    out = capsys.readouterr().out
    assert ended.value.code == 0 and "flow_threshold_px = 1.0" in out and "marks a pixel dynamic" in out


def test_groups_list_their_subcommands(capsys):
    assert main(["checkpoint", "--help"]) == 0
    out = capsys.readouterr().out
    assert all(name in out for name in GROUPS["checkpoint"])
    assert main(["research"]) == 2 and "phrasings" in capsys.readouterr().err
    assert main(["checkpoint", "frobnicate"]) == 2 and "export" in capsys.readouterr().err
