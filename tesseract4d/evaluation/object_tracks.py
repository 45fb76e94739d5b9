"""The object layer of a reconstruction scored against the simulator's stored object poses
(``object_poses/<name>``, xyz + quaternion wxyz per frame).

Each track is matched to a recorded object by name (a segmentation names both alike), else to the
recorded object nearest its first-frame position within ``MATCH_RADIUS_M``. Its error at frame t is the
distance between where the track puts the recorded object's origin (the origin at frame 0, carried by
the track's motion: ``T_world_object[t] inv(T_world_object[0]) p_truth[0]``) and where the simulator
has it; the choice of the track's own origin (the centroid of the points it saw) does not matter.

Per object: ``final_error_m`` (last frame), ``mean_error_m`` (frames ``first_scored_frame`` on), ``yaw_error_deg``
(last frame: the track's turn about the scene's up axis since frame 0 against the truth's),
``displacement_truth_m`` / ``displacement_m`` (last frame from the first), ``displacement_error_m``
(the two displacement vectors apart: the final error, measured from the shared start), ``lost_frames``,
``inferred_frames`` (frames placed by the arm's or the hand's motion, not seen), ``seen_final_error_m`` (where
the track last saw it, its last ``tracked`` frame, against where the truth ends), ``in_view_at_end`` (the truth's
origin at the last frame projects inside that frame's image: an object carried out of the camera's view cannot be
placed by any tracker of this camera's frames).

Summary: the instructed object (the episode intent's target, else the task's target object; none for
"keep still" and gripper-only skills) ``ended_within_2cm`` of the truth; every other object the truth kept
still (moved at most ``STILL_TRUTH_M``) ``stayed_within_1cm`` of the truth in every frame; the share of
objects whose final error is at most ``CEILING_M`` (the tracker's goal on the truth itself), also over the objects in
view at the end only (``within_5mm_in_view``); recorded
objects no track matched count as ``missing`` (and fail both measures).
"""

from __future__ import annotations

import math

import numpy as np

from reconstruction.objects import INFERRED, LOST, TRACKED, ObjectLayer, episode_objects, matrix_from_wxyz, yaw_about
from reconstruction.recon4d import Recon4D
from tesseract4d.dataset_format import CameraFrames, Episode
from tesseract4d.evaluation.instruction_following import TARGET_OBJECT
from tesseract4d.geometry import invert_pose, project_points, scene_up_axis, transform_points
from tesseract4d.segments import NOT_OBJECTS

MATCH_RADIUS_M = 0.05
ENDED_WITHIN_M = 0.02
STAYED_WITHIN_M = 0.01
STILL_TRUTH_M = 0.005
CEILING_M = 0.005
# Skills whose instruction moves no object (the gripper only).
NO_OBJECT_SKILLS = ("hover", "reach", "keep_still")

DEFINITIONS = {
    "final_error_m": "distance at the last frame between where the track carries the recorded object's first-frame "
                     "origin and where the simulator has it, metres",
    "mean_error_m": "the same, mean over the scored frames",
    "yaw_error_deg": "last frame: the track's turn about the up axis since frame 0 minus the truth's, degrees (absolute)",
    "instructed_within_2cm": f"the instructed object ended within {100 * ENDED_WITHIN_M:g} cm of the truth (1/0)",
    "others_still_within_1cm": f"share of the other objects the truth kept still (moved <= {1000 * STILL_TRUTH_M:g} mm) "
                               f"that stayed within {100 * STAYED_WITHIN_M:g} cm of the truth in every frame",
    "within_5mm": f"share of the objects whose final error is <= {1000 * CEILING_M:g} mm (the tracker's goal on the truth)",
    "within_5mm_in_view": "the same over the objects whose true position at the last frame is inside the image",
    "lost_share": "share of object-frames the layer reports lost",
    "inferred_share": "share of object-frames the layer placed by the arm's or the hand's motion, not seen",
    "instructed_seen_within_2cm": f"where the layer last saw the instructed object (its last tracked frame) lies within "
                                  f"{100 * ENDED_WITHIN_M:g} cm of where the truth ends (1/0): the instructed row without "
                                  f"what the layer inferred",
}


