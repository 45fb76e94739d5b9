"""Does a prediction look like a world a person believes? Measures beyond pixel error.

- **Token grid** (:func:`token_grid_ratio`): a transformer that draws each token's patch separately
  leaves seams on the patch grid. The ratio of the image-gradient energy across token boundaries
  to the energy between neighbouring pixels inside a token is about 1 for a real image (edges fall
  anywhere) and grows with visible blocks.
- **Edge sharpness** (:func:`edge_sharpness`): the prediction's gradient magnitude on the ground
  truth's strongest edges, relative to the ground truth's own (1 = as sharp, < 1 blurred).
- **Object permanence** (:func:`objects_present`): in every frame, is every object that the ground
  truth shows also in the prediction, in its colour and where it should be? A small cube that
  dissolves into the arm fails this even when the pixel error barely changes.
- **Instruction contrast** (:func:`instruction_contrast`): across one counterfactual group (one
  first frame, several instructions), does each prediction move the instructed object the
  instructed way, and does "keep still" leave the scene still?

Images are (T, H, W, 3) uint8 RGB; masks and segmentations (T, H, W). Pure functions, no I/O.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from tesseract4d.object_colours import MIN_OBJECT_PIXELS, OBJECT_COLOUR_TOL, dilate, distinctive, min_colour_distance

# A present object shows at least this share of its true pixel count in its colour near its true place.
MIN_PRESENT_FRACTION = 0.3
# How far (pixels) from its true silhouette a predicted object may be and still count as in place.
PRESENCE_SLACK_PX = 2
# Objects smaller than MIN_OBJECT_PIXELS (object_colours.py) in a ground-truth frame are not judged there.
# A prediction moves the instructed object the instructed way when cos(predicted, commanded) > this.
RIGHT_WAY_COSINE = 0.5
# "Keep still" is right when its predicted motion is at most this share of the group's active motions.
STILL_SHARE = 0.10
# Share of ground-truth pixels with the strongest gradients taken as its edges.
EDGE_QUANTILE = 0.9


def _gray(rgb: np.ndarray) -> np.ndarray:
    return np.asarray(rgb, np.float32) @ np.array([0.299, 0.587, 0.114], np.float32)


def token_grid_ratio(rgb: np.ndarray, patch_px: int) -> float:
    """Gradient energy across token boundaries over energy inside tokens (≈ 1 for real images).

    rgb: (T, H, W, 3) or (H, W, 3); patch_px: the token's size in pixels (4 for the ``tiny`` preset).
    Horizontal and vertical neighbour differences both count; a boundary difference is between
    pixels ``k * patch_px - 1`` and ``k * patch_px``.
    """
    g = _gray(rgb)
    g = g[None] if g.ndim == 2 else g  # (T, H, W)
    if patch_px < 2 or min(g.shape[1:]) <= patch_px:
        raise ValueError(f"patch_px must be >= 2 and smaller than the image, got {patch_px} for {g.shape[1:]}")
    dx = np.diff(g, axis=2) ** 2  # (T, H, W-1): difference between column j and j+1
    dy = np.diff(g, axis=1) ** 2  # (T, H-1, W)
    bx = (np.arange(dx.shape[2]) + 1) % patch_px == 0
    by = (np.arange(dy.shape[1]) + 1) % patch_px == 0
    boundary = np.concatenate([dx[:, :, bx].ravel(), dy[:, by, :].ravel()])
    inside = np.concatenate([dx[:, :, ~bx].ravel(), dy[:, ~by, :].ravel()])
    return float(boundary.mean() / max(float(inside.mean()), 1e-6))


def _gradient_magnitude(g: np.ndarray) -> np.ndarray:
    gy, gx = np.gradient(g, axis=(-2, -1))
    return np.sqrt(gx**2 + gy**2)


def edge_sharpness(pred_rgb: np.ndarray, gt_rgb: np.ndarray) -> float:
    """Mean gradient magnitude of the prediction on the ground truth's strongest edges (top
    ``1 - EDGE_QUANTILE`` of its gradients, per frame), relative to the ground truth's: 1 = as sharp."""
    pg, gg = _gradient_magnitude(_gray(pred_rgb)), _gradient_magnitude(_gray(gt_rgb))
    if pg.shape != gg.shape:
        raise ValueError(f"prediction {pg.shape} and ground truth {gg.shape} differ in shape")
    gg3, pg3 = (gg[None], pg[None]) if gg.ndim == 2 else (gg, pg)
    thresholds = np.quantile(gg3.reshape(len(gg3), -1), EDGE_QUANTILE, axis=1)[:, None, None]
    edges = gg3 >= np.maximum(thresholds, 1e-3)
    if not edges.any():
        return float("nan")
    return float(pg3[edges].mean() / max(float(gg3[edges].mean()), 1e-6))


