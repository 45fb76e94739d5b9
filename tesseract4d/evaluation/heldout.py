"""Held-out evaluation of a checkpoint against two baselines, in one run.

For every episode of a held-out dataset (seeds never used in training, instructions from the
held-out paraphrases: ``tesseract4d datagen --seed-start 100000 --instruction-split heldout``)
the model predicts the clip from the episode's first frame and instruction, and three methods
are scored against the simulator's ground truth with ``tesseract4d.evaluation.episode``:

- ``model``: the prediction after the reconstruction's consistency step (normal integration +
  temporal consistency), i.e. what `tesseract4d demo` shows;
- ``model_raw``: the same prediction back-projected as is (no consistency step);
- ``static``: the static world, the first frame repeated (what a model that predicts no motion
  scores; on the moving region it is the baseline to beat);
- ``autoencoder`` (``<name>_autoencoder`` beside several checkpoints), for a latent checkpoint at
  the data's resolution: the ground truth itself encoded and decoded by the checkpoint's
  autoencoder, the best a model in that latent space can show (its ceiling: colours, sharpness and
  object permanence that the autoencoder loses, no latent model can get back). One per distinct
  autoencoder.

Every metric is reported over all pixels and over the moving region (ground-truth pixels that
change over the clip), plus the instruction-following measure of
:mod:`tesseract4d.evaluation.instruction_following` for the tasks it covers, and the
believability measures of :mod:`tesseract4d.evaluation.heldout_believability` (object
permanence, instruction contrast over counterfactual groups, token grid, edge sharpness, motion);
means over all episodes, per task and per skill (``skill`` "task" for episodes without intent).

Several checkpoints can be scored in the same run on the same episodes: methods ``<name>`` and
``<name>_raw`` per checkpoint folder name, side by side with one static world; a single
checkpoint keeps the method keys ``model`` / ``model_raw``.

Checkpoints may predict at another resolution than the data's (the 64×64 ``tiny`` beside a
128×128 latent model), by a whole factor on both axes: the first frame is resized to the model's
resolution and the prediction back to the data's with :func:`tesseract4d.resize.resize_rgbdn`
(K along with them), its frame 0 is the data's first frame again (as a prediction's frame 0 is the
given first frame), and then it is reconstructed and scored like any other, against the untouched
ground truth. Only the token grid is measured on the prediction as the model made it, at its own
resolution and token size: bilinear upsampling alone lifts the ratio of a grid-free clip to
1.3-1.5 at tokens of twice the size. The static world and the ground truth are measured at the data's
resolution with the first checkpoint's token size in data pixels. The report states each
checkpoint's resolution and whether it was resized (``resolutions``, and the labels).

One noise draw decides a good part of each instruction's outcome: on the 48-episode tabletop set
v2 judged with two seeds agrees with itself on 21 of the 38 instructions (its 2-step student on 31). Several
``sample_seed`` values score one row per episode and seed (the static world and the ceiling, which
draw no noise, are the same in each); every mean, breakdown and the contrast then pool over the
seeds, each seed's groups judged on their own.

Every scene draws its own noise (:func:`scene_noise_seed` of ``sample_seed``, the env and the
scene seed), shared by the instructions of its counterfactual group so that their futures differ
only by their words. (Until the evaluation's format version 4 every episode of a run drew the same
noise, so a run was one draw for the whole set: a noise that made the arm flail did so in every
episode at once. Until format 7, several checkpoints in one run all sampled with the first one's
number of steps: a 10-step model listed after a 2-step student was scored at 2 steps. Each now
samples with its own preset's steps and guidance, recorded under "sampler". Format 8 added each
network's instruction discrimination, :func:`instruction_discrimination`; format 9 its words over
another future's noisy sample; format 10 where each clip's arm goes, :mod:`tesseract4d.evaluation.arm_target`.)
Scenes are predicted
several per network call (:func:`tesseract4d.model.predict.predict_scenes`, ``batch_size``), each
from the noise that predicting it alone with its noise seed draws, so the numbers do not depend
on the batch size (up to the rounding of batched maths).
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import zlib
from dataclasses import dataclass
from fractions import Fraction
from pathlib import Path

import numpy as np

from tesseract4d import dataset_format as df
from tesseract4d.errors import UserError
from tesseract4d.evaluation.instruction_following import RIGHT_WAY_COSINE, TARGET_OBJECT, direction_score, summarize
from tesseract4d.evaluation.object_tracks import (episode_object_report, markdown_rows, object_summary,
                                                  truth_tracker_summary)
from tesseract4d.resize import episode_at_resolution, resize_factor
from tesseract4d.evaluation.episode import evaluate_episode, json_safe
from tesseract4d.evaluation.heldout_believability import (
    CONTRAST_GOAL, EDGE_SHARPNESS_GOAL, PRESENCE_GOAL, STILL_SHARE, TOKEN_GRID_GOAL, breakdown, contrast_by_group,
    counts, direction_breakdown, episode_believability, goal_met,
)
from tesseract4d.evaluation.metrics import moving_region_mask
from reconstruction.reconstruct import ReconConfig, reconstruct_episode

METHODS = ("model", "model_raw", "static")
METHOD_LABELS = {"model": "model + consistency", "model_raw": "model, no consistency", "static": "static world"}
# The metrics of the per-method table (docs/evaluation.md): (key, label, higher is better).
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
    checkpoint: Path | list[Path]  # one checkpoint, or several scored side by side
    data: Path
    out: Path | None = None  # where report.json / report.md go; None = print only
    camera: str | None = None  # None = the dataset's first camera
    num_steps: int | None = None  # None: the checkpoint preset's
    # Diffusion noise seed, or several: each episode is then predicted once per seed, every seed's
    # prediction is scored as its own row, and the means and the contrast pool over all of them.
    sample_seed: int | list[int] = 0
    max_episodes: int | None = None  # per task; None = all
    # Evaluation range of the geometric metrics; None = the checkpoint's depth range (its far
    # plane), so that no method is scored on the distant floor the model does not represent.
    max_depth_m: float | None = None
    precision: str = "auto"  # auto|fp32|bf16 (tesseract4d/precision.py)
    batch_size: int | None = None  # scenes per network call; None = predict.DEFAULT_SCENE_BATCH
    text_guidance: float | None = None  # None: each checkpoint preset's text guidance scale
    # A diagnostic: every checkpoint's sampler starts from the episode's true future (through its
    # codec) noised to its first noise level <= this, and runs only the steps from there
    # (docs/research/evaluation.md, "Where a model fails"). None: from pure noise, as a model is used.
    start_from_truth: float | None = None


def sample_seeds(cfg: HeldoutConfig) -> list[int]:
    """The config's noise seed(s) as a list of distinct ints; UserError when empty or repeated."""
    seeds = [cfg.sample_seed] if isinstance(cfg.sample_seed, int) else [int(s) for s in cfg.sample_seed]
    if not seeds or len(set(seeds)) != len(seeds):
        raise UserError(f"--sample-seed takes one or more distinct seeds, got {cfg.sample_seed}")
    return seeds


