"""Drift over a long horizon: per-frame curves of a rollout against the truth.

A rollout longer than one clip continues clip after clip (model/pipeline.py); what it gets wrong
shows as curves that fall with the frame index. For every held-out episode (a chained episode with
its instruction schedule, or any episode at its own length) the model predicts the whole episode from
its first frame, and the model and the static world (the first frame repeated) are scored frame by
frame. The curves (:data:`CURVES`):

- ``rgb_psnr_db_moving``: RGB PSNR over the moving region of that frame (pixels whose truth differs
  from the first frame, ``metrics.moving_region_mask``), dB; NaN in a frame where nothing has moved.
- ``depth_abs_rel``: depth AbsRel over the pixels whose true depth is within the model's range.
- ``objects_present``: object permanence, the share of the objects the truth shows in that frame that
  the prediction shows in their colour where they should be (``believability.objects_present`` on the
  one frame).
- ``object_error_m``: where the truth records object poses, the object layer's position error (the
  first frame's objects tracked through the predicted frames, ``object_tracks.layer_of``), metres,
  mean over the recorded objects a track matched.

Per method the report holds the mean curve over episodes (NaN-aware: a frame counts the episodes
that measure it) and two windows: the first clip's predicted frames (1 .. clip - 1) and the same
number of frames at the end of the horizon (e.g. 49-63 of 64 frames with 16-frame clips), and the
change from the first window to the last. For chained episodes it also holds, per segment, the mean
of every curve over the segment's frames and how often the segment's instructed object moved the
commanded way (its track's displacement over the segment's frames within 60° of the commanded one and
at least half as long; gripper-only segments are not counted). Curves are written as ``horizon.json``, the table as
``horizon.md`` and a plot of the curves as ``horizon.png``.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from tesseract4d import dataset_format as df
from tesseract4d.errors import UserError
from tesseract4d.evaluation.believability import RIGHT_WAY_COSINE, objects_present
from tesseract4d.evaluation.episode import json_safe
from tesseract4d.evaluation.heldout import scene_noise_seed, select_episodes, static_world
from tesseract4d.evaluation.metrics import depth_metrics, moving_region_mask, rgb_psnr
from tesseract4d.evaluation.object_tracks import NO_OBJECT_SKILLS, layer_of, match_tracks, recorded_objects
from tesseract4d.instruction_schedule import clip_new_frames, schedule_of
from tesseract4d.segments import scene_object_ids

# key -> (label, unit, higher is better)
CURVES: dict[str, tuple[str, str, bool]] = {
    "rgb_psnr_db_moving": ("RGB PSNR, moving region", "dB", True),
    "depth_abs_rel": ("depth AbsRel", "", False),
    "objects_present": ("object permanence: share of the truth's objects shown", "", True),
    "object_error_m": ("object layer: position error", "m", False),
}
REPORT_JSON, REPORT_MD, REPORT_PNG = "horizon.json", "horizon.md", "horizon.png"


# --------------------------------------------------------------------------- curves of one episode


def frame_curves(pred: df.CameraFrames, gt: df.CameraFrames, max_depth_m: float | None = None,
                 object_ids: list[int] | None = None, first_scored_frame: int = 1) -> dict[str, np.ndarray]:
    """Per-frame RGB PSNR over the moving region, depth AbsRel and object permanence of ``pred``
    against ``gt`` over the frames both have: key -> (T,) float array, NaN where a frame measures
    nothing and before ``first_scored_frame`` (frame 0 is given to every method). ``object_ids``: the
    truth's object segmentation ids (default: its scene objects; none without a segmentation)."""
    T = min(len(pred.rgb), len(gt.rgb))
    moving = moving_region_mask(gt)[:T]  # (T, H, W)
    depth_ok = np.asarray(gt.depth_m[:T]) <= max_depth_m if max_depth_m is not None else None
    if object_ids is None and gt.segmentation is not None and gt.seg_id_to_name:
        object_ids = scene_object_ids(gt.seg_id_to_name)
    psnr, abs_rel, present = (np.full(T, np.nan) for _ in range(3))
    for t in range(first_scored_frame, T):
        if moving[t].any():
            psnr[t] = rgb_psnr(pred.rgb[t], gt.rgb[t], moving[t])
        abs_rel[t] = depth_metrics(pred.depth_m[t], gt.depth_m[t], None if depth_ok is None else depth_ok[t])["abs_rel"]
        if object_ids and gt.segmentation is not None:
            shown = objects_present(gt.rgb[t:t + 1], gt.segmentation[t:t + 1], object_ids, pred.rgb[t:t + 1])
            if shown.per_object:
                present[t] = float(np.mean(list(shown.per_object.values())))
    return {"rgb_psnr_db_moving": psnr, "depth_abs_rel": abs_rel, "objects_present": present}