@dataclass
class Presence:
    frames_all_present: float  # share of judged frames in which every visible object is present
    per_object: dict[int, float]  # object id -> share of its judged frames in which it is present
    judged_frames: int


def objects_present(gt_rgb: np.ndarray, gt_segmentation: np.ndarray, object_ids: list[int],
                    pred_rgb: np.ndarray) -> Presence:
    """Object permanence of a predicted clip against its ground truth.

    An object is judged in a frame where the ground truth shows at least ``MIN_OBJECT_PIXELS`` of
    it. Its colours in that frame are the ground truth's colours of its *distinctive* pixels: those
    farther than ``OBJECT_COLOUR_TOL`` from every colour the ground truth shows around it (within
    ``PRESENCE_SLACK_PX``), so a shaded cube keeps its lit top and its darker sides while edge pixels
    blended into the table are left out (an object with no distinctive pixel in a frame is not judged
    there). It is present when at least ``MIN_PRESENT_FRACTION`` of that many predicted pixels within
    ``PRESENCE_SLACK_PX`` of its true silhouette are within ``OBJECT_COLOUR_TOL`` of its colours.
    Since its colours differ from everything around it in the ground truth, a prediction cannot pass
    by showing the table, the arm or a same-coloured goal where the object should be.
    gt_rgb, pred_rgb: (T, H, W, 3) uint8; gt_segmentation: (T, H, W) ids.
    """
    gt = np.asarray(gt_rgb, np.float32)
    pred = np.asarray(pred_rgb, np.float32)
    if gt.shape != pred.shape:
        raise ValueError(f"prediction {pred.shape} and ground truth {gt.shape} differ in shape")
    seg = np.asarray(gt_segmentation)
    T = gt.shape[0]
    judged = np.zeros(T, bool)
    all_present = np.ones(T, bool)
    per_object: dict[int, float] = {}
    for oid in object_ids:
        masks = seg == oid  # (T, H, W)
        hits = []
        for t in np.nonzero(masks.reshape(T, -1).sum(axis=1) >= MIN_OBJECT_PIXELS)[0]:
            near = dilate(masks[t], PRESENCE_SLACK_PX)
            palette = gt[t][masks[t]][distinctive(gt[t], masks[t], PRESENCE_SLACK_PX)]
            if len(palette) == 0:
                continue
            found = min_colour_distance(pred[t][near], palette) < OBJECT_COLOUR_TOL
            ok = bool(found.sum() >= MIN_PRESENT_FRACTION * len(palette))
            hits.append(ok)
            judged[t] = True
            all_present[t] &= ok
        if hits:
            per_object[int(oid)] = float(np.mean(hits))
    n = int(judged.sum())
    return Presence(float(all_present[judged].mean()) if n else float("nan"), per_object, n)


@dataclass
class ContrastResult:
    instructions: int
    right: int
    per_instruction: list[dict]

    @property
    def share(self) -> float:
        return self.right / self.instructions if self.instructions else float("nan")


def instruction_contrast(group: list[dict]) -> ContrastResult:
    """Score one counterfactual group (the same first frame under several instructions).

    Each entry: ``{"instruction": str, "still": bool, "commanded_px": (du, dv) or None,
    "predicted_px": (du, dv), "motion": float}`` — ``commanded_px`` the instructed object's
    commanded displacement in the image, ``predicted_px`` its displacement found in the
    prediction, ``motion`` the prediction's overall motion (e.g. mean absolute change from the
    first frame). An active instruction is right when cos(predicted, commanded) > ``RIGHT_WAY_COSINE``;
    "keep still" is right when its motion is at most ``STILL_SHARE`` of the mean motion of the
    group's active predictions.
    """
    active = [g for g in group if not g["still"]]
    active_motion = float(np.mean([g["motion"] for g in active])) if active else float("nan")
    rows = []
    for g in group:
        if g["still"]:
            ok = bool(active) and g["motion"] <= STILL_SHARE * active_motion
            rows.append({"instruction": g["instruction"], "still": True, "motion": float(g["motion"]),
                         "active_motion": active_motion, "right": ok})
            continue
        c = np.asarray(g["commanded_px"], np.float64)
        p = np.asarray(g["predicted_px"], np.float64)
        denom = float(np.linalg.norm(c) * np.linalg.norm(p))
        cos = float(c @ p / denom) if denom > 0 else 0.0
        rows.append({"instruction": g["instruction"], "still": False, "cosine": cos, "right": cos > RIGHT_WAY_COSINE})
    return ContrastResult(len(rows), sum(r["right"] for r in rows), rows)
