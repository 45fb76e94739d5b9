"""Fidelity gate of the RGB-D-N autoencoder: how much of a frame survives encode -> decode.

On held-out frames, over all pixels and over robot/object pixels (from the segmentation):

* ``rgb_psnr_db``: PSNR of the 8-bit RGB (``metrics.rgb_psnr``).
* ``depth_mae_mm``: mean |depth_hat - depth| in millimetres over pixels whose true depth lies inside
  the model space's metric range (farther pixels are "beyond the range" by design);
  ``depth_abs_rel`` over the same pixels (``metrics.depth_metrics``).
* ``normal_mean_deg``: mean angle between decoded (renormalised) and true normals
  (``metrics.normal_metrics``).
* ``rgb_edge_sharpness`` (all pixels only): the decoded colour's gradient on the truth's strongest
  edges relative to the truth's (``believability.edge_sharpness``, the held-out evaluation's
  sharpness; 1 = as sharp). It caps what a latent model decoded by this autoencoder can reach.

Aims (the project's fidelity gate): RGB >= 32 dB; depth <= 5 mm and normals <= 6 deg on robot/object pixels.
"""

from __future__ import annotations

import numpy as np
import torch

from tesseract4d.evaluation.believability import edge_sharpness
from tesseract4d.evaluation.metrics import depth_metrics, normal_metrics, rgb_psnr
from tesseract4d.model.autoencoder import RGBDNAutoencoder
from tesseract4d.model.autoencoder_trainer import FrameSet
from tesseract4d.model.model_space import FAR_BAND
from tesseract4d.colors import colorize_depth, colorize_normals

AIMS = {"rgb_psnr_db": 32.0, "object_depth_mae_mm": 5.0, "object_normal_mean_deg": 6.0}


@torch.no_grad()
def reconstruct_frames(model: RGBDNAutoencoder, frames: torch.Tensor, chunk: int = 16) -> torch.Tensor:
    """(n, 7, H, W) model space -> (n, 7, H, W) decoded through the latent (posterior means)."""
    return torch.cat([model.decode(model.encode(frames[i:i + chunk].float())) for i in range(0, len(frames), chunk)])


def fidelity_metrics(model: RGBDNAutoencoder, heldout: FrameSet) -> dict:
    """The gate's numbers (see the module docstring) for ``heldout`` frames."""
    model.eval()
    ms = model.model_space
    recon = reconstruct_frames(model, heldout.frames)
    gt_rgb, gt_depth, gt_normal = ms.decode(heldout.frames.float())  # (n, H, W, 3), (n, H, W), (n, H, W, 3)
    pr_rgb, pr_depth, pr_normal = ms.decode(recon)
    in_range = (gt_depth > 0) & (gt_depth < ms.far_m - FAR_BAND * (ms.far_m - ms.near_m))
    objects = heldout.masks.numpy()
    out: dict = {"frames": len(heldout), "object_pixel_share": float(objects.mean())}
    for prefix, sel in (("", np.ones_like(objects)), ("object_", objects)):
        d_sel = sel & in_range
        # A decoded depth of 0 ("beyond the range") where the truth is in range counts at far_m.
        pr_d = np.where(pr_depth > 0, pr_depth, ms.far_m)
        out[f"{prefix}rgb_psnr_db"] = rgb_psnr(pr_rgb, gt_rgb, sel)
        out[f"{prefix}depth_mae_mm"] = float(np.abs(pr_d - gt_depth)[d_sel].mean() * 1000.0) if d_sel.any() else float("nan")
        out[f"{prefix}depth_abs_rel"] = depth_metrics(pr_d, gt_depth, d_sel)["abs_rel"]
        out[f"{prefix}normal_mean_deg"] = normal_metrics(pr_normal, gt_normal, sel)["mean_deg"]
    out["rgb_edge_sharpness"] = edge_sharpness(pr_rgb, gt_rgb)
    out["aims"] = AIMS
    out["meets_aims"] = bool(out["rgb_psnr_db"] >= AIMS["rgb_psnr_db"]
                             and out["object_depth_mae_mm"] <= AIMS["object_depth_mae_mm"]
                             and out["object_normal_mean_deg"] <= AIMS["object_normal_mean_deg"])
    return out


def format_fidelity(d: dict) -> str:
    """A small table of the gate's numbers."""
    if "rgb_psnr_db" not in d:
        return "fidelity gate: no held-out frames given (pass --heldout)"
    rows = [("RGB PSNR (dB)", "rgb_psnr_db", ">= 32"), ("depth MAE (mm)", "depth_mae_mm", "<= 5 (objects)"),
            ("depth AbsRel", "depth_abs_rel", ""), ("normal angle (deg)", "normal_mean_deg", "<= 6 (objects)")]
    lines = [f"fidelity gate on {d['frames']} held-out frames (step {d.get('step', '?')}; "
             f"robot/object pixels {100 * d['object_pixel_share']:.1f}%)",
             f"  {'metric':<20} {'all pixels':>11} {'robot/object':>13}   aim"]
    for label, key, aim in rows:
        lines.append(f"  {label:<20} {d[key]:>11.4g} {d['object_' + key]:>13.4g}   {aim}")
    if "rgb_edge_sharpness" in d:  # gates stored before it was measured lack it
        lines.append(f"  {'RGB edge sharpness':<20} {d['rgb_edge_sharpness']:>11.4g} {'':>13}   (1 = as sharp as the truth)")
    lines.append(f"  meets the aims: {'yes' if d['meets_aims'] else 'no'}")
    return "\n".join(lines)


def reconstruction_sheet(model: RGBDNAutoencoder, frames: FrameSet, indices: list[int]) -> np.ndarray:
    """An image (uint8 (rows * 2 * H, 3 * W, 3)): per frame, the truth (upper row) and its reconstruction
    (lower row) as RGB | depth | normals, coloured like every preview."""
    ms = model.model_space
    x = frames.frames[indices].float()  # (n, 7, H, W)
    gt, pr = ms.decode(x), ms.decode(reconstruct_frames(model, x))
    valid = gt[1][gt[1] > 0]
    near, far = np.percentile(valid, [2, 90]) if valid.size else (ms.near_m, ms.far_m)  # the truth's range, for both
    rows = []
    for i in range(len(indices)):
        for rgb, depth, normal in (gt, pr):
            rows.append(np.concatenate([rgb[i], colorize_depth(depth[i], near, far), colorize_normals(normal[i])],
                                       axis=1))
    return np.concatenate(rows, axis=0)
