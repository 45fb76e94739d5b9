"""The ceiling per situation: what a decoder keeps of the truth's objects, frame by frame, and when.

The *ceiling* of a latent model is the truth's own round trip through its autoencoder (encode every
true frame, decode): no model in that latent space shows more than its decoder can draw. The held-out
evaluation (``heldout.py``) reports it as whole-clip means; this module splits it by what is happening
to each scene object in each frame, since a decoder that loses a cube loses it when the arm is at it:

- ``in_gripper``: the object is lifted more than ``LIFTED_M`` above where it started (stored object
  poses; nothing else lifts an object off the table) and the gripper (hand or finger segments) lies
  within ``GRIPPER_NEAR_PX`` of its silhouette;
- ``occluded``: the arm covers part of it: it shows less than ``OCCLUDED_SHARE`` of its first-frame
  pixel count while robot pixels lie within ``ARM_NEAR_PX`` of its silhouette (an object hidden whole
  shows fewer than ``MIN_OBJECT_PIXELS`` and is judged nowhere, as in :func:`believability.objects_present`);
- ``moving``: its position changed by more than ``MOVING_M`` since the previous frame;
- ``all``: every frame in which it is judged.

Two measures per situation, over the frames from ``first_scored_frame`` on (1: frame 0 is given):

- *permanence*: share of (object, frame) pairs in the situation, judged as
  :func:`believability.objects_present` judges them (the object's distinctive colours near its true
  silhouette), in which the object is present; and for ``all`` also the held-out evaluation's
  ``objects_present`` (share of frames in which every judged object is present);
- *found whole*: for the episode's instructed (moved) object, share of its frames in the situation in
  which :func:`heldout_believability.find_object` finds it whole (one object of about its size, not a
  smear or fragments), and whether it is found whole in the last frame (``whole_at_end``, the measure
  of the contrast's "found whole").

Per episode :func:`episode_ceiling`; :func:`summarize` pools episodes per skill (``intent.variant``,
or the task for episodes without intent) and over all. :func:`round_trip` makes a decoder's ceiling
clip of an episode. Images are (T, H, W, 3) uint8; pure functions but ``round_trip``.
"""

from __future__ import annotations

import numpy as np

from tesseract4d.evaluation.believability import objects_present
from tesseract4d.evaluation.heldout_believability import (
    GRIPPER_ONLY_SKILLS, PRESENCE_SLACK_PX, SEARCH_FRACTION, WHOLE_MAX_SPREAD, WHOLE_PIXELS, WHOLE_SPREAD_SLACK_PX,
    _rms_radius,
)
from tesseract4d.object_colours import MIN_OBJECT_PIXELS, dilate, distinctive, matches
from tesseract4d.segments import scene_object_ids
from tesseract4d import dataset_format as df

SITUATIONS = ("all", "in_gripper", "occluded", "moving")
LIFTED_M = 0.01  # higher than this above its start: off the table
GRIPPER_NEAR_PX = 3
GRIPPER_SEGMENTS = ("panda_hand", "panda_leftfinger", "panda_rightfinger")  # name prefixes
OCCLUDED_SHARE = 0.8
ARM_NEAR_PX = 2
MOVED_M = 0.01  # an episode without intent: its moved object is the one that moves farthest, beyond this
MOVING_M = 0.003  # per frame (16 frames over an episode: a push moves a cube 5-15 mm a frame)


def _ids(names: dict, prefixes: tuple[str, ...]) -> list[int]:
    return [int(i) for i, n in names.items() if str(n).startswith(prefixes)]