def static_world(first: df.Episode, camera: str, num_frames: int) -> df.Episode:
    """The first frame of ``camera`` repeated ``num_frames`` times."""
    cam = first.cameras[camera]
    rep = lambda a: np.repeat(a[:1], num_frames, axis=0)  # noqa: E731
    frames = df.CameraFrames(rgb=rep(cam.rgb), depth_m=rep(cam.depth_m), normal_cam=rep(cam.normal_cam),
                             K=rep(cam.K), T_world_cam=rep(cam.T_world_cam))
    return df.Episode(env_id=first.env_id, seed=first.seed, instruction=first.instruction, cameras={camera: frames},
                      frame_steps=np.arange(num_frames, dtype=np.int32), fps=first.fps, source="static-baseline")


def autoencoder_round_trip(pipeline, gt: df.Episode, camera: str) -> df.Episode:
    """The ground truth of ``camera`` encoded and decoded by a latent ``pipeline``'s codec, in the
    precision the pipeline decodes in: what the checkpoint's latent space can show at best."""
    cam = gt.cameras[camera]
    ms = pipeline.model_space
    x = ms.encode(cam.rgb, cam.depth_m, cam.normal_cam)[None].to(pipeline.device)  # (1, T, 7, H, W)
    # A decoder that reads the first frame (first_frame_decoder.py) is given the truth's, as a prediction's is.
    rgb, depth_m, normal_cam = ms.decode(pipeline.decode(pipeline.codec.encode(x), first_frame=x[:, 0])[0])  # (T, 7, H, W)
    frames = df.CameraFrames(rgb=rgb, depth_m=depth_m, normal_cam=normal_cam, K=cam.K, T_world_cam=cam.T_world_cam)
    return df.Episode(env_id=gt.env_id, seed=gt.seed, instruction=gt.instruction, cameras={camera: frames},
                      frame_steps=gt.frame_steps, fps=gt.fps, source="autoencoder-round-trip")


def truth_clip(pipeline, gt: df.Episode, camera: str, num_frames: int):
    """The first ``num_frames`` of ``camera``'s true future in a pipeline's network space (1, t', c, h, w),
    through its codec: where ``evaluate --heldout --start-from-truth`` starts the sampler."""
    import torch

    cam = gt.cameras[camera]
    if num_frames != pipeline.num_frames:
        raise UserError(f"--start-from-truth needs episodes of one clip ({pipeline.num_frames} frames); {gt.env_id} "
                        f"seed {gt.seed} has {num_frames}: evaluate without it, or on such a set")
    x = pipeline.model_space.encode(cam.rgb[:num_frames], cam.depth_m[:num_frames], cam.normal_cam[:num_frames])
    with torch.no_grad():
        return pipeline.codec.encode(x[None].to(pipeline.device)).cpu()


def ceiling_methods(keys: list[tuple[str, str]], pipelines: list, factors: list) -> dict[str, int]:
    """Method key -> pipeline index of the autoencoder ceilings: one per distinct autoencoder among
    the latent checkpoints that predict at the data's resolution."""
    out, seen = {}, set()
    for i, ((with_c, _), pipeline, s) in enumerate(zip(keys, pipelines, factors)):
        ae_hash = getattr(pipeline.codec, "autoencoder_hash", None)
        if ae_hash is None or s != 1 or ae_hash in seen:
            continue
        seen.add(ae_hash)
        out["autoencoder" if with_c == "model" else f"{with_c}_autoencoder"] = i
    return out


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


def token_patch_px(pipeline) -> int:
    """A token's size in pixels: the backbone's patch size times the codec's spatial compression."""
    patch = pipeline.preset.backbone.get("patch_size")
    if patch is None:  # latent presets read the backbone from the pretrained folder
        for obj in (pipeline.transformer, getattr(pipeline.transformer, "backbone", None)):
            cfg = getattr(obj, "config", None)
            if cfg is not None and getattr(cfg, "patch_size", None):
                patch = cfg.patch_size
                break
    spatial = getattr(pipeline.codec, "spatial_compression", None)
    if spatial is None:
        vae = getattr(pipeline.codec, "vae", None)
        spatial = 2 ** (len(vae.config.block_out_channels) - 1) if vae is not None else 1
    return int(patch or 1) * int(spatial)


