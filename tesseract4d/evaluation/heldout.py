"""Held-out evaluation of a checkpoint against two baselines, in one run.

For every episode of a held-out dataset (seeds never used in training, instructions from the
held-out paraphrases: ``tesseract4d datagen --seed-start 100000 --instruction-split heldout``)
the model predicts the clip from the episode's first frame and instruction, and three methods
are scored against the simulator's ground truth with ``tesseract4d.evaluation.episode``:

- ``model``: the prediction after the reconstruction's consistency step (normal integration +
  temporal consistency), i.e. what `tesseract4d demo` shows;
- ``model_raw``: the same prediction back-projected as is (no consistency step);
- ``static``: the static world, the first frame repeated (what a model that predicts no motion
  scores; on the moving region it is the baseline to beat).

Every metric is reported over all pixels and over the moving region (ground-truth pixels that
change over the clip), plus the instruction-following measure of
:mod:`tesseract4d.evaluation.instruction_following` for the tasks it covers.
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
from tesseract4d.evaluation.instruction_following import RIGHT_WAY_COSINE

METHODS = ("model", "model_raw", "static")
METHOD_LABELS = {"model": "model + consistency", "model_raw": "model, no consistency", "static": "static world"}
# The metrics of the README table: (key, label, higher is better).
TABLE_METRICS = (
    ("rgb_psnr_db", "RGB PSNR (dB)", True),
    ("rgb_ssim", "RGB SSIM", True),
    ("depth_abs_rel", "depth AbsRel", False),
    ("depth_delta1", "depth δ1", True),
    ("normal_mean_deg", "normal mean error (°)", False),
    ("normal_within_11_25", "normals < 11.25°", True),
    ("chamfer_l1_m", "4D Chamfer L1 (mm)", False),
)


@dataclass
class HeldoutConfig:
    checkpoint: Path
    data: Path
    out: Path | None = None  # where report.json / report.md go; None = print only
    camera: str | None = None  # None = the dataset's first camera
    num_steps: int | None = None  # None: the checkpoint preset's
    sample_seed: int = 0
    max_episodes: int | None = None  # per task; None = all
    # Evaluation range of the geometric metrics; None = the checkpoint's depth range (its far
    # plane), so that no method is scored on the distant floor the model does not represent.
    max_depth_m: float | None = None
    precision: str = "auto"  # auto|fp32|bf16 (tesseract4d/precision.py)


def static_world(first: df.Episode, camera: str, num_frames: int) -> df.Episode:
    """The first frame of ``camera`` repeated ``num_frames`` times."""
    cam = first.cameras[camera]
    rep = lambda a: np.repeat(a[:1], num_frames, axis=0)  # noqa: E731
    frames = df.CameraFrames(rgb=rep(cam.rgb), depth_m=rep(cam.depth_m), normal_cam=rep(cam.normal_cam),
                             K=rep(cam.K), T_world_cam=rep(cam.T_world_cam))
    return df.Episode(env_id=first.env_id, seed=first.seed, instruction=first.instruction, cameras={camera: frames},
                      frame_steps=np.arange(num_frames, dtype=np.int32), fps=first.fps, source="static-baseline")


def select_episodes(data: Path, max_per_task: int | None) -> list[Path]:
    files = df.list_episode_files(data)
    if not files:
        raise UserError(f"{data} holds no episodes; write a held-out set with `tesseract4d datagen ... "
                        f"--seed-start {df.HELDOUT_SEED_START} --instruction-split heldout --out {data}`")
    if max_per_task is None:
        return files
    kept, count, started = [], {}, set()
    for f in files:  # sorted, so a counterfactual group's files (seed_S_k0, seed_S_k1, ...) are adjacent
        task, group = f.parent.name, (f.parent.name, f.stem.split("_")[1])
        if group in started or count.get(task, 0) < max_per_task:  # never cut a group
            started.add(group)
            kept.append(f)
            count[task] = count.get(task, 0) + 1
    return kept


def _finite_mean(values) -> float:
    v = np.asarray([x for x in values if x is not None], np.float64)
    v = v[np.isfinite(v)]
    return float(v.mean()) if len(v) else float("nan")


def evaluate_heldout(cfg: HeldoutConfig, progress: bool = True) -> dict:
    """Run the evaluation; returns the report (also written to cfg.out when given)."""
    from tqdm import tqdm

    from tesseract4d.evaluation.episode import evaluate_episode, json_safe
    from tesseract4d.evaluation.metrics import moving_region_mask
    from reconstruction.reconstruct import ReconConfig, reconstruct_episode
    from tesseract4d.evaluation.instruction_following import TARGET_OBJECT, direction_score, summarize
    from tesseract4d.model.predict import load_pipeline, predict_episode

    data = Path(cfg.data)
    df.read_info(data)
    files = select_episodes(data, cfg.max_episodes)
    pipeline = load_pipeline(cfg.checkpoint, precision=cfg.precision)
    cfg = dataclasses.replace(cfg, num_steps=cfg.num_steps or pipeline.preset.num_steps)  # resolved, for the report
    max_depth_m = cfg.max_depth_m if cfg.max_depth_m is not None else float(pipeline.model_space.far_m)
    rows, scores = [], {m: [] for m in METHODS}
    bar = tqdm(files, desc="held-out", unit="episode", disable=not progress)
    for path in bar:
        gt = df.read_episode(path)
        camera = cfg.camera or next(iter(gt.cameras))
        if camera not in gt.cameras:
            raise UserError(f"{path} has no camera {camera!r}; it has {sorted(gt.cameras)}")
        gt_cam = gt.cameras[camera]
        num_frames = len(gt_cam.rgb)
        first = df.read_episode(path, cameras=[camera], frames=slice(0, 1))
        bar.set_postfix_str(f"{gt.env_id} seed {gt.seed}")
        pred = predict_episode(pipeline, first, gt.instruction, num_frames=num_frames, seed=cfg.sample_seed,
                               num_steps=cfg.num_steps)
        recon = reconstruct_episode(pred, config=ReconConfig())
        moving = moving_region_mask(gt_cam)
        outputs = {"model": recon, "model_raw": pred, "static": static_world(first, camera, num_frames)}
        row = {"episode": str(path.relative_to(data)), "task": gt.env_id, "seed": gt.seed,
               "instruction": gt.instruction, "metrics": {}, "direction": {}}
        for method, output in outputs.items():
            row["metrics"][method] = evaluate_episode(output, gt, camera=camera, moving_mask=moving, max_depth_m=max_depth_m)["mean"]
            if gt.env_id in TARGET_OBJECT and gt_cam.segmentation is not None:
                last_rgb = output.rgb[-1] if method == "model" else output.cameras[camera].rgb[-1]
                s = direction_score(gt.env_id, gt_cam.rgb, gt_cam.segmentation, gt_cam.seg_id_to_name,
                                    gt.object_poses[TARGET_OBJECT[gt.env_id]], gt_cam.K, gt_cam.T_world_cam, last_rgb)
                scores[method].append(s)
                row["direction"][method] = s.to_dict()
        rows.append(row)

    summary = {}
    for method in METHODS:
        keys = rows[0]["metrics"][method].keys()
        summary[method] = {k: _finite_mean(r["metrics"][method][k] for r in rows) for k in keys}
    tasks = sorted({r["task"] for r in rows})
    per_task = {t: {m: {k: _finite_mean(r["metrics"][m][k] for r in rows if r["task"] == t)
                        for k in ("rgb_psnr_db_moving", "depth_abs_rel_moving", "normal_mean_deg_moving", "chamfer_l1_m_moving")}
                    for m in METHODS} for t in tasks}
    report = {
        "format": "tesseract4d-heldout-eval", "format_version": 1,
        "config": {k: str(v) if isinstance(v, Path) else v for k, v in dataclasses.asdict(cfg).items()},
        "episodes": len(rows), "tasks": tasks, "methods": METHOD_LABELS, "max_depth_m": max_depth_m,
        "summary": summary, "per_task": per_task,
        "instruction_following": {m: summarize(scores[m]) for m in METHODS},
        "rows": rows,
    }
    report = json_safe(report)
    if cfg.out is not None:
        write_heldout_report(report, cfg.out)
    return report


def _fmt(value, key: str) -> str:
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "–"
    if key.startswith("chamfer"):
        return f"{1000 * value:.1f}"
    return f"{value:.3f}" if abs(value) < 10 else f"{value:.2f}"


def write_heldout_report(report: dict, out: str | os.PathLike) -> None:
    """``out/report.json`` and ``out/report.md``."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    df.atomic_write_text(out / "report.json", json.dumps(report, indent=2))
    df.atomic_write_text(out / "report.md", format_markdown(report) + "\n")