def object_situations(gt, camera: str) -> dict[int, dict[str, np.ndarray]]:
    """Segment id -> {situation: (T,) bool} for each scene object visible in the ground truth's first
    frame (see the module docstring). gt: a dataset Episode with segmentation and object poses."""
    cam = gt.cameras[camera]
    seg = np.asarray(cam.segmentation)
    names = cam.seg_id_to_name
    T = seg.shape[0]
    robot = np.isin(seg, _ids(names, ("panda_",)) or [-1])
    gripper = np.isin(seg, _ids(names, GRIPPER_SEGMENTS) or [-1])
    out = {}
    for oid in scene_object_ids(names):
        mask = seg == oid  # (T, H, W)
        count = mask.reshape(T, -1).sum(axis=1)
        if count[0] < MIN_OBJECT_PIXELS:
            continue
        pose = gt.object_poses.get(names[oid])
        if pose is None:
            xyz = np.zeros((T, 3))
        else:
            xyz = np.asarray(pose, np.float64)[:, :3]
        near_gripper = (dilate(mask, GRIPPER_NEAR_PX) & gripper).reshape(T, -1).any(axis=1)
        near_arm = (dilate(mask, ARM_NEAR_PX) & robot).reshape(T, -1).any(axis=1)
        step = np.r_[0.0, np.linalg.norm(np.diff(xyz, axis=0), axis=1)]
        out[oid] = {
            "all": np.ones(T, bool),
            "in_gripper": (xyz[:, 2] - xyz[0, 2] > LIFTED_M) & near_gripper,
            "occluded": (count < OCCLUDED_SHARE * count[0]) & near_arm,
            "moving": step > MOVING_M,
        }
    return out


def presence_per_frame(gt_rgb: np.ndarray, segmentation: np.ndarray, oid: int, pred_rgb: np.ndarray) -> np.ndarray:
    """(T,) 1.0 / 0.0 where object ``oid`` is judged present / absent in ``pred_rgb``, NaN where it is
    not judged (:func:`believability.objects_present`, frame by frame)."""
    out = np.full(len(gt_rgb), np.nan)
    for t in range(len(gt_rgb)):
        p = objects_present(gt_rgb[t:t + 1], segmentation[t:t + 1], [oid], pred_rgb[t:t + 1])
        if oid in p.per_object:
            out[t] = p.per_object[oid]
    return out


def episode_skill(gt) -> str:
    """The episode's skill variant (``push_left``...), its skill, or its task for episodes without intent."""
    intent = gt.intent or {}
    return str(intent.get("variant") or intent.get("skill") or gt.env_id)


def moved_object(gt, camera: str) -> int | None:
    """Segment id of the instructed object of an episode whose skill moves one; for an episode without
    intent (a task's own demonstration), the scene object visible in frame 0 that moves farthest, if it
    moves more than ``MOVED_M``; else None."""
    intent = gt.intent or {}
    names = gt.cameras[camera].seg_id_to_name
    if not intent:
        seg0 = np.asarray(gt.cameras[camera].segmentation[0])
        best, far = None, MOVED_M
        for oid in scene_object_ids(names):
            pose = gt.object_poses.get(names[oid])
            if pose is None or (seg0 == oid).sum() < MIN_OBJECT_PIXELS:
                continue
            d = float(np.linalg.norm(np.asarray(pose)[:, :3] - np.asarray(pose)[:1, :3], axis=1).max())
            if d > far:
                best, far = oid, d
        return best
    if intent.get("skill") in GRIPPER_ONLY_SKILLS or intent.get("skill") == "keep_still":
        return None
    ids = [int(i) for i, n in names.items() if n == intent.get("target")]
    return ids[0] if ids else None


class ObjectFinder:
    """:func:`heldout_believability.find_object`'s "whole" for one object of a first frame, against many
    target frames: the first frame's part (distinctive palette, start, spread, distractors) is computed once
    and the palette's repeated colours are dropped (the nearest-colour distances are the same), so each
    target frame costs one colour match. Same result as ``find_object(first_rgb, mask, target).whole``
    (tests/test_ceiling.py checks it)."""

    def __init__(self, first_rgb: np.ndarray, object_mask: np.ndarray):
        self.mask = np.asarray(object_mask, bool)
        self.palette = None
        if self.mask.sum() < MIN_OBJECT_PIXELS:
            return
        rgb0 = np.asarray(first_rgb, np.float32)
        self.search_px = max(24, round(SEARCH_FRACTION * self.mask.shape[1]))
        keep = distinctive(rgb0, self.mask, PRESENCE_SLACK_PX)
        palette = rgb0[self.mask][keep]
        if not len(palette):
            return
        self.palette = np.unique(palette, axis=0)
        self.count = len(palette)
        vs, us = np.nonzero(self.mask)
        self.start = np.array([us[keep].mean(), vs[keep].mean()])
        self.spread0 = _rms_radius(us[keep], vs[keep])
        self.distractors = matches(rgb0, self.palette) & ~dilate(self.mask, 1)
        self._rms = _rms_radius

    def whole(self, target_rgb: np.ndarray) -> bool:
        if self.palette is None:
            return False
        v, u = np.nonzero(matches(target_rgb, self.palette) & ~self.distractors)
        near = (np.abs(u - self.start[0]) < self.search_px) & (np.abs(v - self.start[1]) < self.search_px)
        if not near.any():
            return False
        u, v = u[near], v[near]
        share = len(u) / self.count
        return bool(WHOLE_PIXELS[0] <= share <= WHOLE_PIXELS[1]
                    and self._rms(u, v) <= WHOLE_MAX_SPREAD * self.spread0 + WHOLE_SPREAD_SLACK_PX)


