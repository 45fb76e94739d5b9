"""The console entry point: help for every subcommand, clear errors for unknown ones."""

from __future__ import annotations

import importlib
import subprocess
import sys

import pytest

from tesseract4d.cli import SUBCOMMANDS, main


def test_top_level_help_lists_every_subcommand(capsys):
    assert main(["--help"]) == 0
    out = capsys.readouterr().out
    for name in SUBCOMMANDS:
        assert name in out


def test_unknown_subcommand_fails_with_the_valid_ones(capsys):
    assert main(["frobnicate"]) == 2
    err = capsys.readouterr().err
    assert "unknown subcommand 'frobnicate'" in err and "datagen" in err


@pytest.mark.parametrize("name", sorted(SUBCOMMANDS))
def test_subcommand_help(name):
    # A subprocess, as a user runs it: the console script must exist and --help must exit 0.
    proc = subprocess.run(
        [sys.executable, "-m", "tesseract4d.cli", name, "--help"], capture_output=True, text=True, timeout=120
    )
    assert proc.returncode == 0, proc.stderr
    assert f"tesseract4d {name}" in proc.stdout


def test_import_is_light():
    code = "import sys, tesseract4d, tesseract4d.cli, tesseract4d.dataset_format, tesseract4d.geometry; " \
           "heavy = [m for m in ('torch', 'diffusers', 'mani_skill', 'open3d', 'viser', 'ray') if m in sys.modules]; " \
           "print(','.join(heavy))"
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip() == "", f"heavy modules imported at package import: {proc.stdout}"


@pytest.mark.parametrize("name, argv", [("predict", []), ("demo", []), ("evaluate", ["--heldout", "data"]), ("view", ["recon"])])
def test_model_defaults_come_from_the_shipped_checkpoint(name, argv):
    # One source for the defaults: the shipped checkpoint, and its preset's sampler steps and frames
    # (None here, resolved from the checkpoint when it is loaded).
    import argparse

    from tesseract4d.model.checkpoint import SHIPPED_CHECKPOINT

    parser = argparse.ArgumentParser()
    importlib.import_module(f"tesseract4d.cli.{name}").add_arguments(parser)
    args = parser.parse_args(argv)
    assert args.checkpoint == SHIPPED_CHECKPOINT
    assert getattr(args, "steps", None) is None and getattr(args, "num_frames", None) is None
