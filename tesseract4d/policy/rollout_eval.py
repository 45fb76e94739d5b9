"""Rollout evaluation: success of four arms on held-out seeds, per task, with 95 % Wilson intervals.

Arms, run the same way on the same seeds:
  motion_planner    ManiSkill's motion planner (the reference, and the source of the oracle future);
  oracle_future     the IDM fed the true future frames (the planner's episode of the same seed);
  world_model       the IDM fed the world model's predicted clips (the number that matters);
  behavior_cloning  the same network without a future (observation + instruction -> action);
  static_world      (on request) the IDM fed the current frame repeated: what the same IDM does when the
                    future holds no motion, the control for what the world model's frames add.

Predict-then-plan arms (on request; ``tesseract4d.policy.plan``), which need no IDM:
  world_model_plan  per replan: predict, reconstruct the clip's object layer, read where it puts the moved
                    object, execute a motion-planned primitive toward it from the perceived poses;
  oracle_plan       the true future through the same reading and primitives (the ceiling of that arm);
  words_plan        no future: the instruction parsed by rules, then the same primitives.
Every arm also runs the tabletop's skills (task Tesseract4dTabletop-v1: one commanded skill per seed, its
success the skill's intent check, ``tesseract4d.policy.tabletop_tasks``); the IDM arms need an IDM trained
on tabletop episodes.

OUT/report.json + OUT/report.md (per task and mean), OUT/rollout_config.json, OUT/videos/<arm>/<env>/seed_*.mp4
(left: what the robot saw after each chunk; right: the frame it was steering toward), and for the
first seeds of the future arms OUT/viewer/<arm>/<env>/seed_*/replan_XX/{observed,predicted,predicted_clip}:
dataset folders that `tesseract4d view OUT/.../predicted --compare OUT/.../observed` shows side by side.
"""

from __future__ import annotations

import dataclasses
import json
import os
import time
import uuid
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from tesseract4d import dataset_format as df
from tesseract4d.configs import knob
from tesseract4d.errors import UserError
from tesseract4d.intervals import wilson_interval
from tesseract4d.precision import precision_field
from tesseract4d.policy.loop import (
    EpisodeResult, LoopConfig, OracleFuture, PolicyRunner, StaticFuture, Trace, WorldModelFuture, observation_episode,
)
from tesseract4d.policy.plan import PLAN_ARMS, OraclePlan, PlanRunner, WordsPlan, WorldModelPlan
from tesseract4d.policy import tabletop_tasks
from datagen.tabletop import ENV_ID as TABLETOP_ID
from tesseract4d.previews import write_preview
from datagen.counterfactual import run_skill
from datagen.simulate import AttemptResult, EpisodeSimulator, SimConfig
from datagen.tasks import get_task
from tesseract4d.model.text_encoder import TextEncoder
from tesseract4d.policy.idm import load_idm
from tesseract4d.outputs import claim_folder
from tesseract4d.model.predict import load_pipeline
from tesseract4d.model.draw_choice import check_draws
from datagen.capture import Frame

DEFAULT_ARMS = ("motion_planner", "oracle_future", "world_model", "behavior_cloning")
ARMS = DEFAULT_ARMS + ("static_world",) + PLAN_ARMS
PLAN_RESOLUTION = (128, 128)  # the plan arms' renders when no model sets it
VIDEO_SCALE = 4


@dataclass
class RolloutConfig:
    tasks: list[str] = field(default_factory=lambda: ["PushCube-v1", "PullCube-v1", "PickCube-v1", "StackCube-v1"])
    seed_start: int = knob(100000, "first held-out seed (never a training seed)")
    episodes: int = 5  # per task and arm
    arms: list[str] = field(default_factory=lambda: list(DEFAULT_ARMS))
    idm: str | None = None
    bc: str | None = None
    checkpoint: str | None = None
    out: str = ""
    videos: int = knob(2, "MP4s per arm and task (first seeds)")
    viewer_episodes: int = knob(1, "episodes per future arm and task written for the viewer (first seeds)")
    loop: LoopConfig = field(default_factory=LoopConfig)
    precision: str = precision_field()  # of the world model


