"""Blend two checkpoints of one latent space in weight space: a guide for autoguidance anyone can rebuild.

Autoguidance (`tesseract4d set-sampler --guide CKPT --autoguidance W`) wants a weaker network of the
same latent space, ideally an earlier checkpoint of the same training run. Where that run's middle
checkpoints are gone, the networks kept in git history still span its path: a network later trained
from an earlier one lies, in weight space, on a nearly straight line from it. This writes a checkpoint
whose transformer is ``(1 - weight) * A + weight * B`` (every float tensor, computed in float32 and
stored in B's dtypes) and everything else B's (config, scheduler, autoencoder).
The two must see the same inputs (resolution, frames, text encoder, latent space) and have the same
tensors; the blend is recorded in the copy's tesseract4d_config.json under ``blended``.

Example (the guide of docs/research/sampling.md, "Autoguidance": a quarter of the way back from step 6's v2 to step 5's):
  mkdir -p runs/v2_step5 runs/v2_step6
  git archive 228897b tesseract4d/checkpoints/v2 | tar -x -C runs/v2_step5
  git archive 66cad09 tesseract4d/checkpoints/v2 | tar -x -C runs/v2_step6
  .venv/bin/python scripts/blend_checkpoints.py runs/v2_step5/tesseract4d/checkpoints/v2 \\
      runs/v2_step6/tesseract4d/checkpoints/v2 --weight 0.75 --out runs/guide_075
  tesseract4d set-sampler --checkpoint tesseract4d/checkpoints/v2 --guide runs/guide_075 --autoguidance 1 \\
      --to runs/v2_ag
"""

from __future__ import annotations

import argparse
import json
import math
import shutil
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))


def blend(a: Path, b: Path, weight: float, out: Path, overwrite: bool = False) -> Path:
    """Write ``out``: checkpoint ``b`` with transformer weights ``(1 - weight) * a + weight * b``."""
    from safetensors.torch import load_file, save_file

    from tesseract4d.errors import UserError
    from tesseract4d.model.checkpoint import (INFERENCE_CONFIG_FILE, MODEL_CARD_FILE, MODEL_CONFIG_FILE,
                                              TRANSFORMER_DIR, WEIGHTS_FILE, check_guide, copy_checkpoint_files,
                                              read_inference_config, weights_digest)
    from tesseract4d.model.latent_checkpoint import own_autoencoder
    from tesseract4d.outputs import OutputDir

    if not math.isfinite(weight):
        raise UserError(f"--weight must be a finite number (0: A's weights, 1: B's), got {weight}")
    a, b = Path(a), Path(b)
    config = read_inference_config(b)
    check_guide(b, config, a)  # the same inputs and latent space, or a UserError naming what differs
    if read_inference_config(a)["preset"].get("backbone") != config["preset"].get("backbone"):
        raise UserError(f"{a} and {b} have different backbones; only networks of one architecture blend")
    # A transformer folder holds float weights as exported (only guide folders are ever stored in 8 bits).
    wa, wb = load_file(str(a / TRANSFORMER_DIR / WEIGHTS_FILE)), load_file(str(b / TRANSFORMER_DIR / WEIGHTS_FILE))
    if wa.keys() != wb.keys() or any(wa[k].shape != wb[k].shape for k in wb):
        raise UserError(f"{a} and {b} hold different tensors; only networks of one architecture blend")
    with OutputDir(out, "blend-checkpoints", inputs=[a, b], overwrite=overwrite) as tmp:
        copy_checkpoint_files(b, tmp, skip=(TRANSFORMER_DIR, MODEL_CARD_FILE))
        (tmp / TRANSFORMER_DIR).mkdir()
        shutil.copy2(b / TRANSFORMER_DIR / MODEL_CONFIG_FILE, tmp / TRANSFORMER_DIR / MODEL_CONFIG_FILE)
        blended = {k: ((1.0 - weight) * wa[k].float() + weight * vb.float()).to(vb.dtype).contiguous()
                   if vb.is_floating_point() else vb for k, vb in wb.items()}
        save_file(blended, str(tmp / TRANSFORMER_DIR / WEIGHTS_FILE), metadata={"format": "pt"})
        config = own_autoencoder(b, config, tmp)  # B's, where B shares the one of the checkpoint beside it
        config["blended"] = {"a": str(a), "b": str(b), "weight": weight, "a_digest": weights_digest(a),
                             "b_digest": weights_digest(b)}
        (tmp / INFERENCE_CONFIG_FILE).write_text(json.dumps(config, indent=2))
    return Path(out)


def main(argv: list[str] | None = None) -> int:
    from tesseract4d.errors import UserError

    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("a", type=Path, help="checkpoint A (weight 0 gives its transformer)")
    parser.add_argument("b", type=Path, help="checkpoint B (weight 1 gives its transformer; the rest is B's)")
    parser.add_argument("--weight", type=float, required=True, help="share of B in the blend (0.75: a quarter back to A)")
    parser.add_argument("--out", type=Path, required=True, help="new checkpoint folder to write")
    parser.add_argument("--overwrite", action="store_true",
                        help="replace an earlier blend in --out (files it did not write are never touched)")
    args = parser.parse_args(argv)
    try:
        out = blend(args.a, args.b, args.weight, args.out, overwrite=args.overwrite)
    except UserError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    print(f"blended checkpoint: {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