def method_keys(checkpoints: list[Path]) -> list[tuple[str, str]]:
    """(method with consistency, method without) per checkpoint: ("model", "model_raw") for one
    checkpoint (the report keys of a single-checkpoint run), else each folder's name (made unique)."""
    if len(checkpoints) == 1:
        return [("model", "model_raw")]
    keys, seen = [], set()
    for ckpt in checkpoints:
        name, i = Path(ckpt).name or "model", 2
        base = name
        while name in seen or name in ("static", "ground_truth"):
            name, i = f"{base}_{i}", i + 1
        seen.add(name)
        keys.append((name, f"{name}_raw"))
    return keys


def _checkpoints(cfg: HeldoutConfig) -> list[Path]:
    ckpts = cfg.checkpoint if isinstance(cfg.checkpoint, (list, tuple)) else [cfg.checkpoint]
    if not ckpts:
        raise UserError("held-out evaluation needs at least one --checkpoint")
    return [Path(c) for c in ckpts]


def data_to_model_factor(checkpoint: Path, model_hw: tuple[int, int], data: Path, data_hw: tuple[int, int]) -> Fraction:
    """The scale from the data's resolution to the model's (1: none); a one-line UserError with the
    fix when evaluation cannot resize between them (not a whole factor, the same on both axes)."""
    s = resize_factor(data_hw, model_hw)
    if s is None:
        (h, w), (H, W) = model_hw, data_hw
        hint = f" (`tesseract4d datagen ... --resolution {h}` or {2 * h})" if h == w else ""
        raise UserError(f"{checkpoint} predicts {h}x{w} frames but {data} holds {H}x{W}, and evaluation resizes "
                        f"only by a whole factor on both axes; write the held-out set at {h}x{w} or a whole multiple or "
                        f"divisor of it{hint}")
    return s


def resolution_note(model_hw: tuple[int, int], data_hw: tuple[int, int]) -> str:
    """"" at the data's resolution, else e.g. " (64×64, upsampled to 128×128)"."""
    if tuple(model_hw) == tuple(data_hw):
        return ""
    how = "upsampled" if model_hw[0] < data_hw[0] else "downsampled"
    return f" ({model_hw[0]}×{model_hw[1]}, {how} to {data_hw[0]}×{data_hw[1]})"


def token_px_in_data(patch_px: int, factor: Fraction) -> int | None:
    """A model token's size in data pixels (``factor`` = model / data resolution), or None when it
    is not a whole number of at least 2 pixels (no token grid to measure)."""
    px = Fraction(patch_px) / factor
    return int(px) if px.denominator == 1 and px >= 2 else None


def scene_noise_seed(sample_seed: int, env_id: str, scene_seed: int) -> int:
    """The noise seed of one held-out scene for a run's ``sample_seed``: its own draw for every scene
    (so the episodes of a run are independent draws, not one draw shared by all), and the same for
    every instruction of a counterfactual group (one env and scene seed), so that a group's futures
    differ only by their words."""
    return (int(sample_seed) * 1_000_003 + zlib.crc32(env_id.encode()) * 7_919 + int(scene_seed)) % (1 << 62)


def predict_at_data_resolution(pipeline, firsts: list[df.Episode], instructions: list[str], cameras: list[str],
                               num_frames: list[int], *, seed: int, num_steps: int,
                               batch_size: int | None, text_guidance: float | None = None,
                               noise_seeds: list[int] | None = None, start_clips: list | None = None,
                               start_sigma: float | None = None) -> list[tuple[df.Episode, np.ndarray]]:
    """One prediction per scene at its first frame's resolution, whatever the model's: a list of
    (prediction at the data's resolution, its RGB as the model made it (T, h, w, 3) uint8).

    ``firsts[i]``: the first-frame episode of scene i (frame 0 of camera ``cameras[i]``);
    ``num_frames[i]``: frames to predict. Scenes go ``batch_size`` per network call
    (``predict_scenes``), scene i from the noise ``predict_episode(..., seed=noise_seeds[i])`` draws
    (default: ``seed`` for every scene). A first frame of another resolution than the model's is
    resized to it, and the prediction back (:func:`~tesseract4d.resize.episode_at_resolution`); frame 0 is then the given first
    frame again. ``start_clips`` (per scene, :func:`truth_clip`) and ``start_sigma``: the pipeline's
    ``start`` diagnostic (the data's resolution must be the model's; one noise draw, whatever the preset's).
    """
    # deferred: imports torch (heavy)
    from tesseract4d.model.predict import predict_scenes

    if noise_seeds is None:
        noise_seeds = [seed] * len(firsts)

    model_hw = tuple(pipeline.resolution)
    inputs = [episode_at_resolution(f, cam, model_hw) for f, cam in zip(firsts, cameras)]
    out: list[tuple[df.Episode, np.ndarray] | None] = [None] * len(firsts)
    for n in sorted(set(num_frames)):  # predict_scenes takes one clip length per call
        idx = [i for i, m in enumerate(num_frames) if m == n]
        preds = predict_scenes(pipeline, [inputs[i] for i in idx], [instructions[i] for i in idx],
                               batch_size=batch_size, num_frames=n, seed=seed, num_steps=num_steps,
                               text_guidance=text_guidance, noise_seeds=[noise_seeds[i] for i in idx],
                               start_clips=None if start_clips is None else [start_clips[i] for i in idx],
                               start_sigma=start_sigma, draws=None if start_sigma is None else 1)
        for i, pred in zip(idx, preds):
            model_rgb = pred.cameras[cameras[i]].rgb
            first = firsts[i].cameras[cameras[i]]
            data_hw = tuple(first.rgb.shape[1:3])
            if data_hw != model_hw:
                pred = episode_at_resolution(pred, cameras[i], data_hw)
                cam = pred.cameras[cameras[i]]
                # Frame 0 of a prediction is the given first frame, at the data's resolution too.
                cam.rgb[0], cam.depth_m[0], cam.normal_cam[0] = first.rgb[0], first.depth_m[0], first.normal_cam[0]
                pred.metadata["prediction"]["resized"] = {"model_resolution": list(model_hw),
                                                          "data_resolution": list(data_hw)}
            out[i] = (pred, model_rgb)
    return out


