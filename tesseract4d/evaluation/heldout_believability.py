"""The believability measures of :mod:`tesseract4d.evaluation.believability` on held-out episodes.

Per episode and per method (a predicted clip against the episode's ground truth):

- ``objects_present``: share of frames in which every scene object that the ground truth shows is
  in the prediction, in its colour, where it should be (goal ≥ ``PRESENCE_GOAL``). Scene objects
  are the segmentation's ids whose names are not the robot, the table, the ground, the background
  or a goal marker (:func:`tesseract4d.segments.scene_object_ids`).
- ``token_grid_ratio``: gradient energy across the checkpoint's token boundaries over that inside
  tokens (≈ 1 for the ground truth; the ground truth's own value is ``token_grid_ratio_gt``).
- ``edge_sharpness``: the prediction's gradient on the ground truth's strongest edges relative to
  the ground truth's (1 = as sharp).
- ``motion``: mean absolute RGB change from the first frame (0-255 units).
- a contrast entry (:func:`contrast_entry`) when the episode has a structured intent: the
  commanded world displacement of the instructed object projected into the image with K and
  T_world_cam, the displacement :func:`find_object` finds in the prediction's last frame, and
  whether it found the object there whole (not a smear, fragments or a copy of its colour); given
  the clip's depth, also which object its arm goes to, and the ground truth's
  (:mod:`tesseract4d.evaluation.arm_target`).

:func:`contrast_by_group` scores each counterfactual group (episodes sharing ``group_id``) with
:func:`believability.instruction_contrast`; :func:`breakdown` averages any per-episode metric per
skill and per task.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from tesseract4d.evaluation.believability import (MIN_OBJECT_PIXELS, PRESENCE_SLACK_PX, RIGHT_WAY_COSINE, STILL_SHARE,
                                                  edge_sharpness, instruction_contrast, objects_present, token_grid_ratio)
from tesseract4d.evaluation.arm_target import arm_visit
from tesseract4d.evaluation.instruction_following import object_pixel_track
from tesseract4d.intervals import wilson_interval
from tesseract4d.object_colours import dilate, distinctive, matches
from tesseract4d.segments import scene_object_ids

PRESENCE_GOAL = 0.95  # goal: every visible object present in at least 95 % of frames
CONTRAST_GOAL = 0.70  # goal: at least 70 % of a group's instructions right
TOKEN_GRID_GOAL = (0.8, 1.25)  # ground truth at 64-128 px measures 0.95-1.16; outside this a grid shows
EDGE_SHARPNESS_GOAL = 0.8  # the prediction keeps at least 80 % of the ground truth's edge contrast
# Skills whose intent moves no object (the gripper's goal is what they fix): no contrast entry.
GRIPPER_ONLY_SKILLS = ("hover", "reach")
# A tracked displacement shorter than this (pixels) is noise, not motion (as instruction_following).
MIN_PREDICTED_PX = 1.0
# find_object's "whole": matched pixels within this share range of the object's distinctive first-frame
# pixels, and their RMS radius at most WHOLE_MAX_SPREAD x the first frame's + WHOLE_SPREAD_SLACK_PX. On
# the ground truth's last frames of the held-out groups (128², 65 tracked objects; one lifted out of the
# search window is not found at all) the share runs 0.65-2.25 and the radius 0.81-1.52x; a second
# copy of a 5 px cube 10 px away spreads it 2.6x.
WHOLE_PIXELS = (0.3, 3.0)
WHOLE_MAX_SPREAD = 1.6
WHOLE_SPREAD_SLACK_PX = 1.0
BELIEVABILITY_METRICS = ("objects_present", "token_grid_ratio", "edge_sharpness", "motion")


def clip_motion(rgb: np.ndarray) -> float:
    """Mean absolute change of a (T, H, W, 3) clip over its predicted frames: from frame 1 (the first
    predicted frame) to every later one. Frame 0 is the given first frame; a latent model's frames
    are decoded by its autoencoder, whose constant reconstruction error against the given frame
    is not motion. A clip of two frames: the change from frame 0 to frame 1."""
    x = np.asarray(rgb, np.float32)
    if len(x) < 2:
        return 0.0
    if len(x) == 2:
        return float(np.abs(x[1] - x[0]).mean())
    return float(np.abs(x[2:] - x[1:2]).mean())


def commanded_px(intent: dict, start_xyz_world: np.ndarray, K: np.ndarray, T_world_cam: np.ndarray) -> tuple[float, float]:
    """The intent's commanded world displacement of its target, seen in the image: (du, dv) pixels.

    start_xyz_world: (3,) the target's position in the first frame; K (3, 3); T_world_cam (4, 4).
    """
    start = np.asarray(start_xyz_world, np.float64)[:3]
    end = start + np.asarray(intent["commanded_displacement_world_m"], np.float64)
    poses = np.zeros((2, 7))
    poses[:, 3] = 1.0  # identity quaternion (wxyz); only the position is projected
    poses[0, :3], poses[1, :3] = start, end
    uv = object_pixel_track(poses, K, T_world_cam)  # (2, 2)
    d = uv[1] - uv[0]
    return float(d[0]), float(d[1])


SEARCH_FRACTION = 24 / 64  # the tracker's window half-size as a share of the image width (24 px at 64x64)


@dataclass
class FoundObject:
    """Where :func:`find_object` found an object in a target frame."""

    du: float  # displacement of its centroid from the first frame's (pixels)
    dv: float
    whole: bool  # found as one object of about its size, not a smear, a fragment or a copy (see WHOLE_*)
    pixels_share: float  # matched pixels / the object's distinctive pixels in the first frame
    spread_ratio: float  # RMS radius of the matched pixels / the first frame's


def find_object(first_rgb: np.ndarray, object_mask: np.ndarray, target_rgb: np.ndarray,
                search_px: int | None = None) -> FoundObject | None:
    """The object of ``object_mask`` (in the ground truth's first frame) found in ``target_rgb``.

    The colour tracker of :mod:`instruction_following` with the object's *distinctive* colours (as
    :func:`believability.objects_present`: its first-frame pixels unlike everything around it) in
    place of its mean colour, which a shaded cube (lit top, dark sides) may match nowhere. Pixels of
    those colours that lay outside the object in the first frame (a same-coloured goal or object)
    are left out, and only a window of ``search_px`` (default: ``SEARCH_FRACTION`` of the image
    width, at least 24 px, so the window covers the same part of the scene at any resolution)
    around the start counts; the start is the same estimator on the first frame, so a static clip
    measures zero motion.

    The displacement is that of the matched pixels' centroid, which a smear of the object's colour
    also moves. So the object also counts as found *whole* only when the matched pixels number
    ``WHOLE_PIXELS`` (a share range) of its distinctive first-frame pixels and their RMS radius
    around their centroid is at most ``WHOLE_MAX_SPREAD`` times the first frame's plus
    ``WHOLE_SPREAD_SLACK_PX``: a streak, a cloud of fragments or a second copy spreads wider, a
    fading object matches too few pixels, a flood of its colour too many.
    first_rgb, target_rgb: (H, W, 3) uint8; object_mask: (H, W) bool. None when the object is not
    visible (or not distinctive) in the first frame, or not found in the target.
    """
    mask = np.asarray(object_mask, bool)
    if mask.sum() < MIN_OBJECT_PIXELS:
        return None
    rgb0 = np.asarray(first_rgb, np.float32)
    W = mask.shape[1]
    if search_px is None:
        search_px = max(24, round(SEARCH_FRACTION * W))
    keep = distinctive(rgb0, mask, PRESENCE_SLACK_PX)
    palette = rgb0[mask][keep]
    if not len(palette):
        return None
    vs, us = np.nonzero(mask)
    start = np.array([us[keep].mean(), vs[keep].mean()])
    spread0 = _rms_radius(us[keep], vs[keep])
    distractors = matches(rgb0, palette) & ~dilate(mask, 1)
    v, u = np.nonzero(matches(target_rgb, palette) & ~distractors)
    near = (np.abs(u - start[0]) < search_px) & (np.abs(v - start[1]) < search_px)
    if not near.any():
        return None
    u, v = u[near], v[near]
    share = len(u) / len(palette)
    spread = _rms_radius(u, v)
    whole = bool(WHOLE_PIXELS[0] <= share <= WHOLE_PIXELS[1]
                 and spread <= WHOLE_MAX_SPREAD * spread0 + WHOLE_SPREAD_SLACK_PX)
    return FoundObject(float(u.mean() - start[0]), float(v.mean() - start[1]), whole, float(share),
                       spread / max(spread0, 1e-6))


def _rms_radius(u: np.ndarray, v: np.ndarray) -> float:
    """Root mean square distance of pixels (u, v) from their centroid."""
    return float(np.sqrt(((u - u.mean()) ** 2 + (v - v.mean()) ** 2).mean()))


def track_object(first_rgb: np.ndarray, object_mask: np.ndarray, target_rgb: np.ndarray,
                 search_px: int | None = None) -> tuple[float, float] | None:
    """Displacement (du, dv) of an object from the ground truth's first frame to ``target_rgb``
    (:func:`find_object`'s centroid displacement), or None where it finds nothing."""
    found = find_object(first_rgb, object_mask, target_rgb, search_px)
    return None if found is None else (found.du, found.dv)


def contrast_entry(gt, camera: str, pred_rgb: np.ndarray, pred_depth_m: np.ndarray | None = None) -> dict | None:
    """The :func:`believability.instruction_contrast` entry of one predicted clip, or None when the
    episode has no intent (version-1 data), its skill moves no object (hover/reach), or its target
    is not recorded. gt: the ground-truth Episode; pred_rgb: (T, H, W, 3) uint8. With ``pred_depth_m``
    (T, H, W) an active entry also says which object the arm goes to, in the prediction and in the
    ground truth (:mod:`tesseract4d.evaluation.arm_target`; ``arm_object``, ``arm_object_truth``)."""
    intent = gt.intent
    if not intent or intent.get("skill") in GRIPPER_ONLY_SKILLS:
        return None
    entry = {"instruction": gt.instruction, "skill": intent.get("skill"), "variant": intent.get("variant"),
             "still": intent.get("skill") == "keep_still", "motion": clip_motion(pred_rgb),
             "commanded_px": None, "predicted_px": (0.0, 0.0), "whole": False}
    if entry["still"]:
        return entry
    target = intent.get("target")
    cam = gt.cameras[camera]
    if target not in gt.object_poses:
        return None
    K, T = np.asarray(cam.K), np.asarray(cam.T_world_cam)
    K0, T0 = (K[0] if K.ndim == 3 else K), (T[0] if T.ndim == 3 else T)
    entry["commanded_px"] = commanded_px(intent, gt.object_poses[target][0, :3], K0, T0)
    ids = [int(i) for i, n in cam.seg_id_to_name.items() if n == target]
    if cam.segmentation is not None and ids:
        found = find_object(np.asarray(cam.rgb[0]), np.isin(cam.segmentation[0], ids), np.asarray(pred_rgb[-1]))
        if found is not None:
            entry["whole"] = found.whole
            if float(np.hypot(found.du, found.dv)) >= MIN_PREDICTED_PX:
                entry["predicted_px"] = (found.du, found.dv)
    if pred_depth_m is not None:
        truth = arm_visit(gt, camera, cam.rgb, cam.depth_m)
        if truth.judged:
            entry.update(target=target, arm_object=arm_visit(gt, camera, pred_rgb, pred_depth_m).object,
                         arm_object_truth=truth.object)
    return entry


def episode_believability(gt, camera: str, pred_rgb: np.ndarray, patch_px: int | None,
                          token_rgb: np.ndarray | None = None, pred_depth_m: np.ndarray | None = None,
                          first_scored_frame: int = 0) -> dict:
    """Every believability measure of one predicted clip (see the module docstring). ``patch_px``:
    the model's token size in pixels of ``token_rgb`` (default ``pred_rgb``), the clip whose token
    grid is measured (a prediction resized to the data's resolution is measured as the model made
    it); None = no token grid to measure (NaN). ``pred_depth_m``: the clip's depth, for where its arm goes
    (:func:`contrast_entry`).

    Returns ``{"metrics": {objects_present, token_grid_ratio, edge_sharpness, motion},
    "per_object": {name: share}, "contrast_entry": dict | None}``. Frames are matched by index.
    ``first_scored_frame``: permanence, token grid and edge sharpness count frames from this one on
    (1 for a prediction, whose frame 0 is given); motion and the contrast read the whole clip
    (they measure change from frame 0).
    """
    cam = gt.cameras[camera]
    gt_rgb = np.asarray(cam.rgb)
    pred_rgb = np.asarray(pred_rgb)
    n = min(len(gt_rgb), len(pred_rgb))
    gt_rgb, pred_rgb = gt_rgb[:n], pred_rgb[:n]
    f = first_scored_frame if first_scored_frame < n else 0  # a clip of given frames only: scored whole
    token_clip = pred_rgb if token_rgb is None else np.asarray(token_rgb)[:n]
    metrics = {"objects_present": float("nan"),
               "token_grid_ratio": float("nan") if patch_px is None else token_grid_ratio(token_clip[f:], patch_px),
               "edge_sharpness": edge_sharpness(pred_rgb[f:], gt_rgb[f:]), "motion": clip_motion(pred_rgb)}
    per_object = {}
    if cam.segmentation is not None:
        ids = scene_object_ids(cam.seg_id_to_name)
        presence = objects_present(gt_rgb[f:], np.asarray(cam.segmentation)[f:n], ids, pred_rgb[f:])
        metrics["objects_present"] = presence.frames_all_present
        per_object = {cam.seg_id_to_name[i]: v for i, v in presence.per_object.items()}
    return {"metrics": metrics, "per_object": per_object,
            "contrast_entry": contrast_entry(gt, camera, pred_rgb,
                                             None if pred_depth_m is None else np.asarray(pred_depth_m)[:n])}


def contrast_by_group(entries: list[tuple[str, dict]]) -> dict:
    """Score counterfactual groups. entries: (group_id, contrast entry) pairs of one method.

    Returns ``{"instructions", "right", "share", "wilson95": [low, high], "groups",
    "still_instructions", "still_right", "active_instructions", "active_right", "arm_measured",
    "arm_judged", "arm_instructed", "arm_judged_wrong", "arm_instructed_wrong", "right_whole",
    "share_whole", "wilson95_whole", "per_skill": {skill: share}, "per_task": {env_id: share},
    "per_group": {group_id: [rows]}}``; "keep still" is only judged in a group with an active
    instruction (its right/wrong is relative to them). ``active_right`` counts the active
    instructions right: a model that never moves gets every "keep still" right and scores the
    share of "keep still" instructions, so the two parts are reported apart as well. ``arm_instructed``
    of ``arm_judged``: active instructions whose arm goes to the instructed object
    (:mod:`~tesseract4d.evaluation.arm_target`), judged where the entry has it (``arm_measured``) and the
    ground truth's own arm is found at the instructed object; ``arm_instructed_wrong`` of
    ``arm_judged_wrong``: the same over those whose contrast is wrong (the arm at the object, the contact
    lost). ``wilson95``
    is the share's 95 % Wilson interval: with a few dozen instructions a model's share is known to
    about ±0.15. ``right_whole``: the right ones whose instructed object was also found whole
    (:func:`find_object`; "keep still" as judged), so a smear of the object's colour that moves the
    centroid the commanded way does not count.
    """
    groups: dict[str, list[dict]] = {}
    for gid, e in entries:
        groups.setdefault(gid, []).append(e)
    rows, per_group = [], {}
    for gid, group in groups.items():
        result = instruction_contrast(group)
        for row, e in zip(result.per_instruction, group):
            row.update(skill=e.get("skill"), variant=e.get("variant"))
            if not e["still"]:
                row.update(commanded_px=list(e["commanded_px"]), predicted_px=list(e["predicted_px"]),
                           whole=bool(e.get("whole", False)))
                if "arm_object_truth" in e:
                    row.update(target=e["target"], arm_object=e["arm_object"], arm_object_truth=e["arm_object_truth"])
            row["right_whole"] = bool(row["right"]) and (bool(e["still"]) or row["whole"])
        per_group[gid] = result.per_instruction
        rows += result.per_instruction
    per_skill: dict[str, list[bool]] = {}
    per_task: dict[str, list[bool]] = {}
    for gid, group_rows in per_group.items():
        for r in group_rows:
            per_skill.setdefault(r["skill"] or "?", []).append(r["right"])
            per_task.setdefault(gid.split("/")[0], []).append(r["right"])
    right = sum(bool(r["right"]) for r in rows)
    right_whole = sum(r["right_whole"] for r in rows)
    still = [bool(r["right"]) for r in rows if r.get("still")]
    active = [bool(r["right"]) for r in rows if not r.get("still")]
    # Where the arm goes, judged where the measure finds the ground truth's own arm at the instructed object.
    measured = [r for r in rows if "arm_object_truth" in r]
    judged = [r for r in measured if r["arm_object_truth"] == r["target"]]
    wrong = [r for r in judged if not r["right"]]
    return {"instructions": len(rows), "right": right, "share": right / len(rows) if rows else float("nan"),
            "wilson95": list(wilson_interval(right, len(rows))), "groups": len(groups),
            "right_whole": right_whole, "share_whole": right_whole / len(rows) if rows else float("nan"),
            "wilson95_whole": list(wilson_interval(right_whole, len(rows))),
            "still_instructions": len(still), "still_right": sum(still),
            "active_instructions": len(active), "active_right": sum(active),
            "arm_measured": len(measured), "arm_judged": len(judged),
            "arm_instructed": sum(r["arm_object"] == r["target"] for r in judged),
            "arm_judged_wrong": len(wrong), "arm_instructed_wrong": sum(r["arm_object"] == r["target"] for r in wrong),
            "per_skill": {s: float(np.mean(v)) for s, v in sorted(per_skill.items())},
            "per_task": {t: float(np.mean(v)) for t, v in sorted(per_task.items())},
            "per_group": per_group, "right_way_cosine": RIGHT_WAY_COSINE, "still_share": STILL_SHARE}


def _finite_mean(values) -> float:
    v = np.asarray([x for x in values if x is not None], np.float64)
    v = v[np.isfinite(v)]
    return float(v.mean()) if len(v) else float("nan")


def breakdown(rows: list[dict], methods, by: str) -> dict:
    """Mean of every metric of ``row["metrics"][method]`` per value of ``row[by]`` ("task" or "skill")."""
    out = {}
    for key in sorted({r[by] for r in rows}):
        sel = [r for r in rows if r[by] == key]
        out[key] = {m: {k: _finite_mean(r["metrics"][m].get(k) for r in sel) for k in sel[0]["metrics"][m]}
                    for m in methods}
    return out


def counts(rows: list[dict], by: str) -> dict:
    """Number of episodes per value of ``row[by]`` (an episode scored with several noise seeds, one
    row each, counts once)."""
    seen: dict = {}
    for i, r in enumerate(rows):
        seen.setdefault(r[by], set()).add(r.get("episode", i))
    return {k: len(v) for k, v in sorted(seen.items())}


def goal_met(key: str, value) -> bool | None:
    """Whether a summary value meets the project's goal; None when there is none or no value."""
    if value is None or not np.isfinite(value):
        return None
    if key == "objects_present":
        return value >= PRESENCE_GOAL
    if key in ("contrast", "contrast_whole"):
        return value >= CONTRAST_GOAL
    if key == "token_grid_ratio":
        return TOKEN_GRID_GOAL[0] <= value <= TOKEN_GRID_GOAL[1]
    if key == "edge_sharpness":
        return value >= EDGE_SHARPNESS_GOAL
    return None


def direction_breakdown(rows: list[dict], methods, by: str) -> dict:
    """Right-way instruction following (``row["direction"][method]``, valid clips only) per value of
    ``row[by]``: {key: {method: {"episodes", "right_way", "mean_cosine"}}}; keys without a valid clip are left out."""
    out = {}
    for key in sorted({r[by] for r in rows}):
        per_method = {}
        for m in methods:
            cos = [r["direction"][m]["cosine"] for r in rows
                   if r[by] == key and m in r.get("direction", {}) and r["direction"][m]["valid"]]
            if cos:
                per_method[m] = {"episodes": len(cos), "right_way": float(np.mean(np.asarray(cos) > RIGHT_WAY_COSINE)),
                                 "mean_cosine": float(np.mean(cos))}
        if per_method:
            out[key] = per_method
    return out
