"""Write a copy of a checkpoint that samples with other default settings, the weights unchanged.

A checkpoint's preset carries how `predict`, `demo`, `evaluate --heldout`, `rollout` and the viewer
sample it by default: the Euler steps, the text and first-frame guidance scales and the guidance
interval (`--guidance-min-sigma S`: the guided passes run only at noise levels ≥ S, the steps below
run one unguided pass, so a clip costs fewer network passes). This writes a copy of the checkpoint
into --to (a new folder; the checkpoint itself is never changed; its model card is not copied) with
the settings given here and the others kept, and records the change (`sampler_changed` in its
tesseract4d_config.json). Score the copy beside the original with `evaluate --heldout`.

Autoguidance (`--guide CKPT --autoguidance W`): the copy carries CKPT's transformer, a weaker network
of the same latent space (an early checkpoint of the same training run), and every step adds W times
the difference of the two networks' predictions, moving the sample away from what the weaker one gets
wrong; one more network pass per step. `--autoguidance-min-sigma S` runs that pass only at noise levels
≥ S, where the motion is laid out, and leaves the last, fine steps to the network alone.

Static compositing (`--static-tolerance T`): where the decoded clip stays within T of its frame 0, the
given first frame's own pixels are shown instead of the decoder's redrawing of them; the parts of the
scene the model moves are left as predicted (docs/research/sampling.md, "Static compositing").

Several noise draws (`--draws N`): every future is predicted from N noises and the one whose objects
keep their colours best is kept (read from the first frame and the predicted clip only: its objects
named by its segmentation, or found by their colour without one; docs/research/sampling.md); N times
the sampling.

Example (v2's 10 guided steps, guidance only at noise ≥ 0.5: 15 network passes per clip instead of 20):
  tesseract4d set-sampler --checkpoint tesseract4d/checkpoints/v2 --guidance-min-sigma 0.5 --to runs/v2_interval
  tesseract4d evaluate --heldout data/heldout_groups128 --checkpoint tesseract4d/checkpoints/v2 \\
      --checkpoint runs/v2_interval --sample-seed 0 1 --out outputs/interval

Example (v2 carries a guide, in 8 bits, off by default; this turns it on; docs/research/sampling.md):
  tesseract4d set-sampler --checkpoint tesseract4d/checkpoints/v2 --autoguidance 1 --to runs/v2_ag

Example (another guide: an earlier v2 of the same latent space, taken from git history):
  mkdir -p runs/v2_step6 && git archive 66cad09 tesseract4d/checkpoints/v2 | tar -x -C runs/v2_step6
  tesseract4d set-sampler --checkpoint tesseract4d/checkpoints/v2 --guide runs/v2_step6/tesseract4d/checkpoints/v2 \\
      --autoguidance 2 --to runs/v2_ag_step6
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
    parser.add_argument("--autoguidance", type=float, metavar="W",
                        help="autoguidance scale: every step adds W × (the network's x0 − the guide's x0), "
                             "first frame and text given to both (0 = none; needs --guide or a copy that has one)")
    parser.add_argument("--autoguidance-min-sigma", type=float, metavar="S",
                        help="autoguide only the steps at noise level ≥ S, where the motion is laid out; the "
                             "steps below run without the guide's pass (0 = every step)")
    parser.add_argument("--static-tolerance", type=float, metavar="T",
                        help="static compositing: where the decoded clip stays within T of its first frame "
                             "(model-space units, channels in [-1, 1]), show the given first frame's own pixels "
                             "instead of the decoder's redrawing of them (0 = off)")
    parser.add_argument("--draws", type=int, metavar="N",
                        help="predict every future from N noise draws and keep the one whose objects (named by the "
                             "first frame's segmentation, or found by their colour) keep their colours best; N times "
                             "the sampling (1 = a single draw; docs/research/sampling.md)")
    parser.add_argument("--guide", type=Path, metavar="CKPT",
                        help="checkpoint whose transformer becomes the copy's autoguidance network: a weaker "
                             "model of the same latent space, e.g. an early checkpoint of the same training run")
    parser.add_argument("--guide-bits", type=int, choices=(16, 8), default=16, metavar="{16,8}",
                        help="store the guide as it is (16) or its matrices in 8 bits, one scale per output "
                             "row (8): half the bytes, loaded back as float32 (default: 16)")
    parser.add_argument("--overwrite", action="store_true",
                        help="write into a --to that holds files set-sampler did not write (an earlier set-sampler copy there is replaced without it; files it did not write are never touched)")


def run(args: argparse.Namespace) -> int:
    from tesseract4d.model.checkpoint import write_sampler_copy

    settings = {name: value for name, value in (("num_steps", args.steps), ("text_guidance", args.text_guidance),
                                                ("image_guidance", args.image_guidance),
                                                ("guidance_min_sigma", args.guidance_min_sigma),
                                                ("autoguidance", args.autoguidance),
                                                ("autoguidance_min_sigma", args.autoguidance_min_sigma),
                                                ("static_tolerance", args.static_tolerance),
                                                ("draws", args.draws))
                if value is not None}
    to = write_sampler_copy(args.checkpoint, args.to, settings, overwrite=args.overwrite, guide=args.guide,
                            guide_bits=args.guide_bits)
    print(f"checkpoint with the new sampler settings: {to}")
    return 0