def instructed_object(gt: Episode) -> str | None:
    """The recorded name of the object the episode's instruction is about, or None."""
    intent = gt.intent or {}
    if intent.get("skill") in NO_OBJECT_SKILLS:
        return None
    target = intent.get("target") or TARGET_OBJECT.get(gt.env_id)
    return target if target in gt.object_poses else None


def recorded_objects(gt: Episode, camera: str) -> list[str]:
    """The scene objects of the ground truth that can be scored: recorded poses, seen in the first frame
    where the episode has a segmentation, never a goal marker or scenery."""
    names = [n for n in gt.object_poses if not str(n).startswith(NOT_OBJECTS)]
    cam = gt.cameras[camera]
    if cam.segmentation is not None and cam.seg_id_to_name:
        seen = {cam.seg_id_to_name.get(int(i)) for i in np.unique(cam.segmentation[0])}
        names = [n for n in names if n in seen]
    return names


def _truth_T(pose: np.ndarray) -> np.ndarray:
    """(T, 4, 4) object -> world of recorded poses (T, 7) xyz + wxyz."""
    pose = np.asarray(pose, np.float64)
    T = np.repeat(np.eye(4)[None], len(pose), 0)
    for t, p in enumerate(pose):
        T[t, :3, :3] = matrix_from_wxyz(p[3:7])
        T[t, :3, 3] = p[:3]
    return T


def in_view(point_world: np.ndarray, K: np.ndarray, T_world_cam: np.ndarray, height: int, width: int) -> bool:
    """Whether a world point projects in front of the camera and inside its ``height`` x ``width`` image."""
    p_cam = transform_points(invert_pose(np.asarray(T_world_cam, np.float64)), np.asarray(point_world, np.float64)[None])
    if p_cam[0, 2] <= 0:
        return False
    uv, _ = project_points(p_cam, np.asarray(K, np.float64))
    u, v = uv[0]
    return bool(0 <= u < width and 0 <= v < height)  # pixel (i, j) spans u in [j, j + 1)


def match_tracks(layer: ObjectLayer, gt: Episode, names: list[str]) -> dict[str, int]:
    """Recorded name -> track index: by name first, then the nearest unmatched track within MATCH_RADIUS_M."""
    out: dict[str, int] = {}
    used: set[int] = set()
    for name in names:
        for k, tr in enumerate(layer.tracks):
            if tr.name == name and k not in used:
                out[name] = k
                used.add(k)
                break
    for name in names:
        if name in out:
            continue
        p0 = np.asarray(gt.object_poses[name][0, :3], np.float64)
        best = min(((np.linalg.norm(tr.T_world_object[0, :3, 3] - p0), k) for k, tr in enumerate(layer.tracks)
                    if k not in used), default=(np.inf, -1))
        if best[0] <= MATCH_RADIUS_M:
            out[name] = best[1]
            used.add(best[1])
    return out


