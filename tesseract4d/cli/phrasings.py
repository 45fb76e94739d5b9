"""A probe of the project's research: does a model keep still under every way of saying "keep still"?

Every scene of a held-out dataset of counterfactual groups (`datagen --instructions-per-scene`) is
predicted from its first frame under each phrasing of the skill library's keep_still skill (its
training and held-out paraphrases, or --phrase ...), once per noise seed, with the noise
`evaluate --heldout` gives that scene. A clip keeps still when its motion is at most 10 % of the mean
motion of the scene's true active futures. Prints one Markdown row per phrasing.

  tesseract4d research phrasings --heldout data/heldout_groups128 \\
      --checkpoint tesseract4d/checkpoints/v2 tesseract4d/checkpoints/v2-2step --sample-seed 0 1
"""

from __future__ import annotations

import argparse
from pathlib import Path

from tesseract4d.cli.argument_types import seed


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--heldout", type=Path, required=True, help="held-out dataset of counterfactual groups")
    parser.add_argument("--checkpoint", type=Path, nargs="+", default=None,
                        help="inference checkpoint(s) (default: the shipped v2-2step)")
    parser.add_argument("--sample-seed", type=seed(), nargs="+", default=[0], metavar="SEED",
                        help="noise seeds, as evaluate's (default 0)")
    parser.add_argument("--phrase", nargs="+", default=None,
                        help="phrasings to ask (default: every keep-still paraphrase of the skill library)")
    parser.add_argument("--json", type=Path, default=None, help="also write the per-clip numbers here (a new file)")


def run(args: argparse.Namespace) -> int:
    from tesseract4d.evaluation.still_phrasings import run_probe
    from tesseract4d.model.checkpoint import SHIPPED_CHECKPOINT

    run_probe(args.heldout, args.checkpoint or [SHIPPED_CHECKPOINT], args.sample_seed, args.phrase, args.json)
    return 0