def instruction_discrimination(pipeline, files: list[Path], camera: str | None, seeds: list[int]) -> dict:
    """The network's instruction discrimination (instruction_discrimination.py) over the counterfactual
    groups of ``files``, each group judged once per sample seed from that seed's scene noise (the
    sampler's initial noise for the scene), and under ``"words_over_sample"`` whether its words win
    over another future's noisy sample. Episodes shorter than the preset's clip are left out."""
    import torch

    # deferred: imports torch (heavy)
    from tesseract4d.evaluation.instruction_discrimination import (discrimination_errors, own_closest,
                                                                   summarize_discrimination,
                                                                   summarize_words_over_sample, words_over_sample)

    groups: dict[str, list[Path]] = {}
    scene: dict[str, tuple[str, int]] = {}  # group -> (env_id, scene seed), the key of its noise
    for path in files:
        attrs = df.read_episode_attrs(path)
        groups.setdefault(attrs["group_id"], []).append(path)
        scene[attrs["group_id"]] = (attrs["env_id"], attrs["seed"])
    p = pipeline.preset
    shape = pipeline.latent_shape(1)
    judged: list[tuple[bool, int]] = []
    words: list[bool] = []
    for group, paths in groups.items():
        frames, texts = [], []
        for path in paths:
            ep = df.read_episode(path, cameras=[camera] if camera else None, frames=slice(0, p.num_frames))
            cam = camera or next(iter(ep.cameras))
            if ep.num_frames >= p.num_frames:
                frames.append(episode_at_resolution(ep, cam, tuple(pipeline.resolution)).cameras[cam])
                texts.append(ep.instruction)
        distinct = len(set(texts))
        if distinct < 2:
            continue
        clips = torch.stack([pipeline.model_space.encode(f.rgb, f.depth_m, f.normal_cam) for f in frames]).float()
        for seed in seeds:
            noise = torch.randn(shape, generator=torch.Generator().manual_seed(scene_noise_seed(seed, *scene[group])))
            errors = discrimination_errors(pipeline, clips, texts, noise)
            judged += [(r, distinct) for r in own_closest(errors, texts) if r is not None]
            words += words_over_sample(pipeline, clips, texts, noise)
    return {**summarize_discrimination(judged), "words_over_sample": summarize_words_over_sample(words)}


def sampler_settings(cfg: HeldoutConfig, pipeline) -> dict:
    """The steps and text guidance one checkpoint samples with: the config's where it sets them, else
    the checkpoint preset's own (a 2-step student and its 10-step teacher each keep their sampler); and
    its preset's guidance interval where it has one."""
    p = pipeline.preset
    settings = {"num_steps": int(cfg.num_steps or p.num_steps),
                "text_guidance": float(p.text_guidance if cfg.text_guidance is None else cfg.text_guidance)}
    if p.guidance_min_sigma > 0:  # a guidance interval (named only where there is one)
        settings["guidance_min_sigma"] = float(p.guidance_min_sigma)
    if p.static_tolerance > 0:
        settings["static_tolerance"] = float(p.static_tolerance)
    if p.draws > 1 and cfg.start_from_truth is None:  # named only where there is a choice (the diagnostic has none)
        settings["draws"] = int(p.draws)
    if cfg.start_from_truth is not None:  # the diagnostic (named only where it ran)
        settings["start_from_truth"] = float(cfg.start_from_truth)
    return settings


def describe_sampler(settings: dict) -> str:
    """"10 steps, text guidance 1.5 at noise ≥ 0.2": one checkpoint's entry of a report's ``sampler``."""
    text = f"{settings['num_steps']} steps, text guidance {settings['text_guidance']:g}"
    text += f" at noise ≥ {settings['guidance_min_sigma']:g}" if settings.get("guidance_min_sigma") else ""
    text += f", first frame kept where still (tolerance {settings['static_tolerance']:g})" if settings.get(
        "static_tolerance") else ""
    text += f", the best of {settings['draws']} noise draws" if settings.get("draws") else ""
    if settings.get("start_from_truth") is not None:
        text += f", started from the true future at noise ≤ {settings['start_from_truth']:g}"
    return text