def object_paths(output: df.Episode, gt: df.Episode, camera: str) -> dict[str, np.ndarray] | None:
    """Per recorded object a track matched: where the track carries the object's recorded first-frame
    origin in every frame, (T, 3) world metres (as ``object_tracks`` scores it); None when the truth
    records no object poses to score."""
    names = recorded_objects(gt, camera)
    if not names:
        return None
    layer = layer_of(output, gt, camera)
    paths = {}
    for name, k in match_tracks(layer, gt, names).items():
        T_pred = layer.tracks[k].T_world_object  # (T, 4, 4) object -> world
        origin = np.linalg.inv(T_pred[0]) @ np.r_[np.asarray(gt.object_poses[name][0, :3], np.float64), 1.0]
        paths[name] = np.einsum("tij,j->ti", T_pred, origin)[:, :3]
    return paths


def object_error_curve(paths: dict[str, np.ndarray] | None, gt: df.Episode) -> np.ndarray | None:
    """(T,) the object layer's position error per frame (metres, mean over the matched objects of
    :func:`object_paths` against the recorded poses), or None when nothing is matched."""
    if not paths:
        return None
    errors = []
    for name, carried in paths.items():
        true = np.asarray(gt.object_poses[name][:, :3], np.float64)  # (T, 3)
        n = min(len(carried), len(true))
        errors.append(np.linalg.norm(carried[:n] - true[:n], axis=1))
    n = min(len(e) for e in errors)
    return np.mean([e[:n] for e in errors], axis=0)


def segment_following(paths: dict[str, np.ndarray] | None, schedule: list | None) -> list[bool | None]:
    """Per segment of a chained episode: did the instructed object's track move the commanded way over
    the segment's frames (cos(moved, commanded) > ``RIGHT_WAY_COSINE`` and at least half the commanded
    distance)? None for a segment that moves no object (gripper-only skills) or whose object has no track."""
    out: list[bool | None] = []
    for seg in schedule or []:
        intent = seg.intent or {}
        target = intent.get("target")
        cmd = np.asarray(intent.get("commanded_displacement_world_m") or [0.0, 0.0, 0.0], np.float64)
        if intent.get("skill") in NO_OBJECT_SKILLS or target is None or not paths or target not in paths \
                or np.linalg.norm(cmd) < 1e-6:
            out.append(None)
            continue
        path = paths[target]
        end = min(seg.frame_end if seg.frame_end is not None else len(path) - 1, len(path) - 1)
        moved = path[end] - path[min(seg.frame_start, end)]
        norm = float(np.linalg.norm(moved) * np.linalg.norm(cmd))
        cos = float(moved @ cmd / norm) if norm > 0 else 0.0
        out.append(bool(cos > RIGHT_WAY_COSINE and np.linalg.norm(moved) >= 0.5 * np.linalg.norm(cmd)))
    return out


def episode_curves(output: df.Episode, gt: df.Episode, camera: str, max_depth_m: float | None,
                   with_objects: bool = True) -> dict[str, np.ndarray]:
    """Every curve of :data:`CURVES` of one output (an Episode) against its truth; the object-layer
    curve is all NaN where it is not measured. With a schedule in the truth, ``"followed"`` holds
    :func:`segment_following` per segment."""
    curves = frame_curves(output.cameras[camera], gt.cameras[camera], max_depth_m)
    T = len(curves["depth_abs_rel"])
    paths = object_paths(output, gt, camera) if with_objects else None
    err = object_error_curve(paths, gt)
    curves["object_error_m"] = np.full(T, np.nan)
    if err is not None:
        curves["object_error_m"][1:min(T, len(err))] = err[1:T]  # frame 0 is given
    curves["followed"] = segment_following(paths, schedule_of(gt.metadata))
    return curves


# --------------------------------------------------------------------------- pooling and windows


def mean_curves(per_episode: list[dict[str, np.ndarray]]) -> dict[str, dict]:
    """Per curve: the NaN-aware mean over episodes per frame and how many episodes measure each frame
    (episodes of different lengths count where they have the frame)."""
    out = {}
    for key in CURVES:
        rows = [np.asarray(c[key], np.float64) for c in per_episode if key in c]
        T = max((len(r) for r in rows), default=0)
        stack = np.full((len(rows), T), np.nan)
        for i, r in enumerate(rows):
            stack[i, :len(r)] = r
        count = np.isfinite(stack).sum(0)
        with np.errstate(invalid="ignore"):
            mean = np.where(count > 0, np.nansum(stack, 0) / np.maximum(count, 1), np.nan)
        out[key] = {"mean": mean.tolist(), "episodes": count.tolist()}
    return out


