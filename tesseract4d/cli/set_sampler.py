"""Write a copy of a checkpoint that samples with other default settings, the weights unchanged.

A checkpoint's preset carries how `predict`, `demo`, `evaluate --heldout`, `rollout` and the viewer
sample it by default: the Euler steps, the text and first-frame guidance scales and the guidance
interval (`--set guidance_min_sigma=S`: the guided passes run only at noise levels ≥ S, the steps below
run one unguided pass, so a clip costs fewer network passes). This writes a copy of the checkpoint
into --to (a new folder; the checkpoint itself is never changed; its model card is not copied) with
the settings given here and the others kept, and records the change (`sampler_changed` in its
tesseract4d_config.json). Score the copy beside the original with `evaluate --heldout`.

Static compositing (`--set static_tolerance=T`): where the decoded clip stays within T of its frame 0, the
given first frame's own pixels are shown instead of the decoder's redrawing of them; the parts of the
scene the model moves are left as predicted (docs/research/sampling.md, "Static compositing").

Several noise draws (`--set draws=N`): every future is predicted from N noises and the one whose objects
keep their colours best is kept (read from the first frame and the predicted clip only: its objects
named by its segmentation, or found by their colour without one; docs/research/sampling.md); N times the sampling.

Example (v2's 10 guided steps, guidance only at noise ≥ 0.5: 15 network passes per clip instead of 20):
  tesseract4d checkpoint set-sampler --checkpoint tesseract4d/checkpoints/v2 --set guidance_min_sigma=0.5 \\
      --to runs/v2_interval
  tesseract4d evaluate --heldout data/heldout_groups128 --checkpoint tesseract4d/checkpoints/v2 \\
      --checkpoint runs/v2_interval --sample-seed 0 1 --out outputs/interval
"""

from __future__ import annotations

import argparse
import dataclasses
from dataclasses import dataclass
from pathlib import Path

from tesseract4d.cli.config_args import add_moved_to_set, add_set_option
from tesseract4d.configs import knob


@dataclass
class SamplerSettings:
    """The sampler defaults a checkpoint's preset carries; None keeps the checkpoint's own."""

    num_steps: int | None = knob(None, "Euler steps per clip (set-sampler --steps)")
    text_guidance: float | None = knob(None, "text guidance scale (1 = none)")
    image_guidance: float | None = knob(None, "first-frame guidance scale (1 = none)")
    guidance_min_sigma: float | None = knob(None, "guide only the steps at noise level >= this (0 = every step; "
                                                  "1 guides only the first)")
    static_tolerance: float | None = knob(None, "static compositing: where the decoded clip stays within this of its "
                                                "first frame (model-space units, channels in [-1, 1]), show the given "
                                                "first frame's own pixels instead of the decoder's redrawing (0 = off)")
    draws: int | None = knob(None, "predict every future from N noise draws and keep the one whose objects keep "
                                   "their colours best; N times the sampling (1 = a single draw)")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--checkpoint", type=Path, required=True, help="an inference checkpoint folder")
    parser.add_argument("--to", type=Path, required=True, help="new checkpoint folder to write")
    parser.add_argument("--steps", type=int, help="sampler (Euler) steps per clip")
    parser.add_argument("--text-guidance", type=float, metavar="SCALE", help="text guidance scale (1 = none)")
    parser.add_argument("--overwrite", action="store_true",
                        help="write into a --to that holds files set-sampler did not write (an earlier set-sampler "
                             "copy there is replaced without it; files it did not write are never touched)")
    add_set_option(parser, SamplerSettings)
    add_moved_to_set(parser, SamplerSettings, [
        ("--image-guidance", "image_guidance", float), ("--guidance-min-sigma", "guidance_min_sigma", float),
        ("--static-tolerance", "static_tolerance", float), ("--draws", "draws", int),
    ])


def run(args: argparse.Namespace) -> int:
    from tesseract4d.configs import with_overrides
    from tesseract4d.model.checkpoint_copies import write_sampler_copy

    chosen = with_overrides(SamplerSettings(num_steps=args.steps, text_guidance=args.text_guidance), args.set_overrides)
    settings = {name: value for name, value in dataclasses.asdict(chosen).items() if value is not None}
    to = write_sampler_copy(args.checkpoint, args.to, settings, overwrite=args.overwrite)
    print(f"checkpoint with the new sampler settings: {to}")
    return 0