def evaluate_heldout(cfg: HeldoutConfig, progress: bool = True) -> dict:
    """Run the evaluation; returns the report (also written to cfg.out when given).

    ``cfg.checkpoint`` may be one checkpoint or a list: every checkpoint predicts every episode
    and all are scored side by side with the static world (methods ``<name>`` / ``<name>_raw``;
    one checkpoint keeps the keys ``model`` / ``model_raw``). Checkpoints of another resolution
    than the data's are evaluated through resizing (see the module docstring).
    """
    from tqdm import tqdm

    # deferred: imports torch (heavy)
    from tesseract4d.model.predict import DEFAULT_SCENE_BATCH, load_pipeline

    data = Path(cfg.data)
    info = df.read_info(data)
    data_hw = (int(info.height), int(info.width))
    files = select_episodes(data, cfg.max_episodes)
    checkpoints = _checkpoints(cfg)
    keys = method_keys(checkpoints)
    seeds = sample_seeds(cfg)
    batch_size = DEFAULT_SCENE_BATCH if cfg.batch_size is None else int(cfg.batch_size)
    if batch_size < 1:
        raise UserError(f"--batch-size must be at least 1, got {batch_size}")
    if cfg.start_from_truth is not None and not 0.0 < float(cfg.start_from_truth) <= 1.0:
        raise UserError(f"--start-from-truth is a noise level in (0, 1] (1: from pure noise), got {cfg.start_from_truth}")
    pipelines = [load_pipeline(c, precision=cfg.precision) for c in checkpoints]
    factors = [data_to_model_factor(c, tuple(p.resolution), data, data_hw) for c, p in zip(checkpoints, pipelines)]
    if cfg.start_from_truth is not None and any(s != 1 for s in factors):
        raise UserError(f"--start-from-truth needs every checkpoint at the data's resolution {data_hw}; "
                        f"evaluate the others without it")
    patch_px = [token_patch_px(p) for p in pipelines]
    ceilings = ceiling_methods(keys, pipelines, factors)
    methods = [k for pair in keys for k in pair] + list(ceilings) + ["static"]
    labels = {"static": METHOD_LABELS["static"]}
    for key, i in ceilings.items():
        labels[key] = f"{keys[i][0]}'s autoencoder: truth encoded + decoded (ceiling)"
    resolutions = {}
    for (with_c, raw), pipeline, s in zip(keys, pipelines, factors):
        note = resolution_note(pipeline.resolution, data_hw)
        labels[with_c] = f"{with_c}{note} + consistency"  # "model + consistency" for a single checkpoint
        labels[raw] = f"{with_c}{note}, no consistency"
        resolutions[with_c] = {"model": list(pipeline.resolution), "data": list(data_hw),
                               "resized": None if s == 1 else ("upsampled" if s < 1 else "downsampled")}
    # Token grids: each model's at its own resolution and token size; the static world's and the
    # ground truth's at the data's, with the first checkpoint's token size in data pixels.
    method_patch = {k: px for (a, b), px in zip(keys, patch_px) for k in (a, b)}
    static_patch_px = token_px_in_data(patch_px[0], factors[0])
    method_patch["static"] = static_patch_px
    method_patch.update({key: patch_px[i] for key, i in ceilings.items()})
    # Each checkpoint samples with its own preset's steps and guidance unless the config sets them for all.
    sampler = {with_c: sampler_settings(cfg, pipeline) for (with_c, _), pipeline in zip(keys, pipelines)}
    cfg = dataclasses.replace(cfg, batch_size=batch_size)  # resolved, for the report
    max_depth_m = cfg.max_depth_m if cfg.max_depth_m is not None else float(pipelines[0].model_space.far_m)
    rows, scores = [], {m: [] for m in methods}
    contrast_entries: dict[str, list] = {m: [] for m in methods + ["ground_truth"]}
    bar = tqdm(total=len(files), desc="held-out", unit="episode", disable=not progress)
    # Episodes go through in chunks of one network batch, so memory does not grow with the set.
    for chunk_start in range(0, len(files), batch_size):
        chunk = files[chunk_start:chunk_start + batch_size]
        gts, cameras, firsts = [], [], []
        for path in chunk:
            gt = df.read_episode(path)
            camera = cfg.camera or next(iter(gt.cameras))
            if camera not in gt.cameras:
                raise UserError(f"{path} has no camera {camera!r}; it has {sorted(gt.cameras)}")
            gts.append(gt)
            cameras.append(camera)
            firsts.append(df.read_episode(path, cameras=[camera], frames=slice(0, 1)))
        num_frames = [len(gt.cameras[cam].rgb) for gt, cam in zip(gts, cameras)]
        bar.set_postfix_str(f"{gts[0].env_id} seed {gts[0].seed}: predicting")
        instructions = [gt.instruction for gt in gts]
        # The diagnostic's true futures, each encoded once per checkpoint (the same for every seed).
        starts = [None if cfg.start_from_truth is None else
                  [truth_clip(pipeline, gt, cam, n) for gt, cam, n in zip(gts, cameras, num_frames)]
                  for pipeline in pipelines]
        predictions = [[predict_at_data_resolution(pipeline, firsts, instructions, cameras, num_frames,
                                                   seed=seed, batch_size=batch_size,
                                                   num_steps=sampler[with_c]["num_steps"],
                                                   text_guidance=sampler[with_c]["text_guidance"],
                                                   noise_seeds=[scene_noise_seed(seed, gt.env_id, gt.seed) for gt in gts],
                                                   start_clips=start_clips, start_sigma=cfg.start_from_truth)
                        for seed in seeds]
                       for (with_c, _), pipeline, start_clips in zip(keys, pipelines, starts)]  # [checkpoint][seed][scene]
        for j, (path, gt, camera, first) in enumerate(zip(chunk, gts, cameras, firsts)):
            gt_cam = gt.cameras[camera]
            bar.set_postfix_str(f"{gt.env_id} seed {gt.seed}")
            moving = moving_region_mask(gt_cam)

            def score(method, output, token_rgb=None):
                """(metrics, per-object presence, contrast entry, direction score or None) of one output."""
                frames = output.cameras[camera] if isinstance(output, df.Episode) else output  # episode or Recon4D
                rgb = frames.rgb
                # Frame 0 is given to every method (the ceiling's is the truth's round trip): each is
                # scored on the frames it predicts, 1 on.
                metrics = evaluate_episode(output, gt, camera=camera, moving_mask=moving, max_depth_m=max_depth_m,
                                           first_scored_frame=1)["mean"]
                believe = episode_believability(gt, camera, rgb, method_patch[method], token_rgb=token_rgb,
                                                pred_depth_m=frames.depth_m, first_scored_frame=1)
                metrics.update(believe["metrics"])
                metrics.update(object_summary(episode_object_report(output, gt, camera)))
                sc = None
                if gt.env_id in TARGET_OBJECT and gt_cam.segmentation is not None:
                    sc = direction_score(gt.env_id, gt_cam.rgb, gt_cam.segmentation, gt_cam.seg_id_to_name,
                                         gt.object_poses[TARGET_OBJECT[gt.env_id]], gt_cam.K, gt_cam.T_world_cam,
                                         rgb[-1])
                return metrics, believe["per_object"], believe["contrast_entry"], sc

            # The ceiling and the static world draw no noise: scored once, the same in every seed's row.
            shared = {key: autoencoder_round_trip(pipelines[i], gt, camera) for key, i in ceilings.items()}
            shared["static"] = static_world(first, camera, num_frames[j])
            shared_scores = {method: score(method, output) for method, output in shared.items()}
            gt_believe = episode_believability(gt, camera, gt_cam.rgb, static_patch_px, pred_depth_m=gt_cam.depth_m,
                                               first_scored_frame=1)
            skill = (gt.intent or {}).get("skill") or "task"
            # The tracker on the truth itself (its frames, not its recorded poses): the object rows' ceiling.
            tracker_on_truth = episode_object_report(gt, gt, camera)
            for k, seed in enumerate(seeds):
                scored = {}
                for (with_c, raw), preds in zip(keys, predictions):
                    pred, token_rgb = preds[k][j]
                    scored[with_c] = score(with_c, reconstruct_episode(pred, config=ReconConfig(), objects_from=gt),
                                           token_rgb)
                    scored[raw] = score(raw, pred, token_rgb)
                scored.update(shared_scores)
                # Each seed's futures of a group are judged together (contrast is relative within a group).
                group = gt.group_id if len(seeds) == 1 or gt.group_id is None else f"{gt.group_id}#noise{seed}"
                row = {"episode": str(path.relative_to(data)), "task": gt.env_id, "seed": gt.seed,
                       "sample_seed": seed, "group_id": gt.group_id, "skill": skill,
                       "variant": (gt.intent or {}).get("variant"), "instruction": gt.instruction,
                       "target": (gt.intent or {}).get("target"), "metrics": {}, "direction": {}, "objects": {},
                       "token_grid_ratio_gt": gt_believe["metrics"]["token_grid_ratio"],
                       "object_tracks_truth": None if tracker_on_truth is None else tracker_on_truth["summary"]}
                if gt_believe["contrast_entry"] is not None:
                    contrast_entries["ground_truth"].append((group, gt_believe["contrast_entry"]))
                for method in methods:
                    metrics, per_object, entry, sc = scored[method]
                    row["metrics"][method] = dict(metrics)
                    row["objects"][method] = per_object
                    if entry is not None:
                        contrast_entries[method].append((group, entry))
                    if sc is not None:
                        scores[method].append(sc)
                        row["direction"][method] = sc.to_dict()
                rows.append(row)
            bar.update(1)
    bar.close()
    discrimination = {}
    for (with_c, raw), pipeline in zip(keys, pipelines):  # one network: the same with and without consistency
        discrimination[with_c] = discrimination[raw] = instruction_discrimination(pipeline, files, cfg.camera, seeds)
    report = build_report(cfg, rows, methods, labels, scores, contrast_entries, max_depth_m,
                          checkpoints=dict(zip([k[0] for k in keys], map(str, checkpoints))),
                          patch_px=dict(zip([k[0] for k in keys], patch_px)), resolutions=resolutions,
                          sampler=sampler, discrimination=discrimination)
    report = json_safe(report)
    if cfg.out is not None:
        write_heldout_report(report, cfg.out)
    return report