def window_frames(num_frames: int, clip_len: int) -> dict[str, list[int]]:
    """The first clip's predicted frames (1 .. clip_len - 1) and as many frames at the end of the horizon."""
    width = min(clip_len - 1, num_frames - 1)
    return {"first": [1, width], "last": [num_frames - width, num_frames - 1]}


def window_means(curve: list[float], window: list[int]) -> float:
    """Mean of ``curve`` over the frames ``window`` [a, b] (both included) that measure something."""
    values = np.asarray(curve[window[0]:window[1] + 1], np.float64)
    values = values[np.isfinite(values)]
    return float(values.mean()) if len(values) else float("nan")


def summarize(curves: dict[str, dict], num_frames: int, clip_len: int) -> dict:
    """Per curve: the first and last windows' means and the change (last - first; a ratio for the
    shares, last / first, as the permanence goal is written)."""
    windows = window_frames(num_frames, clip_len)
    out = {"windows": windows}
    for key, c in curves.items():
        first, last = window_means(c["mean"], windows["first"]), window_means(c["mean"], windows["last"])
        out[key] = {"first": first, "last": last, "change": last - first,
                    "ratio": last / first if first and math.isfinite(first) else float("nan")}
    return out


def segment_means(per_episode: list[dict[str, np.ndarray]], schedules: list) -> list[dict]:
    """For chained episodes: per segment index, each curve's mean over the segment's new frames, over
    the episodes that have that segment."""
    sums: dict[int, dict[str, list[float]]] = {}
    followed: dict[int, list[bool]] = {}
    for curves, schedule in zip(per_episode, schedules):
        if not schedule:
            continue
        for i, seg in enumerate(schedule):
            end = seg.frame_end if seg.frame_end is not None else len(curves["depth_abs_rel"]) - 1
            sums.setdefault(i, {})
            for key in CURVES:
                values = np.asarray(curves[key][seg.frame_start + 1:end + 1], np.float64)
                values = values[np.isfinite(values)]
                if len(values):
                    sums[i].setdefault(key, []).append(float(values.mean()))
            verdicts = curves.get("followed") or []
            if i < len(verdicts) and verdicts[i] is not None:
                followed.setdefault(i, []).append(verdicts[i])
    return [{"segment": i + 1, **{k: float(np.mean(v)) for k, v in sums[i].items()},
             "episodes": max((len(v) for v in sums[i].values()), default=0),
             "followed": int(sum(followed.get(i, []))), "followed_of": len(followed.get(i, []))}
            for i in sorted(sums)]


# --------------------------------------------------------------------------- the evaluation


@dataclass
class HorizonConfig:
    """What `tesseract4d evaluate --horizon` runs; written into horizon.json."""

    checkpoint: Path
    data: Path
    camera: str | None = None
    sample_seed: int = 0
    num_steps: int | None = None
    batch_size: int | None = None
    max_episodes: int | None = None
    precision: str = "auto"
    max_depth_m: float | None = None  # depth counted up to this (none: the checkpoint's depth range)
    text_guidance: float | None = None  # none: the checkpoint preset's
    objects: bool = True  # the object-layer curve (tracks the first frame's objects through every frame)


