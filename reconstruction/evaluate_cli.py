"""Metrics of a prediction or a reconstruction against the ground-truth episode: Chamfer
distance (L1: mean unsquared nearest-neighbour distance, both directions averaged, metres),
depth AbsRel / δ1 / δ2, normal angle mean / median / share under 11.25°, RGB PSNR / SSIM; per
frame and averaged, over all pixels and over the moving region. Prints a table; --json writes
the report that `tesseract4d view --compare GT --metrics REPORT` shows per frame.

PRED is a reconstruction folder (from `tesseract4d reconstruct`) or an episode (.h5, a
prediction folder holding one episode, or DIR/ENV_ID/SEED), which is back-projected as is.

Example:
  tesseract4d evaluate out/recon --gt data/test/episodes/PickCube-v1/seed_100000.h5 --json out/report.json
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("pred", help="reconstruction folder, or a predicted episode (.h5 / folder / DIR/ENV_ID/SEED)")
    parser.add_argument("--gt", required=True, help="ground-truth episode (.h5 / folder / DIR/ENV_ID/SEED)")
    parser.add_argument("--camera", help="camera to compare (default: the ground truth's first)")
    parser.add_argument("--json", type=Path, metavar="REPORT", help="also write the report as JSON")
    parser.add_argument("--no-per-frame", action="store_true", help="print only the means")


def load_prediction(spec: str):
    """A Recon4D for a reconstruction folder, else the episode ``spec`` names."""
    from reconstruction.recon4d import MANIFEST, Recon4D
    from tesseract4d.dataset_format import read_episode, resolve_episode

    if (Path(spec) / MANIFEST).is_file():
        return Recon4D.load(spec)
    return read_episode(resolve_episode(spec))


def run(args: argparse.Namespace) -> int:
    from reconstruction.evaluate import evaluate_episode, format_report, json_safe
    from tesseract4d.dataset_format import read_episode, resolve_episode

    pred = load_prediction(args.pred)
    gt_path = resolve_episode(args.gt)
    report = evaluate_episode(pred, read_episode(gt_path), camera=args.camera)
    report.update({"pred": str(args.pred), "gt": str(gt_path)})
    if report["pred_frames"] != report["gt_frames"]:
        print(f"note: prediction has {report['pred_frames']} frames, ground truth {report['gt_frames']}; "
              f"evaluated the first {report['num_frames']}")
    print(format_report(report, per_frame=not args.no_per_frame))
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(json_safe(report), indent=2))
        print(f"wrote {args.json}")
    return 0
