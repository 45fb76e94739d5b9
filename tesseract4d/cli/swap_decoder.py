"""Put a better decoder into a latent checkpoint, keeping its transformer.

A decoder fine-tuned with `tesseract4d train-autoencoder --recipe ae-f8c32-decoder --init CKPT/autoencoder`
decodes the very latents the checkpoint's transformer was trained on (its encoder and latent
statistics are bit-identical), so it can replace the checkpoint's decoder without retraining the
transformer. This writes a copy of the checkpoint with the new autoencoder into --to (a new folder;
the checkpoint itself is never changed) and records both autoencoders' hashes in its
tesseract4d_config.json. An autoencoder whose encoder differs is refused.

Example:
  tesseract4d train-autoencoder --recipe ae-f8c32-decoder --init tesseract4d/checkpoints/v2/autoencoder \\
      --data data/v2_tabletop_240 data/ae128 --heldout data/heldout_groups128 --out runs/dec_ft
  tesseract4d checkpoint swap-decoder --checkpoint tesseract4d/checkpoints/v2 --autoencoder runs/dec_ft/autoencoder \\
      --to runs/v2_dec_ft --half
  tesseract4d evaluate --heldout data/heldout_groups128 --checkpoint tesseract4d/checkpoints/v2 \\
      --checkpoint runs/v2_dec_ft --out outputs/eval_dec_ft
"""

from __future__ import annotations

import argparse
from pathlib import Path


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--checkpoint", type=Path, required=True, help="a latent checkpoint (e.g. tesseract4d/checkpoints/v2)")
    parser.add_argument("--autoencoder", type=Path, required=True,
                        help="the decoder-only fine-tune of the checkpoint's autoencoder (RUN/autoencoder)")
    parser.add_argument("--to", type=Path, required=True, help="new checkpoint folder to write")
    parser.add_argument("--half", action="store_true", help="store the new autoencoder in float16 (half the size)")
    parser.add_argument("--overwrite", action="store_true",
                        help="write into a --to that holds files swap-decoder did not write (an earlier swap-decoder copy there is replaced without it; files it did not write are never touched)")


def run(args: argparse.Namespace) -> int:
    from tesseract4d.model.checkpoint_copies import replace_decoder

    to = replace_decoder(args.checkpoint, args.autoencoder, args.to, half=args.half, overwrite=args.overwrite)
    print(f"checkpoint with the new decoder: {to}")
    return 0
