"""Per-frame metrics shown in compare mode: read from an evaluation report, or computed cheaply.

The cheap metrics compare the images of a prediction and its ground truth pixel by pixel
(same camera, same resolution): RGB PSNR (dB), depth AbsRel and mean normal angle error (deg).
They are what the viewer shows when no ``tesseract4d evaluate`` report is given.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np

from reconstruction.recon4d import Recon4D
from tesseract4d.errors import UserError


def image_metrics(pred: Recon4D, gt: Recon4D) -> list[dict[str, float]]:
    """One dict per frame present in both (psnr_rgb_db, depth_absrel, normal_deg); empty if the
    image sizes differ (then only a report can give metrics)."""
    if pred.rgb.shape[1:3] != gt.rgb.shape[1:3]:
        return []
    out = []
    for t in range(min(pred.num_frames, gt.num_frames)):
        mse = np.mean((pred.rgb[t].astype(np.float32) - gt.rgb[t].astype(np.float32)) ** 2)
        psnr = float(10 * np.log10(255.0**2 / mse)) if mse > 0 else float("inf")
        d_p, d_g = pred.depth_m[t], gt.depth_m[t]
        both = (d_p > 0) & (d_g > 0) & np.isfinite(d_p) & np.isfinite(d_g)
        absrel = float(np.mean(np.abs(d_p[both] - d_g[both]) / d_g[both])) if both.any() else float("nan")
        n_p, n_g = pred.normal_cam[t], gt.normal_cam[t]
        has_n = (np.linalg.norm(n_p, axis=-1) > 0.5) & (np.linalg.norm(n_g, axis=-1) > 0.5)
        cos = np.sum(n_p[has_n] * n_g[has_n], -1) / (np.linalg.norm(n_p[has_n], axis=-1) * np.linalg.norm(n_g[has_n], axis=-1))
        normal_deg = float(np.degrees(np.mean(np.arccos(np.clip(cos, -1, 1))))) if has_n.any() else float("nan")
        out.append({"psnr_rgb_db": psnr, "depth_absrel": absrel, "normal_deg": normal_deg})
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