def summarize(rows: list[dict], arms: list[str], tasks: list[str]) -> dict:
    """Per task and arm: successes, trials, rate, 95 % Wilson interval; per arm the mean over tasks."""
    per_task: dict = {}
    for task in tasks:
        per_task[task] = {}
        for arm in arms:
            sel = [r for r in rows if r["task"] == task and r["arm"] == arm]
            k, n = sum(bool(r["success"]) for r in sel), len(sel)
            lo, hi = wilson_interval(k, n)
            per_task[task][arm] = {"successes": k, "trials": n, "rate": k / n if n else None, "wilson95": [lo, hi]}
    mean = {}
    for arm in arms:
        rates = [per_task[t][arm]["rate"] for t in tasks if per_task[t][arm]["trials"]]
        k = sum(per_task[t][arm]["successes"] for t in tasks)
        n = sum(per_task[t][arm]["trials"] for t in tasks)
        mean[arm] = {"mean_rate": float(np.mean(rates)) if rates else None, "successes": k, "trials": n,
                     "pooled_wilson95": list(wilson_interval(k, n))}
    return {"per_task": per_task, "mean": mean}


def format_markdown(summary: dict, arms: list[str], tasks: list[str], timing: dict, config: dict) -> str:
    def cell(d):
        if not d["trials"]:
            return "–"
        lo, hi = d["wilson95"]
        return f"{100 * d['rate']:.0f} % ({d['successes']}/{d['trials']}; {100 * lo:.0f}–{100 * hi:.0f})"

    lines = ["# Rollout evaluation", "",
             f"Held-out seeds {config['seed_start']}..{config['seed_start'] + config['episodes'] - 1} per task; "
             f"replan every {config['loop']['replan_every']} predicted frames; success = the env's own success signal "
             f"at any step within {config['loop']['max_steps']} steps"
             + (f" ({TABLETOP_ID}: the commanded skill's intent check, after each chunk or primitive)"
                if TABLETOP_ID in tasks else "") + "."
             + (f" The world model keeps the best of {config['loop']['draws']} noise draws per prediction."
                if (config['loop'].get('draws') or 1) > 1 and "world_model" in arms else "")
             + " Cells: success rate (successes/trials; 95 % Wilson interval).", "",
             "| task | " + " | ".join(arms) + " |", "|---" * (len(arms) + 1) + "|"]
    for t in tasks:
        lines.append(f"| {t} | " + " | ".join(cell(summary["per_task"][t][a]) for a in arms) + " |")
    means = []
    for a in arms:
        m = summary["mean"][a]
        means.append("–" if m["mean_rate"] is None else
                     f"{100 * m['mean_rate']:.0f} % (pooled {100 * m['pooled_wilson95'][0]:.0f}–{100 * m['pooled_wilson95'][1]:.0f})")
    lines.append("| **mean** | " + " | ".join(means) + " |")
    idm_timing = {a: t for a, t in timing.items() if a not in PLAN_ARMS}
    plan_timing = {a: t for a, t in timing.items() if a in PLAN_ARMS}
    if plan_timing:
        lines += ["", "## Plan arms: seconds per replan and per episode (means)", "",
                  "predict + reconstruct (the clip's object layer) + plan (read the goal) = the replanning cycle; "
                  "motion planning and the simulator's steps are apart.", "",
                  "| arm | predict | reconstruct | plan | cycle | motion planning | simulate | primitives/episode | episode |",
                  "|---|---|---|---|---|---|---|---|---|"]
        for a, t in plan_timing.items():
            lines.append(f"| {a} | {t['predict_s']:.3f} | {t['reconstruct_s']:.3f} | {t['plan_s']:.3f} | {t['cycle_s']:.3f} | "
                         f"{t['motion_planning_s']:.2f} | {t['simulate_s']:.2f} | {t['primitives']:.2f} | {t['episode_s']:.1f} |")
    if not idm_timing:
        return "\n".join(lines) + "\n"
    timing = idm_timing
    lines += ["", "## Seconds per replanning cycle and per episode (means)", "",
              "| arm | predict | reconstruct (back-projection) | IDM | cycle (predict+reconstruct+IDM) | episode |", "|---|---|---|---|---|---|"]
    for a, t in timing.items():
        lines.append(f"| {a} | {t['predict_s']:.3f} | {t['reconstruct_s']:.3f} | {t['idm_s']:.3f} | {t['cycle_s']:.3f} | {t['episode_s']:.1f} |")
    return "\n".join(lines) + "\n"


def cycle_timing(results: list[EpisodeResult]) -> dict:
    """Mean seconds per replanning cycle: one prediction, and the reconstruct/IDM work of its k chunks."""
    cycles = sum(max(r.replans, 1) if r.arm != "behavior_cloning" else r.chunks for r in results) or 1
    tot = {s: sum(r.stage_seconds.get(s, 0.0) for r in results) for s in ("predict", "reconstruct", "idm")}
    out = {f"{s}_s": v / cycles for s, v in tot.items()}
    out["cycle_s"] = sum(out.values())
    out["episode_s"] = float(np.mean([r.seconds for r in results])) if results else 0.0
    return out