def format_markdown(report: dict) -> str:
    """The results table: each metric over all pixels and over the moving region, per method;
    the best method per row in bold; then instruction following."""
    summary = report["summary"]
    head = "| metric | region | " + " | ".join(METHOD_LABELS[m] for m in METHODS) + " |"
    lines = [head, "|" + "---|" * (2 + len(METHODS))]
    for key, label, higher in TABLE_METRICS:
        for region, suffix in (("all", ""), ("moving", "_moving")):
            vals = [summary[m].get(key + suffix) for m in METHODS]
            finite = [v for v in vals if v is not None and math.isfinite(v)]
            best = (max(finite) if higher else min(finite)) if finite else None
            cells = [f"**{_fmt(v, key)}**" if v is not None and v == best else _fmt(v, key) for v in vals]
            lines.append(f"| {label} | {region} | " + " | ".join(cells) + " |")
    follow = report["instruction_following"]
    lines.append(f"| instruction following: moved the right way (cos > {RIGHT_WAY_COSINE:g}) | target object | "
                 + " | ".join(_fmt(follow[m].get("right_way"), "") for m in METHODS) + " |")
    lines.append("| instruction following: mean cosine | target object | "
                 + " | ".join(_fmt(follow[m].get("mean_cosine"), "") for m in METHODS) + " |")
    n = follow["model"].get("episodes", 0)
    lines.append("")
    lines.append(f"{report['episodes']} held-out episodes ({', '.join(report['tasks'])}); depth, normal and Chamfer "
                 f"metrics over pixels with true depth ≤ {report['max_depth_m']:g} m (the model's depth range); "
                 f"instruction following over the {n} of them whose target object the colour tracker can follow "
                 f"(tracker error on the ground truth: {_fmt(follow['model'].get('tracker_px'), '')} px).")
    return "\n".join(lines)