def object_track_metrics(layer: ObjectLayer, gt: Episode, camera: str | None = None, first_scored_frame: int = 1) -> dict:
    """Score ``layer`` against ``gt``'s recorded poses (see the module docstring). Frames are matched by
    index over the frames both have. Returns ``{"per_object": {name: {...}}, "instructed": name | None,
    "missing": [names], "summary": {...}}``; NaN where nothing is measured."""
    camera = camera or next(iter(gt.cameras))
    names = recorded_objects(gt, camera)
    instructed = instructed_object(gt)
    matched = match_tracks(layer, gt, names)
    up = scene_up_axis(np.asarray(gt.cameras[camera].T_world_cam)[0])
    per_object = {}
    for name in names:
        if name not in matched:
            continue
        tr = layer.tracks[matched[name]]
        T_true = _truth_T(gt.object_poses[name])
        n = min(len(T_true), tr.num_frames)
        T_pred = tr.T_world_object[:n]
        origin = np.linalg.inv(T_pred[0]) @ np.r_[T_true[0, :3, 3], 1.0]
        pred = np.einsum("tij,j->ti", T_pred, origin)[:, :3]
        true = T_true[:n, :3, 3]
        err = np.linalg.norm(pred - true, axis=1)
        first = first_scored_frame if first_scored_frame < n else 0
        yaw_pred = yaw_about(T_pred[-1, :3, :3] @ T_pred[0, :3, :3].T, up)
        yaw_true = yaw_about(T_true[n - 1, :3, :3] @ T_true[0, :3, :3].T, up)
        yaw_err = abs(math.degrees(math.remainder(yaw_pred - yaw_true, 2 * math.pi)))
        still = float(np.linalg.norm(true - true[0], axis=1).max()) <= STILL_TRUTH_M
        frames = gt.cameras[camera]
        visible_end = in_view(true[-1], frames.K[n - 1], frames.T_world_cam[n - 1], *frames.depth_m.shape[1:3])
        seen = np.flatnonzero(np.asarray(tr.state[:n]) == TRACKED)
        last_seen = int(seen[-1]) if len(seen) else 0
        per_object[name] = {
            "track": tr.name, "final_error_m": float(err[-1]), "mean_error_m": float(err[first:].mean()),
            "max_error_m": float(err.max()), "yaw_error_deg": yaw_err,
            "displacement_truth_m": float(np.linalg.norm(true[-1] - true[0])),
            "displacement_m": float(np.linalg.norm(pred[-1] - pred[0])),
            "displacement_error_m": float(np.linalg.norm((pred[-1] - pred[0]) - (true[-1] - true[0]))),
            "still_in_truth": still, "stayed_within_1cm": bool(err.max() <= STAYED_WITHIN_M),
            "lost_frames": int((np.asarray(tr.state[:n]) == LOST).sum()),
            "inferred_frames": int((np.asarray(tr.state[:n]) == INFERRED).sum()), "frames": int(n),
            "last_seen_frame": last_seen, "seen_final_error_m": float(np.linalg.norm(pred[last_seen] - true[-1])),
            "in_view_at_end": visible_end,
        }
    missing = [n for n in names if n not in per_object]
    others = [n for n in names if n != instructed]
    still_others = [n for n in others if n in missing or per_object[n]["still_in_truth"]]
    scored = list(per_object.values())
    in_view_names = [n for n in names if n not in per_object or per_object[n]["in_view_at_end"]]
    summary = {
        "objects": len(names), "missing": len(missing),
        "instructed_within_2cm": (float("nan") if instructed is None or instructed not in names else
                                  float(instructed in per_object and per_object[instructed]["final_error_m"] <= ENDED_WITHIN_M)),
        "instructed_seen_within_2cm": (float("nan") if instructed is None or instructed not in names else
                                       float(instructed in per_object and per_object[instructed]["seen_final_error_m"] <= ENDED_WITHIN_M)),
        "instructed_final_error_m": per_object[instructed]["final_error_m"] if instructed in per_object else float("nan"),
        "instructed_displacement_error_m": (per_object[instructed]["displacement_error_m"] if instructed in per_object
                                            else float("nan")),
        "others_still": len(still_others),
        "others_still_within_1cm": (float(np.mean([n in per_object and per_object[n]["stayed_within_1cm"] for n in still_others]))
                                    if still_others else float("nan")),
        "final_error_m": float(np.mean([r["final_error_m"] for r in scored])) if scored else float("nan"),
        "mean_error_m": float(np.mean([r["mean_error_m"] for r in scored])) if scored else float("nan"),
        "yaw_error_deg": float(np.mean([r["yaw_error_deg"] for r in scored])) if scored else float("nan"),
        "within_5mm": (float(np.mean([n in per_object and per_object[n]["final_error_m"] <= CEILING_M for n in names]))
                       if names else float("nan")),
        "objects_in_view": len(in_view_names),
        "within_5mm_in_view": (float(np.mean([n in per_object and per_object[n]["final_error_m"] <= CEILING_M
                                              for n in in_view_names])) if in_view_names else float("nan")),
        "lost_share": (float(sum(r["lost_frames"] for r in scored) / sum(r["frames"] for r in scored)) if scored
                       else float("nan")),
        "inferred_share": (float(sum(r["inferred_frames"] for r in scored) / sum(r["frames"] for r in scored)) if scored
                           else float("nan")),
    }
    return {"per_object": per_object, "instructed": instructed, "missing": missing, "summary": summary}