def plan_timing(results: list[EpisodeResult]) -> dict:
    """Mean seconds of a plan arm per replan (predict, reconstruct, plan and their sum, the cycle) and per
    primitive executed (motion planning, simulator steps)."""
    replans = sum(max(r.replans, 1) for r in results) or 1
    primitives = sum(r.chunks for r in results)
    tot = {s: sum(r.stage_seconds.get(s, 0.0) for r in results)
           for s in ("predict", "reconstruct", "plan", "execute", "simulate", "observe")}
    out = {f"{s}_s": tot[s] / replans for s in ("predict", "reconstruct", "plan")}
    out["cycle_s"] = sum(out.values())
    out["motion_planning_s"] = tot["execute"] / max(primitives, 1)
    out["simulate_s"] = tot["simulate"] / max(primitives, 1)
    out["observe_s"] = tot["observe"] / replans
    out["primitives"] = primitives / max(len(results), 1)
    out["episode_s"] = float(np.mean([r.seconds for r in results])) if results else 0.0
    return out


def write_video(path: Path, trace: Trace) -> Path:
    """MP4: observed frame | target frame (black when the arm has none), scaled up."""
    import imageio.v2 as imageio

    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.stem}.{uuid.uuid4().hex}.partial.mp4")
    try:
        with imageio.get_writer(tmp, format="FFMPEG", fps=4, codec="libx264", pixelformat="yuv420p",
                                macro_block_size=16, ffmpeg_log_level="error") as writer:
            for obs, target in zip(trace.observed, trace.targets):
                right = target if target is not None else np.zeros_like(obs.rgb)
                frame = np.concatenate([obs.rgb, right], axis=1)
                writer.append_data(np.repeat(np.repeat(frame, VIDEO_SCALE, 0), VIDEO_SCALE, 1))
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return path


def write_viewer_folders(root: Path, trace: Trace, env_id: str, seed: int, instruction: str, camera: str) -> list[Path]:
    """Per replan: observed frames and the predicted frames they were steering toward (same count),
    plus the whole predicted clip, as one-episode dataset folders."""
    written = []
    bounds = [i for i, _ in trace.replans] + [len(trace.observed) - 1]
    for r, (start, clip) in enumerate(trace.replans):
        end = bounds[r + 1]
        # as many observed frames as the clip has, evenly spaced (a plan arm observes many per clip frame)
        pick = np.unique(np.linspace(start, end, min(end - start + 1, len(clip.rgb))).round().astype(int))
        observed = observation_episode([trace.observed[k] for k in pick], env_id, seed, instruction, camera)
        m = observed.num_frames
        predicted = observation_episode([trace.observed[start]] * m, env_id, seed, instruction, camera)
        pc = predicted.cameras[camera]
        pc.rgb = clip.rgb[:m].copy()
        pc.depth_m = clip.depth_m[:m].astype(np.float32)
        if clip.episode is not None:
            pc.normal_cam = clip.episode.cameras[camera].normal_cam[:m].astype(np.float32)
        predicted.source = "prediction"
        folder = root / f"replan_{r:02d}"
        for name, ep in (("observed", observed), ("predicted", predicted)):
            df.write_episode_dataset(folder / name, ep)
            write_preview(folder / name, ep)
        if clip.episode is not None:
            df.write_episode_dataset(folder / "predicted_clip", clip.episode)
            write_preview(folder / "predicted_clip", clip.episode)
        written.append(folder)
    return written


def check_heldout(idm_config, tasks: list[str], seeds: list[int], label: str) -> None:
    """UserError when a rollout seed was a training episode of the IDM (its dataset, if still on disk)."""
    data = idm_config.training.get("data")
    if not data or not Path(data).is_dir():
        return
    for f in df.list_episode_files(data):
        if f.parent.name in tasks and int(f.stem.split("_")[1]) in seeds:
            raise UserError(f"seed {int(f.stem.split('_')[1])} of {f.parent.name} is a training episode of the {label} "
                            f"({f}); evaluate on held-out seeds (--seed-start beyond the training seeds)")