def build_report(cfg, rows: list[dict], methods: list[str], labels: dict, scores: dict, contrast_entries: dict,
                 max_depth_m: float, checkpoints: dict, patch_px: dict, resolutions: dict | None = None,
                 sampler: dict | None = None, discrimination: dict | None = None) -> dict:
    """The report of scored rows: summary, per task, per skill, instruction following, contrast.
    ``resolutions``: per checkpoint method, its model and data resolution and how it was resized;
    ``sampler``: per checkpoint method, the steps and text guidance it sampled with;
    ``discrimination``: per checkpoint method, its network's instruction discrimination."""
    summary = {}
    for method in methods:
        keys = rows[0]["metrics"][method].keys()
        summary[method] = {k: _finite_mean(r["metrics"][method][k] for r in rows) for k in keys}
    tasks = sorted({r["task"] for r in rows})
    contrast = {m: contrast_by_group(contrast_entries.get(m, [])) for m in methods + ["ground_truth"]}
    for m in methods:
        summary[m]["contrast"] = contrast[m]["share"]
        summary[m]["contrast_whole"] = contrast[m]["share_whole"]
        summary[m].update(presence_by_role(rows, m))
    config = {k: (str(v) if isinstance(v, Path) else [str(x) for x in v] if isinstance(v, (list, tuple)) else v)
              for k, v in dataclasses.asdict(cfg).items()}
    return {
        "format": "tesseract4d-heldout-eval", "format_version": 11,  # 11: clip measures from frame 1 on
        "config": config, "checkpoints": checkpoints, "sampler": sampler or {}, "token_patch_px": patch_px,
        "resolutions": resolutions or {},
        "episodes": len({r["episode"] for r in rows}), "sample_seeds": sorted({r.get("sample_seed", 0) for r in rows}),
        "tasks": tasks, "methods": {m: labels[m] for m in methods}, "max_depth_m": max_depth_m,
        "summary": summary, "per_task": breakdown(rows, methods, "task"), "per_skill": breakdown(rows, methods, "skill"),
        "episodes_per_task": counts(rows, "task"), "episodes_per_skill": counts(rows, "skill"),
        "token_grid_ratio_gt": _finite_mean(r["token_grid_ratio_gt"] for r in rows),
        "object_tracks_truth": truth_tracker_summary(rows),
        "instruction_following": {m: summarize(scores[m]) for m in methods},
        "instruction_following_per_task": direction_breakdown(rows, methods, "task"),
        "instruction_following_per_skill": direction_breakdown(rows, methods, "skill"),
        "contrast": contrast,
        "discrimination": discrimination or {},
        "rows": rows,
    }