def pooled(rows: list[dict]) -> dict:
    """Rates over many episodes' :func:`object_track_metrics` results, pooled by object (not averaged per
    episode): instructed objects within 2 cm, still others within 1 cm, objects within 5 mm, mean errors."""
    inst = [r["summary"]["instructed_within_2cm"] for r in rows if not math.isnan(r["summary"]["instructed_within_2cm"])]
    inst_seen = [r["summary"].get("instructed_seen_within_2cm", float("nan")) for r in rows]
    inst_seen = [v for v in inst_seen if not math.isnan(v)]
    still_hits = still_n = five_hits = five_n = view_hits = view_n = 0
    finals = []
    for r in rows:
        s = r["summary"]
        if s["others_still"]:
            still_hits += s["others_still_within_1cm"] * s["others_still"]
            still_n += s["others_still"]
        if s["objects"]:
            five_hits += s["within_5mm"] * s["objects"]
            five_n += s["objects"]
        if s.get("objects_in_view"):
            view_hits += s["within_5mm_in_view"] * s["objects_in_view"]
            view_n += s["objects_in_view"]
        finals += [o["final_error_m"] for o in r["per_object"].values()]
    return {
        "instructed": len(inst), "instructed_within_2cm": float(np.mean(inst)) if inst else float("nan"),
        "instructed_seen_within_2cm": float(np.mean(inst_seen)) if inst_seen else float("nan"),
        "others_still": still_n, "others_still_within_1cm": still_hits / still_n if still_n else float("nan"),
        "objects": five_n, "within_5mm": five_hits / five_n if five_n else float("nan"),
        "objects_in_view": view_n, "within_5mm_in_view": view_hits / view_n if view_n else float("nan"),
        "final_error_m": float(np.mean(finals)) if finals else float("nan"),
        "missing": int(sum(r["summary"]["missing"] for r in rows)),
    }


def format_rows(result: dict) -> str:
    """Plain-text lines of one episode's object metrics (the `evaluate` command prints them)."""
    s = result["summary"]
    lines = [f"objects: {s['objects']} recorded, {s['missing']} without a track; instructed: {result['instructed'] or '-'}",
             f"{'object':<14}{'final mm':>10}{'mean mm':>10}{'yaw deg':>9}{'moved mm':>10}{'truth mm':>10}{'lost':>6}{'inferred':>9}"]
    for name, r in result["per_object"].items():
        lines.append(f"{name:<14}{1000 * r['final_error_m']:>10.1f}{1000 * r['mean_error_m']:>10.1f}{r['yaw_error_deg']:>9.1f}"
                     f"{1000 * r['displacement_m']:>10.1f}{1000 * r['displacement_truth_m']:>10.1f}{r['lost_frames']:>6}"
                     f"{r.get('inferred_frames', 0):>9}")
    fmt = lambda v: "-" if v is None or (isinstance(v, float) and math.isnan(v)) else f"{v:.2f}"  # noqa: E731
    lines.append(f"instructed object within 2 cm: {fmt(s['instructed_within_2cm'])}; others kept still within 1 cm: "
                 f"{fmt(s['others_still_within_1cm'])} of {s['others_still']}; final error <= 5 mm: {fmt(s['within_5mm'])}")
    return "\n".join(lines)


def layer_of(output, gt: Episode, camera: str) -> ObjectLayer:
    """The object layer of a scored output: a reconstruction's own, else the objects of the ground truth's
    first frame tracked through the output's frames (a predicted or static episode)."""
    if isinstance(output, Recon4D) and output.objects is not None:
        return output.objects
    if isinstance(output, Recon4D):  # a reconstruction made without objects: track them in its depth
        frames = Episode(env_id=gt.env_id, seed=gt.seed, instruction=gt.instruction, cameras={camera: _recon_frames(output)},
                         frame_steps=np.arange(output.num_frames, dtype=np.int32), source="prediction")
        return episode_objects(frames, camera, objects_from=gt)
    name = camera if camera in output.cameras else next(iter(output.cameras))
    return episode_objects(output, name, objects_from=gt)


def _recon_frames(recon: Recon4D) -> CameraFrames:
    return CameraFrames(rgb=recon.rgb, depth_m=recon.depth_m, normal_cam=recon.normal_cam, K=recon.K, T_world_cam=recon.T_world_cam)


