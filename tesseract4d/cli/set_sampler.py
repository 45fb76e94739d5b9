"""Write a copy of a checkpoint that samples with other default settings, the weights unchanged.

A checkpoint's preset carries how `predict`, `demo`, `evaluate --heldout`, `rollout` and the viewer
sample it by default: the Euler steps, the text and first-frame guidance scales and the guidance
interval (`--guidance-min-sigma S`: the guided passes run only at noise levels ≥ S, the steps below
run one unguided pass, so a clip costs fewer network passes). This writes a copy of the checkpoint
into --to (a new folder; the checkpoint itself is never changed; its model card is not copied) with
the settings given here and the others kept, and records the change (`sampler_changed` in its
tesseract4d_config.json). Score the copy beside the original with `evaluate --heldout`.

Static compositing (`--static-tolerance T`): where the decoded clip stays within T of its frame 0, the
given first frame's own pixels are shown instead of the decoder's redrawing of them; the parts of the
scene the model moves are left as predicted (docs/research/sampling.md, "Static compositing").

Several noise draws (`--draws N`): every future is predicted from N noises and the one whose objects
keep their colours best is kept (read from the first frame and the predicted clip only: its objects
named by its segmentation, or found by their colour without one; docs/research/sampling.md); N times the sampling.

Example (v2's 10 guided steps, guidance only at noise ≥ 0.5: 15 network passes per clip instead of 20):
  tesseract4d set-sampler --checkpoint tesseract4d/checkpoints/v2 --guidance-min-sigma 0.5 --to runs/v2_interval
  tesseract4d evaluate --heldout data/heldout_groups128 --checkpoint tesseract4d/checkpoints/v2 \\
      --checkpoint runs/v2_interval --sample-seed 0 1 --out outputs/interval

"""

from __future__ import annotations

import argparse
from pathlib import Path


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--checkpoint", type=Path, required=True, help="an inference checkpoint folder")
    parser.add_argument("--to", type=Path, required=True, help="new checkpoint folder to write")
    parser.add_argument("--steps", type=int, help="Euler steps per clip")
    parser.add_argument("--text-guidance", type=float, metavar="SCALE", help="text guidance scale (1 = none)")
    parser.add_argument("--image-guidance", type=float, metavar="SCALE", help="first-frame guidance scale (1 = none)")
    parser.add_argument("--guidance-min-sigma", type=float, metavar="S",
                        help="guide only the steps at noise level ≥ S (0 = every step; 1 guides only the first)")
    parser.add_argument("--static-tolerance", type=float, metavar="T",
                        help="static compositing: where the decoded clip stays within T of its first frame "
                             "(model-space units, channels in [-1, 1]), show the given first frame's own pixels "
                             "instead of the decoder's redrawing of them (0 = off)")
    parser.add_argument("--draws", type=int, metavar="N",
                        help="predict every future from N noise draws and keep the one whose objects (named by the "
                             "first frame's segmentation, or found by their colour) keep their colours best; N times "
                             "the sampling (1 = a single draw; docs/research/sampling.md)")
    parser.add_argument("--overwrite", action="store_true",
                        help="write into a --to that holds files set-sampler did not write (an earlier set-sampler copy there is replaced without it; files it did not write are never touched)")


def run(args: argparse.Namespace) -> int:
    from tesseract4d.model.checkpoint_copies import write_sampler_copy

    settings = {name: value for name, value in (("num_steps", args.steps), ("text_guidance", args.text_guidance),
                                                ("image_guidance", args.image_guidance),
                                                ("guidance_min_sigma", args.guidance_min_sigma),
                                                ("static_tolerance", args.static_tolerance),
                                                ("draws", args.draws))
                if value is not None}
    to = write_sampler_copy(args.checkpoint, args.to, settings, overwrite=args.overwrite)
    print(f"checkpoint with the new sampler settings: {to}")
    return 0