def presence_by_role(rows: list[dict], method: str) -> dict:
    """Where object permanence is lost: the mean share of judged frames in which the instructed object
    (its intent's target) is present, and the same over every other scene object, over the rows that
    name a target; NaN where there is none."""
    instructed, others = [], []
    for r in rows:
        target = r.get("target")
        for name, share in (r.get("objects", {}).get(method) or {}).items():
            if target is not None and share is not None:
                (instructed if name == target else others).append(share)
    return {"objects_present_instructed": _finite_mean(instructed), "objects_present_others": _finite_mean(others)}


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


# A contrast share in the summary -> its Wilson interval in the report's contrast entry.
INTERVAL_OF = {"contrast": "wilson95", "contrast_whole": "wilson95_whole"}


def _interval(contrast: dict | None, key: str) -> str:
    """" (low–high)": the 95 % Wilson interval of a contrast share (``key``), when the report has it."""
    ci = (contrast or {}).get(key)
    return f" ({ci[0]:.2f}–{ci[1]:.2f})" if ci else ""


def _right_of(contrast: dict | None, kind: str) -> str:
    """"right / judged" of the "keep still" (``kind`` "still") or the active instructions."""
    c = contrast or {}
    return f"{c[kind + '_right']} / {c[kind + '_instructions']}" if kind + "_instructions" in c else "–"


def _arm_of(contrast: dict | None) -> str:
    """"at the instructed object / judged" of where the arm goes, "–" where nothing was judged."""
    c = contrast or {}
    if not c.get("arm_judged"):
        return "–"
    wrong = (f" (judged wrong: {c['arm_instructed_wrong']} / {c['arm_judged_wrong']})"
             if c.get("arm_judged_wrong") else "")
    return f"{c['arm_instructed']} / {c['arm_judged']}{wrong}"


def _discriminated(entry: dict | None) -> str:
    """"right / episodes (chance c)" of a network's instruction discrimination, "–" where none."""
    if not entry or not entry.get("episodes"):
        return "–"
    return f"{entry['right']} / {entry['episodes']} (chance {entry['chance']:.2f})"


def _words_won(entry: dict | None) -> str:
    """"words / pairs" of a network's words-over-the-noisy-sample judgments, "–" where none."""
    words = (entry or {}).get("words_over_sample") or {}
    return f"{words['words']} / {words['pairs']}" if words.get("pairs") else "–"


def _mark(key: str, value) -> str:
    met = goal_met(key, value)
    return "" if met is None else (" ✓" if met else " ✗")