def episode_object_report(output, gt: Episode, camera: str | None = None, first_scored_frame: int = 1) -> dict | None:
    """:func:`object_track_metrics` of an output (Recon4D or Episode) against ``gt``, or None when the
    ground truth records no scene object poses to score against."""
    camera = camera or next(iter(gt.cameras))
    if not recorded_objects(gt, camera):
        return None
    return object_track_metrics(layer_of(output, gt, camera), gt, camera, first_scored_frame)


# The object rows of a held-out report: metric key in a method's summary -> (label, region).
SUMMARY_KEYS = {
    "obj_instructed_within_2cm": ("object layer: the instructed object ended within 2 cm of the truth", "instructed object"),
    "obj_others_still_within_1cm": ("object layer: objects the truth kept still stayed within 1 cm", "other objects"),
    "obj_instructed_final_error_m": ("object layer: the instructed object's final position error (mm)", "instructed object"),
    "obj_final_error_m": ("object layer: final position error (mm), mean over objects", "scene objects"),
    "obj_yaw_error_deg": ("object layer: final yaw error (degrees), mean over objects", "scene objects"),
    "obj_lost_share": ("object layer: object-frames reported lost", "scene objects"),
    "obj_inferred_share": ("object layer: object-frames placed by the arm's or the hand's motion (inferred)", "scene objects"),
    "obj_instructed_seen_within_2cm": ("object layer: the instructed object, where last seen, within 2 cm of the truth's end",
                                       "instructed object"),
}


def object_summary(result: dict | None) -> dict:
    """The per-episode numbers a held-out report averages per method (NaN where not measured)."""
    nan = float("nan")
    if result is None:
        return {k: nan for k in SUMMARY_KEYS}
    s = result["summary"]
    return {"obj_instructed_within_2cm": s["instructed_within_2cm"], "obj_others_still_within_1cm": s["others_still_within_1cm"],
            "obj_instructed_final_error_m": s["instructed_final_error_m"], "obj_final_error_m": s["final_error_m"],
            "obj_yaw_error_deg": s["yaw_error_deg"], "obj_lost_share": s["lost_share"],
            "obj_inferred_share": s.get("inferred_share", nan),
            "obj_instructed_seen_within_2cm": s.get("instructed_seen_within_2cm", nan)}


def truth_tracker_summary(rows: list[dict]) -> dict:
    """The tracker on the ground truth's own frames over a report's rows (each episode once): the share of
    objects within 5 mm at the end (goal >= 98 %), the instructed and still-object rates."""
    seen, summaries = set(), []
    for r in rows:
        if r.get("object_tracks_truth") is not None and r["episode"] not in seen:
            seen.add(r["episode"])
            summaries.append({"summary": r["object_tracks_truth"], "per_object": {}})
    p = pooled(summaries)
    return {k: p[k] for k in ("objects", "within_5mm", "objects_in_view", "within_5mm_in_view", "instructed",
                              "instructed_within_2cm", "others_still", "others_still_within_1cm", "missing")}


def markdown_rows(summary: dict, methods: list[str], truth: dict | None) -> list[str]:
    """The held-out results table's object rows (one per SUMMARY_KEYS entry a method has)."""
    def cell(key, v):
        if v is None or (isinstance(v, float) and math.isnan(v)):
            return "–"
        return f"{1000 * v:.1f}" if key.endswith("_m") else f"{v:.1f}" if key.endswith("_deg") else f"{v:.3f}"

    lines = []
    for key, (label, region) in SUMMARY_KEYS.items():
        if not any(key in summary[m] for m in methods):
            continue
        lines.append(f"| {label} | {region} | " + " | ".join(cell(key, summary[m].get(key)) for m in methods) + " |")
    if lines and truth and truth.get("objects"):
        lines.append(f"| object layer: the tracker on the ground truth's frames, final error ≤ 5 mm (goal ≥ 98 %) | "
                     f"{truth['objects']} objects | {truth['within_5mm']:.3f}" + " |" * len(methods))
        if truth.get("objects_in_view", truth["objects"]) < truth["objects"]:
            lines.append(f"| object layer: the same, objects whose true end lies inside the image | "
                         f"{truth['objects_in_view']} objects | {truth['within_5mm_in_view']:.3f}" + " |" * len(methods))
    return lines