def episode_ceiling(gt, camera: str, pred_rgb: np.ndarray, first_scored_frame: int = 1) -> dict:
    """Per-situation counts of one decoded clip against its ground truth (module docstring).

    Returns ``{"skill", "episode", "objects_present": share of frames with every judged object present,
    "permanence": {situation: [present, judged]}, "whole": {situation: [whole, judged]},
    "whole_at_end": bool | None}`` (counts, so that :func:`summarize` pools them exactly)."""
    cam = gt.cameras[camera]
    gt_rgb, pred = np.asarray(cam.rgb), np.asarray(pred_rgb)
    if gt_rgb.shape != pred.shape:
        raise ValueError(f"prediction {pred.shape} and ground truth {gt_rgb.shape} differ in shape")
    seg = np.asarray(cam.segmentation)
    f = first_scored_frame
    situations = object_situations(gt, camera)
    permanence = {s: [0, 0] for s in SITUATIONS}
    all_present = np.ones(len(gt_rgb), bool)
    judged_any = np.zeros(len(gt_rgb), bool)
    for oid, sit in situations.items():
        present = presence_per_frame(gt_rgb, seg, oid, pred)
        judged = ~np.isnan(present)
        judged[:f] = False
        judged_any |= judged
        all_present &= ~judged | (present == 1.0)
        for s in SITUATIONS:
            sel = judged & sit[s]
            permanence[s][0] += int((present[sel] == 1.0).sum())
            permanence[s][1] += int(sel.sum())
    whole = {s: [0, 0] for s in SITUATIONS}
    whole_at_end = None
    target = moved_object(gt, camera)
    if target is not None and target in situations:
        finder = ObjectFinder(gt_rgb[0], seg[0] == target)
        for t in range(f, len(gt_rgb)):
            if (seg[t] == target).sum() < MIN_OBJECT_PIXELS:
                continue
            ok = finder.whole(pred[t])
            for s in SITUATIONS:
                if situations[target][s][t]:
                    whole[s][0] += int(ok)
                    whole[s][1] += 1
        whole_at_end = finder.whole(pred[-1])
    n = int(judged_any.sum())
    return {"skill": episode_skill(gt), "episode": gt.episode_id,
            "objects_present": float(all_present[judged_any].mean()) if n else float("nan"),
            "permanence": permanence, "whole": whole, "whole_at_end": whole_at_end}


def _pool(rows: list[dict]) -> dict:
    out = {"episodes": len(rows)}
    op = [r["objects_present"] for r in rows if np.isfinite(r["objects_present"])]
    out["objects_present"] = float(np.mean(op)) if op else float("nan")
    for key in ("permanence", "whole"):
        for s in SITUATIONS:
            a = sum(r[key][s][0] for r in rows)
            b = sum(r[key][s][1] for r in rows)
            out[f"{key}_{s}"] = [a, b]
    ends = [r["whole_at_end"] for r in rows if r["whole_at_end"] is not None]
    out["whole_at_end"] = [int(sum(ends)), len(ends)]
    return out