def evaluate_horizon(cfg: HorizonConfig, progress: bool = True) -> dict:
    """Predict every held-out episode at its own length (with its schedule when it has one) and score
    the model and the static world frame by frame; returns the report (see the module docstring)."""
    from tqdm import tqdm

    # deferred: imports torch (heavy)
    from tesseract4d.model.predict import load_pipeline, predict_scenes

    files = select_episodes(Path(cfg.data), cfg.max_episodes)
    pipe = load_pipeline(cfg.checkpoint, precision=cfg.precision)
    max_depth_m = float(pipe.model_space.far_m) if cfg.max_depth_m is None else float(cfg.max_depth_m)
    clip_len = pipe.num_frames
    per_method: dict[str, list] = {"model": [], "static": []}
    schedules, episodes = [], []
    bar = tqdm(total=len(files), desc="horizon", unit="episode", disable=not progress)
    for path in files:
        gt = df.read_episode(path)
        camera = cfg.camera or next(iter(gt.cameras))
        if camera not in gt.cameras:
            raise UserError(f"{path} has no camera {camera!r}; it has {sorted(gt.cameras)}")
        if tuple(gt.cameras[camera].rgb.shape[1:3]) != tuple(pipe.resolution):
            raise UserError(f"{path} is {gt.cameras[camera].rgb.shape[1]}x{gt.cameras[camera].rgb.shape[2]} but the "
                            f"model predicts {pipe.resolution[0]}x{pipe.resolution[1]}; the horizon report needs "
                            f"held-out data at the model's resolution (datagen --resolution {pipe.resolution[0]})")
        first = df.read_episode(path, cameras=[camera], frames=slice(0, 1))
        schedule = schedule_of(gt.metadata)
        T = gt.num_frames
        pred = predict_scenes(pipe, [first], [gt.instruction], num_frames=T, num_steps=cfg.num_steps,
                              text_guidance=cfg.text_guidance,
                              seed=cfg.sample_seed, camera=camera, batch_size=cfg.batch_size,
                              noise_seeds=[scene_noise_seed(cfg.sample_seed, gt.env_id, gt.seed)],
                              schedules=[schedule])[0]
        per_method["model"].append(episode_curves(pred, gt, camera, max_depth_m, cfg.objects))
        per_method["static"].append(episode_curves(static_world(first, camera, T), gt, camera, max_depth_m, cfg.objects))
        schedules.append(schedule)
        episodes.append({"episode": str(path.relative_to(cfg.data)), "frames": T, "instruction": gt.instruction,
                         "segments": len(schedule) if schedule else 1})
        bar.update(1)
    bar.close()
    if not episodes:
        raise UserError(f"{cfg.data} holds no episodes to evaluate")
    return build_report(cfg, per_method, schedules, episodes, clip_len, max_depth_m,
                        history_frames=pipe.preset.history_frames)


def build_report(cfg: HorizonConfig | None, per_method: dict[str, list], schedules: list, episodes: list[dict],
                 clip_len: int, max_depth_m: float | None, history_frames: int = 1) -> dict:
    """The report of per-episode curves of each method (see the module docstring)."""
    num_frames = max(e["frames"] for e in episodes)
    methods = {}
    for method, curves in per_method.items():
        mean = mean_curves(curves)
        methods[method] = {"curves": mean, "summary": summarize(mean, num_frames, clip_len),
                           "segments": segment_means(curves, schedules)}
    config = {} if cfg is None else {k: (str(v) if isinstance(v, Path) else v) for k, v in dataclasses.asdict(cfg).items()}
    return {"config": config, "clip_frames": clip_len, "history_frames": history_frames, "num_frames": num_frames,
            "max_depth_m": max_depth_m,
            "episodes": episodes, "methods": methods, "definitions": {k: v[0] for k, v in CURVES.items()}}


# --------------------------------------------------------------------------- outputs


def _fmt(value: float, key: str) -> str:
    if value is None or not math.isfinite(value):
        return "–"
    if key == "object_error_m":
        return f"{1000 * value:.1f} mm"
    return f"{value:.2f}" if key == "rgb_psnr_db_moving" else f"{value:.3f}"


def format_markdown(report: dict) -> str:
    """The horizon table: per curve and method, the first and last windows and the change."""
    methods = report["methods"]
    windows = next(iter(methods.values()))["summary"]["windows"]
    (a0, a1), (b0, b1) = windows["first"], windows["last"]
    lines = [f"# Drift over {report['num_frames']} frames ({len(report['episodes'])} episodes, clips of "
             f"{report['clip_frames']} frames)", "",
             f"| curve | method | frames {a0}–{a1} | frames {b0}–{b1} | change |", "|---|---|---|---|---|"]
    for key, (label, _unit, _) in CURVES.items():
        for method, m in methods.items():
            s = m["summary"][key]
            change = (f"×{s['ratio']:.2f}" if key == "objects_present" and math.isfinite(s["ratio"])
                      else _fmt(s["change"], key) if key != "rgb_psnr_db_moving" or not math.isfinite(s["change"])
                      else f"{s['change']:+.2f} dB")
            lines.append(f"| {label} | {method} | {_fmt(s['first'], key)} | {_fmt(s['last'], key)} | {change} |")
    segs = {method: m["segments"] for method, m in methods.items() if m["segments"]}
    if segs:
        lines += ["", "Per segment of the chained episodes (mean over the segment's frames):", "",
                  "| method | segment | episodes | " + " | ".join(CURVES[k][0] for k in CURVES)
                  + " | instructed object moved the commanded way |",
                  "|---|---|---|" + "---|" * (len(CURVES) + 1)]
        for method, rows in segs.items():
            for r in rows:
                lines.append(f"| {method} | {r['segment']} | {r['episodes']} | "
                             + " | ".join(_fmt(r.get(k, float("nan")), k) for k in CURVES)
                             + f" | {r['followed']} of {r['followed_of']} |")
    return "\n".join(lines)


