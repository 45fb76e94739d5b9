"""A diagnostic of the project's research, not a way to use a model: held-out evaluation in which
every checkpoint's sampler starts from the episode's true future (through its codec) noised to its
first noise level <= SIGMA, with the scene's noise, and runs only the steps from there. It measures
how much of a right future the network keeps (0 < SIGMA <= 1; 1 = from pure noise). Needs one-clip
episodes at the model's resolution. Everything else is as `tesseract4d evaluate --heldout`.

  tesseract4d research from-truth --sigma 0.5 --heldout data/heldout_groups128 \\
      --checkpoint tesseract4d/checkpoints/v2 --out outputs/from_truth
"""

from __future__ import annotations

import argparse


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from tesseract4d.cli import evaluate

    parser.add_argument("--sigma", type=float, required=True, dest="start_from_truth", metavar="SIGMA",
                        help="start every sampler at its first noise level <= SIGMA from the true future")
    evaluate.add_heldout_arguments(parser)
    parser.set_defaults(pred=None)


def run(args: argparse.Namespace) -> int:
    from tesseract4d.cli import evaluate
    from tesseract4d.errors import UserError

    if args.heldout is None:
        raise UserError("pass --heldout DIR (a held-out dataset) and --checkpoint CKPT")
    return evaluate.run_heldout(args)