def summarize(rows: list[dict]) -> dict:
    """Pool :func:`episode_ceiling` rows over all episodes (``"all"``) and per skill.
    Counts stay ``[hits, judged]`` pairs; ``objects_present`` is the mean of the episodes' shares."""
    out = {"all": _pool(rows)}
    for skill in sorted({r["skill"] for r in rows}):
        out[skill] = _pool([r for r in rows if r["skill"] == skill])
    return out


def round_trip(autoencoder, gt, camera: str, first_frame: bool = True, bf16: bool = False) -> np.ndarray:
    """The ground truth of ``camera`` encoded and decoded by ``autoencoder`` (an RGBDNAutoencoder; a
    first-frame decoder is given the truth's frame 0 when ``first_frame``): (T, H, W, 3) uint8 RGB,
    decoded in bf16 autocast when ``bf16`` (as the pipeline decodes on a CPU with native bf16)."""
    import torch

    cam = gt.cameras[camera]
    ms = autoencoder.model_space
    x = ms.encode(cam.rgb, cam.depth_m, cam.normal_cam)  # (T, 7, H, W)
    with torch.no_grad():
        z = autoencoder.encode(x)[None]  # (1, T, C, h, w), fp32 as the pipeline's codec encodes
        with torch.autocast("cpu", dtype=torch.bfloat16, enabled=bf16):
            if getattr(autoencoder.config, "first_frame_injection", None) is not None:
                y = autoencoder.decode_clips(z, first_frame=x[:1] if first_frame else None)
            else:
                y = autoencoder.decode_clips(z)
    rgb, _, _ = ms.decode(y[0].float().clamp(-1, 1))
    return rgb


def ceiling_report(autoencoders: dict[str, str], data: list, camera: str | None = None, bf16: bool = False,
                   log=None) -> dict:
    """Every episode of the dataset folders ``data`` round-tripped through each named autoencoder folder
    (and the truth itself, as the measure's own reference): ``{"sets": {folder name: {method: summarize()}},
    "autoencoders": {name: {"folder", "latents_hash"}}}``."""
    from pathlib import Path

    # deferred: imports torch (heavy)
    from tesseract4d.model.autoencoder import latents_hash
    from tesseract4d.model.autoencoder_loading import load_autoencoder

    models = {name: load_autoencoder(folder) for name, folder in autoencoders.items()}
    report = {"autoencoders": {n: {"folder": str(f), "latents_hash": latents_hash(f)} for n, f in autoencoders.items()},
              "sets": {}}
    for folder in data:
        rows = {name: [] for name in ["truth", *models]}
        for path in df.list_episode_files(folder):
            gt = df.read_episode(path)
            cam = camera or next(iter(gt.cameras))
            rows["truth"].append(episode_ceiling(gt, cam, gt.cameras[cam].rgb))
            for name, model in models.items():
                rows[name].append(episode_ceiling(gt, cam, round_trip(model, gt, cam, bf16=bf16)))
            if log is not None:
                log(f"{Path(folder).name}: {gt.episode_id}")
        report["sets"][Path(folder).name] = {name: summarize(r) for name, r in rows.items()}
    return report


def report_markdown(report: dict) -> str:
    """The report as tables: one per dataset, a row per measure and situation, a column per method."""
    lines = []
    for set_name, methods in report["sets"].items():
        names = list(methods)
        skills = list(methods[names[0]])
        lines += [f"### {set_name}", "", "| skill | measure | " + " | ".join(names) + " |",
                  "|---|---|" + "---|" * len(names)]
        for skill in skills:
            rows = [("objects_present (frames)", lambda d: f"{d['objects_present']:.3f}"),
                    ("moved object whole at end", lambda d: f"{d['whole_at_end'][0]} / {d['whole_at_end'][1]}")]
            for key, label in (("permanence", "permanence"), ("whole", "moved object whole")):
                for s in SITUATIONS:
                    rows.append((f"{label}: {s}", lambda d, k=f"{key}_{s}": (
                        f"{d[k][0] / d[k][1]:.3f} ({d[k][0]}/{d[k][1]})" if d[k][1] else "–")))
            for label, fmt in rows:
                lines.append(f"| {skill} ({methods[names[0]][skill]['episodes']} ep) | {label} | "
                             + " | ".join(fmt(methods[n][skill]) for n in names) + " |")
        lines.append("")
    return "\n".join(lines)