def run_rollouts(cfg: RolloutConfig, progress: bool = True) -> dict:
    from tqdm import tqdm

    if not cfg.out:
        raise UserError("pass --out DIR for the report, videos and viewer folders")
    unknown = [a for a in cfg.arms if a not in ARMS]
    if unknown:
        raise UserError(f"unknown arm(s) {', '.join(unknown)}; choose from {', '.join(ARMS)}")
    for t in cfg.tasks:
        get_task(t)
    lc = cfg.loop
    seeds = list(range(cfg.seed_start, cfg.seed_start + cfg.episodes))
    idm = bc = pipeline = None
    if {"oracle_future", "world_model", "static_world"} & set(cfg.arms):
        if not cfg.idm:
            raise UserError("the oracle_future, world_model and static_world arms need --idm (a folder from "
                            "`tesseract4d train-idm`)")
        idm = load_idm(cfg.idm)
        if not idm.config.use_future:
            raise UserError(f"--idm {cfg.idm} is a behaviour-cloning model (no future input); pass it as --bc")
    if "behavior_cloning" in cfg.arms:
        if not cfg.bc:
            raise UserError("the behavior_cloning arm needs --bc (a folder from `tesseract4d train-idm --recipe bc`)")
        bc = load_idm(cfg.bc)
        if bc.config.use_future:
            raise UserError(f"--bc {cfg.bc} is an inverse dynamics model (it needs a future); train one with `tesseract4d train-idm --recipe bc`")
    for label, model in (("IDM", idm), ("BC policy", bc)):
        if model is None:
            continue
        trained = model.config.training.get("tasks") or []
        missing = [t for t in cfg.tasks if trained and t not in trained]
        if missing:
            raise UserError(f"the {label} was trained on {', '.join(trained)} but the rollout asks for "
                            f"{', '.join(missing)}, whose objects it has never seen; train it on those tasks or drop them")
        check_heldout(model.config, cfg.tasks, seeds, label)
    if {"world_model", "world_model_plan"} & set(cfg.arms):
        if not cfg.checkpoint:
            raise UserError("the world_model and world_model_plan arms need --checkpoint (a world-model inference folder)")

        pipeline = load_pipeline(cfg.checkpoint, precision=cfg.precision)

        lc = dataclasses.replace(lc, draws=check_draws(pipeline.preset.draws if lc.draws is None else lc.draws))
        cfg = dataclasses.replace(cfg, loop=lc)
    if lc.resolution is None:  # render at the world model's resolution, else at the IDM's
        policy = idm or bc
        source = (pipeline.resolution if pipeline is not None else policy.config.resolution if policy is not None
                  else PLAN_RESOLUTION if set(PLAN_ARMS) & set(cfg.arms) else LoopConfig.resolution)
        lc = dataclasses.replace(lc, resolution=tuple(int(x) for x in source))
        cfg = dataclasses.replace(cfg, loop=lc)
    if pipeline is not None:
        WorldModelFuture(pipeline, lc)  # checks camera and resolution before any rollout
    text_encoder = TextEncoder("minilm", max_tokens=32)
    out = Path(cfg.out)

    # A folder of another command's (or the user's) files is refused: the rollout never overwrites them.
    claim_folder(out, "rollout", inputs=[p for p in (cfg.idm, cfg.bc, cfg.checkpoint) if p],
                 legacy_marker="rollout_config.json")
    df.atomic_write_text(out / "rollout_config.json", json.dumps(dataclasses.asdict(cfg), indent=2, default=str))

    rows: list[dict] = []
    results: dict[str, list[EpisodeResult]] = {a: [] for a in cfg.arms}
    bar = tqdm(total=len(cfg.tasks) * len(seeds) * len(cfg.arms), desc="rollouts", unit="ep", disable=not progress)
    for task in cfg.tasks:
        # every step rendered for the IDM's oracle future; the clip's frames otherwise
        frames = 0 if "oracle_future" in cfg.arms else lc.num_frames
        sim = EpisodeSimulator(task, SimConfig(height=lc.resolution[0], width=lc.resolution[1], cameras=[lc.camera],
                                               frames=frames, instruction_split=lc.instruction_split))
        runners = {name: PolicyRunner(sim, m, text_encoder, lc) for name, m in (("idm", idm), ("bc", bc)) if m is not None}
        plan_runner = PlanRunner(sim, lc)
        try:
            for i, seed in enumerate(seeds):
                planner = skill = None
                if task == TABLETOP_ID:
                    skill = tabletop_tasks.skill_task(sim, seed)
                if {"motion_planner", "oracle_future", "oracle_plan"} & set(cfg.arms):
                    t0 = time.perf_counter()
                    planner = sim.run(seed) if skill is None else _run_skill(sim, seed, skill)
                    if "motion_planner" in cfg.arms:
                        # The same step budget as the other arms: a plan that succeeds only after it counts as failed
                        # (its success is known at the plan's end, so a longer plan is not credited).
                        within = planner.success and planner.num_steps <= lc.max_steps
                        error = planner.error or ("" if within or not planner.success else
                                                  f"the plan succeeded after {planner.num_steps} steps, beyond --max-steps "
                                                  f"{lc.max_steps}")
                        r = EpisodeResult(task, seed, "motion_planner", within, within, planner.num_steps,
                                          0, 0, time.perf_counter() - t0, {},
                                          skill.instruction if skill else planner.episode.instruction if planner.episode else "",
                                          error)
                        results["motion_planner"].append(r)
                        rows.append({"task": task, **_row(r)})
                        if i < cfg.videos and planner.episode is not None:
                            _write_planner_video(out / "videos" / "motion_planner" / task / f"seed_{seed:06d}.mp4",
                                                 planner.episode, lc.camera)
                        bar.update(1)
                # a tabletop skill: its own words, and its intent's check instead of the env's success signal
                words = skill.instruction if skill else None
                check = (lambda s=skill: tabletop_tasks.success_check(sim, s)) if skill else None
                for arm in [a for a in cfg.arms if a != "motion_planner"]:
                    trace = Trace() if i < max(cfg.videos, cfg.viewer_episodes) else None
                    if arm in ("oracle_future", "oracle_plan") and (planner is None or planner.episode is None):
                        r = EpisodeResult(task, seed, arm, False, False, 0, 0, 0, 0.0, {}, "",
                                          f"no true future: the planner failed on this seed ({planner.error if planner else ''})")
                    elif arm == "oracle_future":
                        r = runners["idm"].run(seed, OracleFuture(planner.episode, lc), trace, words, check)
                    elif arm == "world_model":
                        r = runners["idm"].run(seed, WorldModelFuture(pipeline, lc), trace, words, check)
                    elif arm in PLAN_ARMS:
                        if arm == "world_model_plan":
                            source = WorldModelPlan(pipeline, lc)
                            source.env_id, source.seed = task, seed
                        else:
                            source = OraclePlan(planner.episode, lc) if arm == "oracle_plan" else WordsPlan()
                        r = plan_runner.run(seed, source, words, check, trace)
                    elif arm == "static_world":
                        r = runners["idm"].run(seed, StaticFuture(lc), trace, words, check)
                    else:
                        r = runners["bc"].run(seed, None, trace, words, check)
                    results[arm].append(r)
                    rows.append({"task": task, **_row(r)})
                    if trace is not None and trace.observed:
                        if i < cfg.videos:
                            write_video(out / "videos" / arm / task / f"seed_{seed:06d}.mp4", trace)
                        if i < cfg.viewer_episodes and trace.replans:
                            write_viewer_folders(out / "viewer" / arm / task / f"seed_{seed:06d}", trace, task, seed,
                                                 r.instruction, lc.camera)
                    bar.update(1)
                    bar.set_postfix_str(f"{task} {seed} {arm} {'ok' if r.success else 'fail'}")
        finally:
            sim.close()
    bar.close()
    summary = summarize(rows, cfg.arms, cfg.tasks)
    timing = {a: (plan_timing(rs) if a in PLAN_ARMS else cycle_timing(rs))
              for a, rs in results.items() if a != "motion_planner" and rs}
    report = {"config": dataclasses.asdict(cfg), "summary": summary, "timing_s": timing, "episodes": rows,
              "idm": idm.config.training if idm is not None else None, "bc": bc.config.training if bc is not None else None}
    df.atomic_write_text(out / "report.json", json.dumps(report, indent=2, default=str))
    df.atomic_write_text(out / "report.md", format_markdown(summary, cfg.arms, cfg.tasks, timing, dataclasses.asdict(cfg)))
    return report


def _run_skill(sim, seed: int, skill):
    """The motion planner's run of a tabletop skill, as the ManiSkill tasks' ``sim.run`` reports it."""

    t0 = time.perf_counter()
    episode, tried = run_skill(sim, seed, skill.variant, skill.target, skill.other)
    if episode is not None:
        episode.instruction = skill.instruction
    return AttemptResult(sim.env_id, seed, episode is not None, tried["num_steps"], 0 if episode is None else episode.num_frames,
                         time.perf_counter() - t0, error=tried.get("error", ""), episode=episode)


def _row(r: EpisodeResult) -> dict:
    d = dataclasses.asdict(r)
    d.pop("env_id")
    return d


def _write_planner_video(path: Path, episode: df.Episode, camera: str) -> Path:
    cam = episode.cameras[camera]
    trace = Trace()
    for t in range(0, cam.num_frames, max(1, cam.num_frames // 40)):
        trace.observed.append(Frame(cam.rgb[t], cam.depth_m[t], cam.normal_cam[t], np.zeros(cam.rgb.shape[1:3], np.int32),
                                    cam.K[t], cam.T_world_cam[t]))
        trace.targets.append(None)
    return write_video(path, trace)
