"""Per-frame metrics shown in compare mode: read from an evaluation report, or computed cheaply.

The cheap metrics compare the images of a prediction and its ground truth pixel by pixel
(same camera, same resolution): RGB PSNR (dB), depth AbsRel and mean normal angle error (deg),
as defined in :mod:`tesseract4d.evaluation.metrics`. They are what the viewer shows when no
``tesseract4d evaluate`` report is given.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

from reconstruction.recon4d import Recon4D
from tesseract4d.evaluation.metrics import depth_metrics, normal_metrics, rgb_psnr
from tesseract4d.errors import UserError


def image_metrics(pred: Recon4D, gt: Recon4D) -> list[dict[str, float]]:
    """One dict per frame present in both (psnr_rgb_db, depth_absrel, normal_deg); empty if the
    image sizes differ (then only a report can give metrics)."""
    if pred.rgb.shape[1:3] != gt.rgb.shape[1:3]:
        return []
    out = []
    for t in range(min(pred.num_frames, gt.num_frames)):
        out.append({
            "psnr_rgb_db": rgb_psnr(pred.rgb[t], gt.rgb[t]),
            "depth_absrel": depth_metrics(pred.depth_m[t], gt.depth_m[t])["abs_rel"],
            "normal_deg": normal_metrics(pred.normal_cam[t], gt.normal_cam[t])["mean_deg"],
        })
    return out


def load_report_per_frame(path: str | os.PathLike) -> list[dict[str, float]]:
    """Per-frame metrics from a JSON report: the first ``per_frame`` entry found, either a list
    of {metric: value} (one per frame) or {metric: [value per frame]}."""
    path = Path(path)
    try:
        report = json.loads(path.read_text())
    except FileNotFoundError as e:
        raise UserError(f"metrics report {path} does not exist; write one with `tesseract4d evaluate`.") from e
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise UserError(f"metrics report {path} is not valid JSON ({e}); re-run `tesseract4d evaluate`.") from e
    found = _find_per_frame(report)
    if found is None:
        raise UserError(f"metrics report {path} has no 'per_frame' metrics; re-run `tesseract4d evaluate` or leave out --metrics.")
    if isinstance(found, dict):
        n = max((len(v) for v in found.values() if isinstance(v, list)), default=0)
        return [{k: v[t] for k, v in found.items() if isinstance(v, list) and t < len(v)} for t in range(n)]
    return [dict(row) for row in found if isinstance(row, dict)]


def _find_per_frame(obj):
    if isinstance(obj, dict):
        if isinstance(obj.get("per_frame"), (list, dict)):
            return obj["per_frame"]
        children = obj.values()
    elif isinstance(obj, list):
        children = obj
    else:
        return None
    for child in children:
        found = _find_per_frame(child)
        if found is not None:
            return found
    return None


def format_metrics(row: dict | None, t: int) -> str:
    """Markdown for one frame's metrics."""
    if not row:
        return f"Frame {t}: no metrics."
    cells = []
    for k, v in row.items():
        cells.append(f"| {k} | {v:.4g} |" if isinstance(v, (int, float)) else f"| {k} | {v} |")
    return f"**Frame {t}**\n\n| metric | value |\n|---|---|\n" + "\n".join(cells)
