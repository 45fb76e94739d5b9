"""Export a training run's latest EMA weights as an inference checkpoint folder.

  tesseract4d checkpoint export runs/tiny --to checkpoints/mine        # default RUN/final
  tesseract4d checkpoint export runs/v2 --to checkpoints/v2 --half      # float16, half the size

Every `tesseract4d train` run already ends with this export to RUN/final; use it for a run that was
killed, or to write the weights elsewhere or in float16.
"""

from __future__ import annotations

import argparse
from pathlib import Path


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("run", type=Path, metavar="RUN", help="run folder of `tesseract4d train` (its --out)")
    add_export_options(parser)


def add_export_options(parser: argparse.ArgumentParser, hidden: bool = False) -> None:
    """--to, --overwrite, --half (hidden where `train --export` keeps them for one release)."""
    def say(text: str) -> str:
        return argparse.SUPPRESS if hidden else text

    parser.add_argument("--to", type=Path, help=say("the inference folder to write (default RUN/final)"))
    parser.add_argument("--overwrite", action="store_true",
                        help=say("write into a folder holding other files (only the export's files are replaced)"))
    parser.add_argument("--half", action="store_true",
                        help=say("store the weights (and a latent model's autoencoder) in float16, half the size"))


def export(run_folder: Path, to: Path | None, overwrite: bool, half: bool) -> int:
    from tesseract4d.model.trainer import export_checkpoint

    folder = export_checkpoint(run_folder, to, overwrite=overwrite, half=half)
    print(f"exported {folder}")
    return 0


def run(args: argparse.Namespace) -> int:
    return export(args.run, args.to, args.overwrite, args.half)
