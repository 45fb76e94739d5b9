"""Encode a dataset with an RGB-D-N autoencoder once, into a latent cache the latent model trains on.

The cache (default DATASET/latent_cache/<camera>/) records the autoencoder's hash and the dataset's
episode files; it is reused while both are unchanged and rebuilt (atomically) when either changes.
`tesseract4d train --preset latent-128` builds it on its own when needed; this command does it ahead.

Example:
  tesseract4d encode-latents --data data/ae128 --autoencoder runs/ae/autoencoder
"""

from __future__ import annotations

import argparse
from pathlib import Path


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--data", type=Path, required=True, help="dataset folder (tesseract4d datagen)")
    parser.add_argument("--autoencoder", type=Path, required=True,
                        help="autoencoder folder (RUN/autoencoder written by `tesseract4d train-autoencoder`)")
    parser.add_argument("--camera", default=None, help="camera to encode (default: the dataset's first)")
    parser.add_argument("--cache", type=Path, default=None, help="cache folder (default DATA/latent_cache/<camera>)")
    parser.add_argument("--rebuild", action="store_true", help="rebuild even if the cache is valid")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")


def run(args: argparse.Namespace) -> int:
    from tesseract4d.errors import UserError
    from tesseract4d.model.latent_cache import ensure_latent_cache

    if args.cache is not None:
        # the cache folder, or the nearest of its parents that exists, must be a folder
        there = next((p for p in (args.cache, *args.cache.parents) if p.exists()), None)
        if there is not None and not there.is_dir():
            what = "is a file" if there == args.cache else f"lies under the file {there}"
            raise UserError(f"--cache {args.cache} {what}; --cache must be a folder (a new one, or a latent cache "
                            f"written before): pass a folder path, or leave --cache out for DATA/latent_cache/<camera>")
    cache, built = ensure_latent_cache(args.data, args.autoencoder, camera=args.camera, folder=args.cache,
                                       rebuild=args.rebuild, progress=not args.quiet)
    shape = cache.meta["latent_shape"]
    print(f"{'built' if built else 'reused'} latent cache {cache.folder}: {len(cache.episodes)} episodes, "
          f"latent {shape} per frame, autoencoder {cache.autoencoder_hash}")
    return 0
