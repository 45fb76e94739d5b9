"""Does a predicted clip move the instructed object the right way?

The instructions of the tasks differ in their target: where the cube is pushed or pulled, which
way and how high it is lifted, onto which cube it is stacked. A prediction follows the
instruction when the object it moves ends up displaced like in the ground truth. We measure
that in the image, with no model of our own:

1. the object's pixel position over the ground-truth clip comes from its simulator pose
   projected with K and T_world_cam (``object_poses`` in the episode);
2. its position in the predicted last frame is the centre of the pixels of its first-frame
   colour (from its segmentation) near where it started;
3. the scores are the cosine between predicted and true displacement (1 = same direction,
   0 = no motion or perpendicular, -1 = opposite) and the endpoint error in pixels.

The same tracker run on the ground-truth last frame gives its error bound: ``tracker_px``.
Episodes whose true displacement is below ``min_motion_px`` say nothing about direction and
are skipped (``valid`` False).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from tesseract4d.geometry import invert_pose, project_points, transform_points

# The object each task's instruction is about (the one whose motion the instruction fixes).
# A clip moved its target object "the right way" when the cosine between the predicted and the
# true displacement exceeds this (within 60 degrees).
RIGHT_WAY_COSINE = 0.5
TARGET_OBJECT = {
    "PickCube-v1": "cube",
    "PushCube-v1": "cube",
    "PullCube-v1": "cube",
    "StackCube-v1": "cubeA",
    "PullCubeTool-v1": "cube",
}
# LiftPegUpright, PlugCharger and PegInsertionSide are left out: their objects are two-toned
# or move little in the image, so the colour tracker cannot measure them on the ground truth.


@dataclass
class DirectionScore:
    task: str
    valid: bool
    true_px: tuple[float, float]  # true displacement of the object, first → last frame (u, v)
    pred_px: tuple[float, float]  # displacement found in the prediction
    cosine: float  # cos(pred, true); 0 when the prediction does not move the object
    endpoint_error_px: float
    tracker_px: float  # tracker error on the ground-truth last frame (measurement noise)

    def to_dict(self) -> dict:
        return asdict(self)


def object_pixel_track(object_pose_world: np.ndarray, K: np.ndarray, T_world_cam: np.ndarray) -> np.ndarray:
    """Pixel position (T, 2) of an object's origin from its poses (T, 7: xyz + quaternion)."""
    xyz_world = np.asarray(object_pose_world, dtype=np.float64)[:, :3]
    T_cam_world = invert_pose(np.asarray(T_world_cam, dtype=np.float64))  # (T, 4, 4) or (4, 4)
    if T_cam_world.ndim == 2:
        T_cam_world = np.broadcast_to(T_cam_world, (len(xyz_world), 4, 4))
    K = np.broadcast_to(np.asarray(K, dtype=np.float64), (len(xyz_world), 3, 3))
    uv = [project_points(transform_points(T_cam_world[t], xyz_world[t]), K[t])[0] for t in range(len(xyz_world))]
    return np.stack(uv)


def track_colour(first_rgb: np.ndarray, object_mask: np.ndarray, target_rgb: np.ndarray,
                 colour_tol: float = 40.0, search_px: int = 24) -> tuple[float, float] | None:
    """Displacement (du, dv) of the object's colour blob from the first frame to ``target_rgb``.

    The object's colour is its mean first-frame colour; pixels of that colour which already
    lay outside the object in the first frame (a same-coloured goal, the other cube) are left
    out, and only a window of ``search_px`` around the start counts. Colour survives blur and
    partial occlusion by the gripper far better than template matching at 64x64.
    first_rgb, target_rgb: (H, W, 3) uint8; object_mask: (H, W) bool in the first frame.
    Returns None when the object is not visible in the first frame or not found in the target.
    """
    if not object_mask.any():
        return None
    colour = first_rgb[object_mask].astype(np.float32).mean(axis=0)
    distractors = (np.linalg.norm(first_rgb.astype(np.float32) - colour, axis=-1) < colour_tol) & ~object_mask
    found = (np.linalg.norm(target_rgb.astype(np.float32) - colour, axis=-1) < colour_tol) & ~distractors
    # Start = the same estimator on the first frame, so a static clip measures zero motion.
    vs, us = np.nonzero(object_mask & (np.linalg.norm(first_rgb.astype(np.float32) - colour, axis=-1) < colour_tol))
    if len(us) == 0:
        return None
    start = np.array([us.mean(), vs.mean()])
    v, u = np.nonzero(found)
    near = (np.abs(u - start[0]) < search_px) & (np.abs(v - start[1]) < search_px)
    if not near.any():
        return None
    return float(u[near].mean() - start[0]), float(v[near].mean() - start[1])


def direction_score(task: str, gt_rgb: np.ndarray, gt_segmentation: np.ndarray, seg_id_to_name: dict,
                    object_pose_world: np.ndarray, K: np.ndarray, T_world_cam: np.ndarray,
                    pred_last_rgb: np.ndarray, min_motion_px: float = 2.0) -> DirectionScore:
    """Score one predicted clip. gt_rgb (T, H, W, 3), gt_segmentation (T, H, W), pred_last_rgb (H, W, 3).

    Valid only when the true motion is at least ``min_motion_px`` and the tracker finds the
    object in the ground-truth last frame (so the measurement is possible). A prediction in
    which the object cannot be found, or moves less than half of ``min_motion_px``, scores 0.
    """
    name = TARGET_OBJECT.get(task)
    ids = [int(i) for i, n in seg_id_to_name.items() if n == name]
    track = object_pixel_track(object_pose_world, K[0] if np.ndim(K) == 3 else K,
                               T_world_cam[0] if np.ndim(T_world_cam) == 3 else T_world_cam)
    true = track[-1] - track[0]
    mask = np.isin(gt_segmentation[0], ids) if ids else np.zeros(gt_segmentation.shape[1:], bool)
    found_pred = track_colour(gt_rgb[0], mask, pred_last_rgb)
    found_gt = track_colour(gt_rgb[0], mask, gt_rgb[-1])
    true_norm = float(np.linalg.norm(true))
    valid = found_gt is not None and true_norm >= min_motion_px
    pred = np.asarray(found_pred if found_pred is not None else (0.0, 0.0), dtype=np.float64)
    pred_norm = float(np.linalg.norm(pred))
    # Sub-pixel shifts of the blob are noise, not motion: they score 0 like a static clip.
    moved = pred_norm >= min_motion_px / 2
    cosine = float(pred @ true / (pred_norm * true_norm)) if valid and moved else 0.0
    tracker = float(np.linalg.norm(np.asarray(found_gt) - true)) if found_gt is not None else float("nan")
    return DirectionScore(
        task=task, valid=bool(valid), true_px=(float(true[0]), float(true[1])), pred_px=(float(pred[0]), float(pred[1])),
        cosine=cosine, endpoint_error_px=float(np.linalg.norm(pred - true)), tracker_px=tracker,
    )


def summarize(scores: list[DirectionScore]) -> dict:
    """Mean cosine, share of clips moved the right way (cosine > RIGHT_WAY_COSINE), endpoint error, tracker noise."""
    valid = [s for s in scores if s.valid]
    if not valid:
        return {"episodes": 0}
    cos = np.array([s.cosine for s in valid])
    return {
        "episodes": len(valid),
        "mean_cosine": float(cos.mean()),
        "right_way": float((cos > RIGHT_WAY_COSINE).mean()),
        "endpoint_error_px": float(np.mean([s.endpoint_error_px for s in valid])),
        "tracker_px": float(np.nanmean([s.tracker_px for s in valid])),
    }