COLOURS_BGR = {"model": (200, 90, 30), "static": (60, 60, 60)}  # further methods cycle through EXTRA_BGR
EXTRA_BGR = [(40, 160, 40), (30, 30, 200), (160, 40, 160)]


def plot_curves(report: dict, path: str | os.PathLike, panel_px: tuple[int, int] = (300, 480)) -> Path:
    """A PNG with one panel per curve (frame index across, value up), one line per method."""
    import cv2

    h, w = panel_px
    margin = 48
    methods = report["methods"]
    colours = dict(COLOURS_BGR)
    for i, m in enumerate(k for k in methods if k not in colours):
        colours[m] = EXTRA_BGR[i % len(EXTRA_BGR)]
    panels = []
    for key, (label, unit, _) in CURVES.items():
        img = np.full((h, w, 3), 255, np.uint8)
        series = {m: np.asarray(methods[m]["curves"][key]["mean"], np.float64) for m in methods}
        values = np.concatenate([s[np.isfinite(s)] for s in series.values()] + [np.zeros(0)])
        title = f"{label}" + (f" ({unit})" if unit else "")
        cv2.putText(img, title, (8, 18), cv2.FONT_HERSHEY_SIMPLEX, 0.42, (0, 0, 0), 1, cv2.LINE_AA)
        if len(values):
            lo, hi = float(values.min()), float(values.max())
            if hi - lo < 1e-9:
                lo, hi = lo - 0.5, hi + 0.5
            n = max(len(s) for s in series.values())
            x_of = lambda t: int(margin + (w - margin - 10) * t / max(n - 1, 1))  # noqa: E731
            y_of = lambda v: int(h - margin + (v - lo) / (hi - lo) * -(h - margin - 30))  # noqa: E731
            cv2.rectangle(img, (margin, 30), (w - 10, h - margin), (200, 200, 200), 1)
            for v, txt in ((lo, f"{lo:.3g}"), (hi, f"{hi:.3g}")):
                cv2.putText(img, txt, (2, y_of(v) + 4), cv2.FONT_HERSHEY_SIMPLEX, 0.35, (0, 0, 0), 1, cv2.LINE_AA)
            # Where each clip starts: the last given frame before its new frames.
            starts = [0] + [r.start - 1 for r in clip_new_frames(n, report["clip_frames"],
                                                                 report.get("history_frames", 1))[1:]]
            for t in starts:
                cv2.line(img, (x_of(t), 30), (x_of(t), h - margin), (225, 225, 225), 1)
                cv2.putText(img, str(t), (x_of(t) - 6, h - margin + 14), cv2.FONT_HERSHEY_SIMPLEX, 0.35, (0, 0, 0), 1)
            for m, s in series.items():
                pts = [(x_of(t), y_of(v)) for t, v in enumerate(s) if np.isfinite(v)]
                if len(pts) > 1:
                    cv2.polylines(img, [np.asarray(pts, np.int32)], False, colours[m], 2, cv2.LINE_AA)
        for i, m in enumerate(methods):
            cv2.putText(img, m, (margin + 8 + 110 * i, h - 10), cv2.FONT_HERSHEY_SIMPLEX, 0.42, colours[m], 1, cv2.LINE_AA)
        cv2.putText(img, "frame", (w - 60, h - margin + 28), cv2.FONT_HERSHEY_SIMPLEX, 0.35, (0, 0, 0), 1)
        panels.append(img)
    top, bottom = np.hstack(panels[:2]), np.hstack(panels[2:4])
    out = Path(path)
    cv2.imwrite(str(out), np.vstack([top, bottom]))
    return out


def write_horizon_report(report: dict, out: str | os.PathLike) -> None:
    """horizon.json, horizon.md and horizon.png into the folder ``out`` (which exists)."""
    out = Path(out)
    (out / REPORT_JSON).write_text(json.dumps(json_safe(report), indent=2))
    (out / REPORT_MD).write_text(format_markdown(report) + "\n")
    plot_curves(report, out / REPORT_PNG)
