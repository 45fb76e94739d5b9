"""Store one autoencoder for two latent checkpoints side by side that carry the same one.

`v2` and its 2-step student `v2-2step` decode with the very same autoencoder (5.4 MB, the same hash).
This writes a copy of CHECKPOINT into --to, a folder beside SIBLING, without its own autoencoder: the
copy's tesseract4d_config.json names ../SIBLING/autoencoder, which loading checks by its hash as
before. Everything else is copied as it is (model card included); CHECKPOINT itself is not changed.
A copy of the sharing checkpoint written elsewhere by `set-sampler --to` or `swap-decoder --to` takes
its own copy of the autoencoder again. How the shipped v2-2step was made to share v2's:

  .venv/bin/python scripts/share_autoencoder.py tesseract4d/checkpoints/v2-2step \\
      --with tesseract4d/checkpoints/v2 --to tesseract4d/checkpoints/v2-2step-shared
  # then the shared copy takes the place of the original folder (by hand, under version control)
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))


def main(argv: list[str] | None = None) -> int:
    from tesseract4d.errors import UserError
    from tesseract4d.model.latent_checkpoint import share_autoencoder

    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("checkpoint", type=Path, help="the latent checkpoint to copy without its autoencoder")
    parser.add_argument("--with", dest="sibling", type=Path, required=True,
                        help="the checkpoint whose autoencoder (the same one) the copy reads")
    parser.add_argument("--to", type=Path, required=True, help="new checkpoint folder, in the same folder as --with")
    parser.add_argument("--overwrite", action="store_true",
                        help="replace an earlier copy in --to (files it did not write are never touched)")
    args = parser.parse_args(argv)
    try:
        to = share_autoencoder(args.checkpoint, args.sibling, args.to, overwrite=args.overwrite)
    except UserError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    print(f"checkpoint sharing {args.sibling}'s autoencoder: {to}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
