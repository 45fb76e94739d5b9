"""Evaluation of a prediction (an episode) or a reconstruction (a Recon4D) against a ground
truth episode of the same camera: per-frame and mean metrics, over all pixels and over the
moving region (keys ending in ``_moving``). Definitions in ``metrics.py``.

The report (what ``tesseract4d evaluate --json`` writes and the viewer's compare mode reads)::

    {"format": "tesseract4d-eval", "format_version": 2, "definitions": {...},
     "camera": str, "max_depth_m": M or null, "num_frames": n, "pred_frames": Tp, "gt_frames": Tg,
     "first_scored_frame": f, "mean": {metric: value}, "per_frame": [{metric: value}, ... one per frame]}

Values are floats; NaN (nothing to measure, e.g. an empty moving region) is written as null.
The means are over frames ``first_scored_frame`` on: a prediction's frame 0 is the first frame it
was given (scored, it would add a perfect frame to every mean), so its means start at frame 1
(:func:`given_frames`); a reconstruction of a recorded episode is scored from frame 0.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from tesseract4d.evaluation import metrics as M
from reconstruction.recon4d import Recon4D
from tesseract4d.dataset_format import Episode
from tesseract4d.errors import UserError
from tesseract4d.geometry import depth_to_world_points, invert_pose, project_points, transform_points
from reconstruction.reconstruct import check_frames, select_camera

REPORT_FORMAT = "tesseract4d-eval"
REPORT_VERSION = 2  # 2: means from first_scored_frame on (a prediction's given frame 0 no longer counts)

DEFINITIONS = {
    "chamfer_l1_m": "0.5 * (mean_pred min_gt |p - g| + mean_gt min_pred |g - p|), Euclidean, metres; "
                    "reconstructed (or back-projected) world points vs ground-truth depth back-projected, per frame",
    "depth_abs_rel": "mean |pred - gt| / gt over pixels with gt > 0 and pred > 0",
    "depth_delta1": "share of valid pixels with max(pred/gt, gt/pred) < 1.25",
    "depth_delta2": "share of valid pixels with max(pred/gt, gt/pred) < 1.25^2",
    "normal_mean_deg": "mean angle between predicted and ground-truth normals, degrees",
    "normal_median_deg": "median angle, degrees",
    "normal_within_11_25": "share of pixels with angle < 11.25 degrees",
    "rgb_psnr_db": f"PSNR of RGB (peak 255), dB, at most {M.PSNR_MAX_DB:g}",
    "rgb_ssim": "SSIM (11x11 Gaussian window, sigma 1.5), mean over channels and pixels",
    "_moving": "same metric restricted to ground-truth pixels that change over the clip (RGB or depth "
               "differs from frame 0; frame 0: pixels that change later)",
    "moving_share": "share of pixels in the moving region",
}
METRICS = ("chamfer_l1_m", "depth_abs_rel", "depth_delta1", "depth_delta2", "normal_mean_deg",
           "normal_median_deg", "normal_within_11_25", "rgb_psnr_db", "rgb_ssim")


@dataclass
class _Frames:
    """What the metrics need from either side. T frames of H x W."""

    rgb: np.ndarray  # (T, H, W, 3) uint8
    depth_m: np.ndarray  # (T, H, W)
    normal_cam: np.ndarray  # (T, H, W, 3)
    points_world: list[np.ndarray]  # T x (N_t, 3)


def given_frames(pred: "Episode | Recon4D") -> int:
    """How many leading frames of ``pred`` were given, not predicted: 1 for a prediction (its frame
    0 is the conditioning frame, copied) or a reconstruction of one, 0 otherwise."""
    if isinstance(pred, Episode):
        return int(pred.source == "prediction")
    return int(str(pred.metadata.get("source", "")).startswith("episode (prediction)"))


def _episode_frames(episode: Episode, camera: str | None, role: str) -> tuple[str, _Frames, object]:
    name, cam = select_camera(episode, camera)
    depth, normals, _ = check_frames(cam, f"{role} {episode.episode_id}/{name}")
    points = [depth_to_world_points(depth[t], cam.K[t], cam.T_world_cam[t])[0] for t in range(len(depth))]
    return name, _Frames(np.asarray(cam.rgb, np.uint8), depth, normals, points), cam


def _recon_frames(recon: Recon4D) -> _Frames:
    recon.validate()
    depth = np.asarray(recon.depth_m, np.float32)
    return _Frames(np.asarray(recon.rgb, np.uint8), np.where(np.isfinite(depth), depth, 0.0),
                   np.asarray(recon.normal_cam, np.float32), list(recon.points_world))


def _in_mask(points_world: np.ndarray, mask: np.ndarray, K: np.ndarray, T_world_cam: np.ndarray) -> np.ndarray:
    """Which world points project (with the given camera) into pixels where ``mask`` (H, W) is set."""
    uv, z = project_points(transform_points(invert_pose(T_world_cam), points_world), K)
    H, W = mask.shape
    with np.errstate(invalid="ignore"):
        col, row = np.floor(uv[:, 0]), np.floor(uv[:, 1])
        inside = (z > 0) & (col >= 0) & (row >= 0) & (col < W) & (row < H)
    keep = np.zeros(len(points_world), bool)
    keep[inside] = mask[row[inside].astype(np.int64), col[inside].astype(np.int64)]
    return keep


def evaluate_episode(pred: Episode | Recon4D, gt: Episode, camera: str | None = None,
                     moving_mask: np.ndarray | None = None, max_depth_m: float | None = None,
                     first_scored_frame: int | None = None) -> dict:
    """Metrics of ``pred`` against ``gt`` (see the module docstring for the report's shape).
    ``first_scored_frame``: the first frame the means count (None: :func:`given_frames` of
    ``pred``); every frame keeps its row in ``per_frame``.

    pred: a predicted/raw episode (its depth is back-projected as is) or a Recon4D (its points
    and refined depth are used). camera: the camera of ``gt`` (and of ``pred`` if it has one of
    that name); None = the first. moving_mask: (T, H, W) bool of the ground truth's frames;
    None = :func:`metrics.moving_region_mask`. Frames are matched by index; when the counts
    differ, the common leading frames are evaluated. max_depth_m: the evaluation range; the
    geometric metrics (depth, normals, Chamfer) then count only pixels whose true depth is at
    most this (e.g. a model's depth range: the workspace, not the distant floor); RGB metrics
    always count every pixel.
    """
    if not isinstance(pred, (Episode, Recon4D)):
        raise UserError(f"evaluate: pred must be an Episode or a Recon4D, got {type(pred).__name__}")
    cam_name, truth, gt_cam = _episode_frames(gt, camera, "gt")
    if isinstance(pred, Recon4D):
        pred_frames = _recon_frames(pred)
    else:  # a prediction may name its camera differently; then its first camera
        pred_frames = _episode_frames(pred, cam_name if cam_name in pred.cameras else None, "pred")[1]
    if pred_frames.rgb.shape[1:3] != truth.rgb.shape[1:3]:
        raise UserError(f"prediction is {pred_frames.rgb.shape[2]}x{pred_frames.rgb.shape[1]} but ground truth is "
                        f"{truth.rgb.shape[2]}x{truth.rgb.shape[1]}; evaluate at the ground truth's resolution")
    n = min(len(pred_frames.rgb), len(truth.rgb))
    if moving_mask is None:
        moving_mask = M.moving_region_mask(gt_cam)
    moving_mask = np.asarray(moving_mask, bool)
    if moving_mask.shape[1:] != truth.depth_m.shape[1:] or len(moving_mask) < n:
        raise UserError(f"moving mask has shape {moving_mask.shape}; expected ({len(truth.depth_m)}, H, W) of the ground truth")

    per_frame = []
    for t in range(n):
        row: dict[str, float] = {}
        gt_all = truth.points_world[t]
        gt_valid = truth.depth_m[t] > 0
        in_range = None if max_depth_m is None else truth.depth_m[t] <= max_depth_m
        for suffix, mask in (("", None), ("_moving", moving_mask[t])):
            geo_mask = mask if in_range is None else (in_range if mask is None else mask & in_range)
            gt_pts, pred_pts = gt_all, pred_frames.points_world[t]
            if geo_mask is not None:
                gt_pts = gt_all[geo_mask[gt_valid]]
                pred_pts = pred_pts[_in_mask(pred_pts, geo_mask, gt_cam.K[t], gt_cam.T_world_cam[t])]
            row["chamfer_l1_m" + suffix] = M.chamfer_l1_m(pred_pts, gt_pts)
            d = M.depth_metrics(pred_frames.depth_m[t], truth.depth_m[t], geo_mask)
            row["depth_abs_rel" + suffix], row["depth_delta1" + suffix], row["depth_delta2" + suffix] = d["abs_rel"], d["delta1"], d["delta2"]
            nm = M.normal_metrics(pred_frames.normal_cam[t], truth.normal_cam[t], geo_mask)
            row["normal_mean_deg" + suffix], row["normal_median_deg" + suffix], row["normal_within_11_25" + suffix] = (
                nm["mean_deg"], nm["median_deg"], nm["within_11_25"])
            row["rgb_psnr_db" + suffix] = M.rgb_psnr(pred_frames.rgb[t], truth.rgb[t], mask)
            row["rgb_ssim" + suffix] = M.rgb_ssim(pred_frames.rgb[t], truth.rgb[t], mask)
        row["moving_share"] = float(moving_mask[t].mean())
        per_frame.append(row)

    first = given_frames(pred) if first_scored_frame is None else int(first_scored_frame)
    first = first if first < len(per_frame) else 0  # a clip of given frames only: scored as it is
    scored = per_frame[first:]
    keys = list(per_frame[0]) if per_frame else []
    mean = {}
    for k in keys:
        vals = np.array([r[k] for r in scored], np.float64)
        mean[k] = float(np.mean(vals[np.isfinite(vals)])) if np.isfinite(vals).any() else float("nan")
    return {
        "format": REPORT_FORMAT, "format_version": REPORT_VERSION, "definitions": DEFINITIONS,
        "camera": cam_name, "max_depth_m": max_depth_m, "num_frames": n, "pred_frames": int(len(pred_frames.rgb)), "gt_frames": int(len(truth.rgb)),
        "first_scored_frame": first, "mean": mean, "per_frame": per_frame,
    }


def json_safe(obj):
    """The report with NaN/inf floats replaced by None (strict JSON)."""
    if isinstance(obj, dict):
        return {k: json_safe(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [json_safe(v) for v in obj]
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    return obj


def format_report(report: dict, per_frame: bool = True) -> str:
    """A plain-text table: every metric's mean over all pixels and over the moving region, then
    (optionally) a few key metrics per frame."""
    fmt = lambda v: "-" if v is None or (isinstance(v, float) and not math.isfinite(v)) else f"{v:.4g}"  # noqa: E731
    mean = report["mean"]
    first = report.get("first_scored_frame", 0)
    scored = f"; means over frames {first} to {report['num_frames'] - 1}" + (
        " (frame 0 is the given first frame)" if first == 1 else "") if first else ""
    lines = [f"camera {report['camera']}, {report['num_frames']} frames "
             f"(prediction {report['pred_frames']}, ground truth {report['gt_frames']}){scored}",
             f"{'metric':<22}{'all':>12}{'moving':>12}"]
    for k in METRICS:
        lines.append(f"{k:<22}{fmt(mean.get(k)):>12}{fmt(mean.get(k + '_moving')):>12}")
    if per_frame:
        cols = ("chamfer_l1_m", "depth_abs_rel", "depth_delta1", "normal_mean_deg", "rgb_psnr_db", "rgb_ssim", "chamfer_l1_m_moving")
        lines.append("")
        lines.append(f"{'frame':>5}" + "".join(f"{c:>21}" for c in cols))
        for t, row in enumerate(report["per_frame"]):
            lines.append(f"{t:>5}" + "".join(f"{fmt(row.get(c)):>21}" for c in cols))
    return "\n".join(lines)