def format_markdown(report: dict) -> str:
    """The results table: each metric over all pixels and over the moving region, per method;
    the best method per row in bold; then instruction following, the believability measures with
    their goals (✓ met, ✗ not met), and the per-skill / per-task breakdowns."""
    summary = report["summary"]
    methods = list(report.get("methods", METHOD_LABELS))
    labels = report.get("methods", METHOD_LABELS)
    head = "| metric | region | " + " | ".join(labels[m] for m in methods) + " |"
    lines = [head, "|" + "---|" * (2 + len(methods))]
    for key, label, higher in TABLE_METRICS:
        for region, suffix in (("all", ""), ("moving", "_moving")):
            vals = [summary[m].get(key + suffix) for m in methods]
            finite = [v for v in vals if v is not None and math.isfinite(v)]
            best = (max(finite) if higher else min(finite)) if finite else None
            cells = [f"**{_fmt(v, key)}**" if v is not None and v == best else _fmt(v, key) for v in vals]
            lines.append(f"| {label} | {region} | " + " | ".join(cells) + " |")
    follow = report["instruction_following"]
    lines.append(f"| instruction following: moved the right way (cos > {RIGHT_WAY_COSINE:g}) | target object | "
                 + " | ".join(_fmt(follow[m].get("right_way"), "") for m in methods) + " |")
    lines.append("| instruction following: mean cosine | target object | "
                 + " | ".join(_fmt(follow[m].get("mean_cosine"), "") for m in methods) + " |")
    believe = (
        ("objects_present", f"object permanence: frames with every object (goal ≥ {PRESENCE_GOAL:.0%})", "scene objects"),
        ("objects_present_instructed", "object permanence: frames with the instructed object, per object",
         "instructed object"),
        ("objects_present_others", "object permanence: frames with each other object, per object", "other objects"),
        ("contrast", f"instruction contrast: instructions right (goal ≥ {CONTRAST_GOAL:.0%})", "held-out groups"),
        ("contrast_whole", "instruction contrast, the moved object found whole", "held-out groups"),
        ("token_grid_ratio", f"token grid ratio (goal {TOKEN_GRID_GOAL[0]:g}–{TOKEN_GRID_GOAL[1]:g}; "
                             f"ground truth {_fmt(report.get('token_grid_ratio_gt'), '')})", "all"),
        ("edge_sharpness", f"edge sharpness vs ground truth (goal ≥ {EDGE_SHARPNESS_GOAL:g})", "ground-truth edges"),
        ("motion", "motion: mean absolute RGB change from the first predicted frame", "all"),
    )
    contrast = report.get("contrast") or {}
    for key, label, region in believe:
        if not any(key in summary[m] for m in methods):
            continue
        lines.append(f"| {label} | {region} | "
                     + " | ".join(_fmt(summary[m].get(key), "") + _mark(key, summary[m].get(key))
                                  + (_interval(contrast.get(m), INTERVAL_OF[key]) if key in INTERVAL_OF else "")
                                  for m in methods) + " |")
        if key == "contrast":
            if any(contrast.get(m, {}).get("still_instructions") for m in methods):
                lines.append("| instruction contrast: \"keep still\" right | held-out groups | "
                             + " | ".join(_right_of(contrast.get(m), "still") for m in methods) + " |")
            if any(contrast.get(m, {}).get("active_instructions") for m in methods):
                lines.append("| instruction contrast: active instructions right | held-out groups | "
                             + " | ".join(_right_of(contrast.get(m), "active") for m in methods) + " |")
            if any(contrast.get(m, {}).get("arm_judged") for m in methods):
                lines.append("| where the arm goes: the instructed object | active instructions | "
                             + " | ".join(_arm_of(contrast.get(m)) for m in methods) + " |")
    lines += markdown_rows(summary, methods, report.get("object_tracks_truth"))
    discrimination = report.get("discrimination") or {}
    if any(discrimination.get(m, {}).get("episodes") for m in methods):
        lines.append("| instruction discrimination: the network's one-step prediction from its own instruction "
                     "closest to the true future | held-out groups | "
                     + " | ".join(_discriminated(discrimination.get(m)) for m in methods) + " |")
    if any((discrimination.get(m, {}).get("words_over_sample") or {}).get("pairs") for m in methods):
        lines.append("| words over the noisy sample: shown another instruction's future noised to t = 0.5, the "
                     "prediction from its own words closer to its own future | held-out groups | "
                     + " | ".join(_words_won(discrimination.get(m)) for m in methods) + " |")
    first = methods[0]
    seeds = report.get("sample_seeds") or [report.get("config", {}).get("sample_seed", 0)]
    ns = len(seeds)
    n = follow[first].get("episodes", 0) // ns
    lines.append("")
    noise = (f"each predicted with {ns} noise seeds ({', '.join(map(str, seeds))}), every mean over all "
             f"{ns * report['episodes']} predictions; " if ns > 1 else "")
    lines.append(f"{report['episodes']} held-out episodes ({', '.join(report['tasks'])}); {noise}every clip measure "
                 f"over the predicted frames, 1 on (frame 0 is the given first frame; the ceiling's is its round "
                 f"trip); depth, normal and "
                 f"Chamfer metrics over pixels with true depth ≤ {report['max_depth_m']:g} m (the model's depth range); "
                 f"instruction following over the {n} of them whose target object the colour tracker can follow "
                 f"(tracker error on the ground truth: {_fmt(follow[first].get('tracker_px'), '')} px).")
    sampler = report.get("sampler") or {}
    if sampler:
        lines.append("Samplers: " + "; ".join(f"{m} {describe_sampler(v)}" for m, v in sampler.items()) + ".")
    resized = {m: r for m, r in report.get("resolutions", {}).items() if r.get("resized")}
    if resized:
        lines.append("Resolutions: " + "; ".join(
            f"{m} predicts {r['model'][0]}×{r['model'][1]}, {r['resized']} to the data's {r['data'][0]}×{r['data'][1]}"
            for m, r in resized.items())
            + "; the first frame is resized to the model's resolution and the prediction back "
              "(tesseract4d/resize.py); every metric is taken at the data's resolution but the token grid, which is "
              "measured on the prediction at the model's own resolution and token size.")
    if contrast and contrast[first].get("instructions"):
        gt = contrast.get("ground_truth", {})
        judged = contrast[first].get("instructions", 0)
        over = (f"{judged // ns} instructions in {contrast[first].get('groups', 0) // ns} groups, each judged with "
                f"{ns} noise seeds ({judged} judgments; the interval treats them as independent, which the seeds of "
                f"one instruction are not, so it is somewhat too narrow)" if ns > 1 else
                f"{judged} instructions in {contrast[first].get('groups', 0)} groups")
        lines.append(f"Instruction contrast over {over} (the ground truth itself scores "
                     f"{_fmt(gt.get('share'), '')}): an instruction is right when the tracked instructed object moves "
                     f"with cos > {RIGHT_WAY_COSINE:g} to its commanded image displacement; \"keep still\" when the "
                     f"clip's motion is at most {STILL_SHARE:.0%} of the group's active instructions'. In brackets: "
                     f"the 95 % Wilson interval of the share (a difference between two models well inside both "
                     f"intervals is within what the sample of instructions can show). \"Found whole\": a right active "
                     f"instruction counts only if the tracker finds the object in the last frame as one object of "
                     f"about its size (not a smear, fragments or a copy of its colour; the ground truth scores "
                     f"{_fmt(gt.get('share_whole'), '')}).")
        if gt.get("arm_measured"):
            lines.append(f"Where the arm goes (tesseract4d/evaluation/arm_target.py): the scene object with the most "
                         f"changed points just above the table near it, judged on the {gt['arm_judged']} of "
                         f"{gt['arm_measured']} active instructions where it finds the ground truth's own arm at the "
                         f"instructed object; a prediction's arm elsewhere is a wrong choice of object, its arm at "
                         f"the object with the instruction judged wrong a lost contact.")
    for by in ("per_skill", "per_task"):
        table, n_eps = report.get(by), report.get("episodes_" + by, {})
        if not table:
            continue
        follow_by = report.get("instruction_following_" + by, {})
        lines += ["", f"{by.replace('_', ' ')} (moving-region RGB PSNR / object permanence / contrast / "
                      f"moved the right way):", "",
                  f"| {by[4:]} | episodes | " + " | ".join(labels[m] for m in methods) + " |",
                  "|" + "---|" * (2 + len(methods))]
        for key, entry in table.items():
            cells = []
            for m in methods:
                c = (contrast or {}).get(m, {}).get(by, {}).get(key)
                right_way = follow_by.get(key, {}).get(m, {}).get("right_way")
                cells.append(f"{_fmt(entry[m].get('rgb_psnr_db_moving'), '')} / {_fmt(entry[m].get('objects_present'), '')}"
                             f" / {_fmt(c, '')} / {_fmt(right_way, '')}")
            lines.append(f"| {key} | {n_eps.get(key, '')} | " + " | ".join(cells) + " |")
    return "\n".join(lines)
