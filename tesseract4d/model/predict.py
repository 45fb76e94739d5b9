"""Prediction: first RGB-D-N frame + instruction -> predicted RGB-D-N episode (dataset format).

    pipe = load_pipeline("runs/tiny/final")
    first = render_first_frame("PickCube-v1", HELDOUT_SEED_START, height=64, width=64)   # or read_episode(...)
    pred = predict_episode(pipe, first, "pick up the red cube", seed=0)  # the preset's frames and steps
    write_prediction(pred, "out/prediction")      # episode .h5 + MP4 preview (RGB | depth | normal)

The predicted episode keeps the first frame's env id, seed, intrinsics and (static) camera pose;
its frame 0 is the given first frame, depth is metric (0 = beyond the model's depth range),
normals are unit vectors in the OpenCV camera frame.

A checkpoint whose preset has ``draws`` N > 1 predicts every future from N noise draws and keeps the
one whose objects keep their colours best (draw_choice.py; ``draws=`` overrides the preset); the
kept draw and every draw's score are in the episode's ``metadata["prediction"]["draws"]``.

An instruction schedule (``schedule=``, tesseract4d/instruction_schedule.py; a chained episode's own)
gives each clip of a long rollout the words of the segment it continues; the predicted episode keeps
the schedule in ``metadata["instruction_schedule"]`` and the words each clip got in
``metadata["prediction"]["clip_instructions"]``. ``on_clip(k, episode_so_far)`` receives the rollout
as each clip is decoded (streaming).

A first frame at a whole multiple or divisor of the model's resolution (256² or 64² for a 128² model)
is resized to it with its K (resize.py) and predicted there; ``metadata["prediction"]["first_frame_resized_from"]``
keeps its size.
"""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path
from typing import Callable

import numpy as np
import torch

from tesseract4d import dataset_format as df
from tesseract4d.errors import UserError
from tesseract4d.instruction_schedule import SCHEDULE_KEY, Segment, check_schedule, clip_instructions, clip_new_frames
from tesseract4d.precision import announce, resolve_precision
from tesseract4d.resize import episode_at_resolution, resize_factor
from tesseract4d.model.model_space import ModelSpace
from tesseract4d.model.draw_choice import check_draws, choose, draw_noise_seed, object_windows
from tesseract4d.model.checkpoint import INFERENCE_CONFIG_FILE, load_scheduler, load_transformer, read_inference_config
from tesseract4d.model.pipeline import RGBDNPipeline
from tesseract4d.model.presets import PRESETS, preset_from_dict
from tesseract4d.model.build import build_codec, build_text_encoder
from tesseract4d.model.recipe import check_samples_as_trained
from tesseract4d.model.latent_checkpoint import checkpoint_autoencoder
from tesseract4d.previews import write_preview

# Where a predicted episode records the size of a first frame it was resized from.
RESIZED_FROM = "first_frame_resized_from"
# The rate a predicted clip plays at (frames per second). The models learn clips whose frames are
# spread over a whole datagen episode, so a clip's pace is the training data's, not the first
# frame's (a rendered first frame carries the simulator's 20 Hz control rate): the median clip rate
# of the datasets the shipped models were trained on (v2_tabletop_160 3.2, v2_tasks_160 3.3 fps).
PREDICTED_CLIP_FPS = 3.3


def load_pipeline(checkpoint: str | os.PathLike, device: str = "cpu", precision: str = "auto") -> RGBDNPipeline:
    """Load an inference checkpoint folder (``tesseract4d checkpoint export``, or RUN/final).

    ``precision``: auto|fp32|bf16 (see tesseract4d/precision.py); auto = bf16 only where the
    hardware has native bf16.

    Raises UserError when the folder is missing, is not a tesseract4d checkpoint, names an unknown
    preset, or holds weights that do not match its preset.
    """
    ckpt = Path(checkpoint)
    cfg = read_inference_config(ckpt)
    check_samples_as_trained(cfg.get("recipe") or {}, ckpt)
    try:
        preset = preset_from_dict(cfg["preset"])
        space = ModelSpace(**cfg["model_space"])
    except (KeyError, TypeError) as e:
        raise UserError(f"{ckpt / INFERENCE_CONFIG_FILE} is corrupt ({type(e).__name__}: {e}); re-export the checkpoint") from e
    if cfg["preset"].get("name") not in PRESETS:
        raise UserError(f"{ckpt} uses preset {cfg['preset'].get('name')!r}, unknown to this tesseract4d "
                        f"(known: {', '.join(PRESETS)}); update tesseract4d or use a matching checkpoint")
    chosen = resolve_precision(precision, device)
    announce(chosen)
    pretrained = cfg.get("pretrained_dir")
    autoencoder = None
    if "autoencoder" in cfg:
        autoencoder = checkpoint_autoencoder(ckpt, cfg["autoencoder"])
    codec = build_codec(preset, pretrained, autoencoder=autoencoder)
    transformer = load_transformer(ckpt, preset, codec.modality_channels)
    text_encoder = build_text_encoder(preset, pretrained, device=device)
    if transformer.backbone.config.text_embed_dim != text_encoder.dim:
        raise UserError(f"{ckpt}: the transformer expects {transformer.backbone.config.text_embed_dim}-d text "
                        f"embeddings but the {preset.text_encoder} encoder gives {text_encoder.dim}")
    pipe = RGBDNPipeline(transformer, load_scheduler(ckpt, cfg), codec, text_encoder, preset, space,
                         camera_name=cfg.get("camera_name"), bf16=chosen.bf16, config=cfg)
    return pipe.to(device)


def _first_frame_arrays(first_frame: df.Episode, camera: str | None) -> tuple[str, df.CameraFrames]:
    if not first_frame.cameras:
        raise UserError("the first-frame episode has no camera")
    name = camera or next(iter(first_frame.cameras))
    if name not in first_frame.cameras:
        raise UserError(f"the first-frame episode has no camera {name!r}; it has {', '.join(first_frame.cameras)}")
    return name, first_frame.cameras[name]


def predict_episode(
    pipeline: RGBDNPipeline,
    first_frame: df.Episode,
    instruction: str,
    *,
    num_frames: int | None = None,
    seed: int = 0,
    num_steps: int | None = None,
    text_guidance: float | None = None,
    image_guidance: float | None = None,
    camera: str | None = None,
    progress: Callable[[int, int], None] | None = None,
    draws: int | None = None,
    schedule: list[Segment] | None = None,
    on_clip: Callable[[int, df.Episode], None] | None = None,
) -> df.Episode:
    """Predict ``num_frames`` RGB-D-N frames from frame 0 of ``first_frame`` (its first camera, or
    ``camera``) and ``instruction``. Frames (one clip), sampler steps and guidance scales default to
    the checkpoint's preset. ``schedule``/``on_clip``: see the module docstring.

    Raises UserError for an empty instruction or a first frame whose resolution is not the model's.
    """
    episodes = predict_episodes(pipeline, first_frame, instruction, num_samples=1, num_frames=num_frames, seed=seed,
                                num_steps=num_steps, text_guidance=text_guidance, image_guidance=image_guidance,
                                camera=camera, progress=progress, draws=draws, schedule=schedule, on_clip=on_clip)
    return episodes[0]


def instruction_budget_note(pipeline: RGBDNPipeline, instruction: str) -> str | None:
    """A warning when ``instruction`` is longer than the text encoder's token budget, else None."""
    n, budget = pipeline.text_encoder.count_tokens(instruction), pipeline.text_encoder.max_tokens
    if n <= budget:
        return None
    return (f"warning: the instruction has {n} tokens; the text encoder keeps the first {budget} "
            f"({len(instruction)} characters given); shorten it to say what matters first")


def predict_episodes(
    pipeline: RGBDNPipeline,
    first_frame: df.Episode,
    instruction: str,
    *,
    num_samples: int = 1,
    num_frames: int | None = None,
    seed: int = 0,
    num_steps: int | None = None,
    text_guidance: float | None = None,
    image_guidance: float | None = None,
    camera: str | None = None,
    progress: Callable[[int, int], None] | None = None,
    draws: int | None = None,
    schedule: list[Segment] | None = None,
    on_clip: Callable[[int, df.Episode], None] | None = None,
) -> list[df.Episode]:
    """``num_samples`` different predictions of the same first frame, sampled as one batch from the
    generator seeded with ``seed`` (same arguments, same episodes); each the best of ``draws``.
    ``schedule``: the instructions by frame (then ``instruction`` is the episode's one line);
    ``on_clip(k, episode)``: the first sample's rollout up to clip k, as each clip is decoded (with
    several draws, the first draw's)."""
    num_frames, num_steps = _check_sampling(pipeline, num_frames, num_steps, num_samples)
    scenes = [_scene(pipeline, first_frame, instruction, camera, schedule)] * num_samples

    def draw(k: int, step_progress) -> list[df.Episode]:
        return _predict_batch(pipeline, scenes, list(range(num_samples)), num_frames=num_frames,
                              num_steps=num_steps, text_guidance=text_guidance, image_guidance=image_guidance,
                              seed=seed, generator=torch.Generator().manual_seed(draw_noise_seed(seed, k)),
                              progress=step_progress, on_clip=on_clip if k == 0 else None)

    return _best_of_draws(pipeline, scenes, draw, draws, progress)


def predict_counterfactuals(
    pipeline: RGBDNPipeline,
    first_frame: df.Episode,
    instructions: list[str],
    *,
    num_frames: int | None = None,
    seed: int = 0,
    num_steps: int | None = None,
    text_guidance: float | None = None,
    image_guidance: float | None = None,
    camera: str | None = None,
    progress: Callable[[int, int], None] | None = None,
    draws: int | None = None,
) -> list[df.Episode]:
    """One future of the same first frame per instruction, sampled as one batch from the same
    initial noise, so the futures differ only by their words (a counterfactual group).

    The shared noise is what :func:`predict_episode` draws for ``seed`` with the pixel and latent
    presets, so there future i is the prediction of ``instructions[i]`` alone with that seed (up
    to floating-point rounding of batched maths). Frames beyond one clip continue with noise
    drawn per future. With ``draws`` N > 1 every draw's noise is shared by the group, and each
    instruction keeps its own best of the N.
    """
    if not instructions:
        raise UserError("no instructions to predict; give at least one")
    num_frames, num_steps = _check_sampling(pipeline, num_frames, num_steps, 1)
    scenes = [_scene(pipeline, first_frame, text, camera) for text in instructions]

    def draw(k: int, step_progress) -> list[df.Episode]:
        s = draw_noise_seed(seed, k)
        noise = torch.randn(pipeline.latent_shape(1), generator=torch.Generator().manual_seed(s))  # (1, t', c, h, w)
        return _predict_batch(pipeline, scenes, [0] * len(scenes), num_frames=num_frames, num_steps=num_steps,
                              text_guidance=text_guidance, image_guidance=image_guidance, seed=seed,
                              generator=torch.Generator().manual_seed(s),
                              latents=noise.expand(len(scenes), *noise.shape[1:]), progress=step_progress)

    return _best_of_draws(pipeline, scenes, draw, draws, progress)


# Scenes per pipeline call of predict_scenes when not given. Measured with
# benchmarks/bench_throughput.py on a quiet 2-core AMD EPYC with AVX512-BF16, clips/s for 1/2/4/8
# scenes per call: the default v2-2step in bf16 2.45/2.70/2.84/2.97, capped to AVX2 (fp32)
# 2.30/2.44/2.31/2.14; v2 (10 guided steps) for 1/4: 0.52/0.61 bf16, 0.49/0.46 capped. 4 is within 7%
# of the best everywhere and keeps memory moderate. Re-measure on another machine.
DEFAULT_SCENE_BATCH = 4


def predict_scenes(
    pipeline: RGBDNPipeline,
    first_frames: list[df.Episode],
    instructions: list[str],
    *,
    batch_size: int | None = None,
    num_frames: int | None = None,
    seed: int = 0,
    num_steps: int | None = None,
    text_guidance: float | None = None,
    image_guidance: float | None = None,
    camera: str | None = None,
    noise_seeds: list[int] | None = None,
    progress: Callable[[int, int], None] | None = None,
    start_clips: list[torch.Tensor] | None = None,
    start_sigma: float | None = None,
    draws: int | None = None,
    schedules: list[list[Segment] | None] | None = None,
) -> list[df.Episode]:
    """One prediction per scene (``first_frames[i]`` with ``instructions[i]``, clip by clip the words of
    ``schedules[i]`` when given and not None), ``batch_size`` scenes
    per network call (default :data:`DEFAULT_SCENE_BATCH`): the throughput path for evaluations.
    ``start_clips`` (one (1, t', c, h, w) clean clip per scene in the network's space) and
    ``start_sigma``: the pipeline's ``start`` diagnostic, each scene from its own clip.

    Scene i's initial noise comes from a generator seeded with (``seed``, i), or with
    ``noise_seeds[i]`` when given, so its first clip does not depend on ``batch_size`` or on the
    other scenes (up to floating-point rounding of batched maths). A noise seed s draws the noise
    that :func:`predict_episode` with ``seed=s`` draws, for codecs whose encoding draws none (pixel
    and autoencoder presets). ``progress(step, total)`` counts denoising steps over all batches (and
    draws). Each scene keeps the best of ``draws``; draw k of scene i starts from
    ``draw_noise_seed(its noise seed, k)``.
    """
    if len(first_frames) != len(instructions):
        raise UserError(f"{len(first_frames)} first frames for {len(instructions)} instructions; give one of each per scene")
    if noise_seeds is not None and len(noise_seeds) != len(first_frames):
        raise UserError(f"{len(noise_seeds)} noise seeds for {len(first_frames)} scenes; give one per scene, or none")
    if (start_clips is None) != (start_sigma is None) or (start_clips is not None and len(start_clips) != len(first_frames)):
        raise ValueError("start_clips needs start_sigma and one clip per scene")
    batch_size = DEFAULT_SCENE_BATCH if batch_size is None else int(batch_size)
    if batch_size < 1:
        raise UserError(f"--batch-size must be at least 1, got {batch_size}")
    num_frames, num_steps = _check_sampling(pipeline, num_frames, num_steps, 1)
    if schedules is not None and len(schedules) != len(first_frames):
        raise UserError(f"{len(schedules)} instruction schedules for {len(first_frames)} scenes; give one per scene "
                        f"(None for a scene with one instruction)")
    scenes = [_scene(pipeline, f, i, camera, None if schedules is None else schedules[j])
              for j, (f, i) in enumerate(zip(first_frames, instructions))]
    num_batches = -(-len(scenes) // batch_size)
    noise_shape = pipeline.latent_shape(1)  # (1, t', c, h, w); asks the codec once, not per scene
    scene_seeds = [int(seed) * 1_000_003 + i if noise_seeds is None else int(noise_seeds[i]) for i in range(len(scenes))]

    def draw(k: int, draw_progress) -> list[df.Episode]:
        out: list[df.Episode] = []
        for b in range(num_batches):
            chunk = range(b * batch_size, min(len(scenes), (b + 1) * batch_size))
            latents = torch.cat([torch.randn(noise_shape, generator=torch.Generator().manual_seed(
                draw_noise_seed(scene_seeds[i], k))) for i in chunk])
            step_progress = None
            if draw_progress is not None:
                step_progress = (lambda s, t, b=b: draw_progress(b * t + s, num_batches * t))
            start = None if start_clips is None else (torch.cat([start_clips[i] for i in chunk]), float(start_sigma))
            out += _predict_batch(pipeline, [scenes[i] for i in chunk], [0] * len(chunk), num_frames=num_frames,
                                  num_steps=num_steps, text_guidance=text_guidance, image_guidance=image_guidance,
                                  seed=seed, generator=torch.Generator().manual_seed(draw_noise_seed(int(seed) + b, k)),
                                  latents=latents, progress=step_progress, start=start)
        return out

    return _best_of_draws(pipeline, scenes, draw, draws, progress)


def _best_of_draws(pipeline: RGBDNPipeline, scenes: list, draw: Callable, draws: int | None,
                   progress: Callable[[int, int], None] | None) -> list[df.Episode]:
    """Every scene's kept future of ``draws`` (default: the preset's) noise draws (draw_choice.py).
    ``draw(k, progress)`` predicts all ``scenes`` from draw k's noise. A first frame's objects are its
    segmentation's, or found by colour without one; a scene with none keeps draw 0, and when no scene
    has any only draw 0 is sampled."""
    draws = check_draws(pipeline.preset.draws if draws is None else draws)
    found: dict[int, list] = {}  # a first frame's objects, found once however many samples share it

    def windows_of(cam) -> list:
        if id(cam) not in found:
            found[id(cam)] = object_windows(cam.rgb[0], None if cam.segmentation is None else cam.segmentation[0],
                                            cam.seg_id_to_name)
        return found[id(cam)]

    windows = [windows_of(cam) for _, _, _, cam, _, _ in scenes] if draws > 1 else []
    if not any(windows):
        draws = 1
    candidates = []
    for k in range(draws):
        draw_progress = None
        if progress is not None:
            draw_progress = (lambda s, t, k=k: progress(k * t + s, draws * t))
        candidates.append(draw(k, draw_progress))
    if draws == 1:
        return candidates[0]
    out = []
    for i, (_, _, cam_name, _, _, _) in enumerate(scenes):
        kept, scores = choose(windows[i], [c[i].cameras[cam_name].rgb for c in candidates])
        episode = candidates[kept][i]
        episode.metadata["prediction"]["draws"] = {"count": draws, "kept": kept, "objects_kept": scores}
        out.append(episode)
    return out


def _check_sampling(pipeline: RGBDNPipeline, num_frames, num_steps, num_samples) -> tuple[int, int]:
    num_frames = pipeline.num_frames if num_frames is None else int(num_frames)
    num_steps = pipeline.preset.num_steps if num_steps is None else int(num_steps)
    if num_frames < 1 or num_steps < 1 or num_samples < 1:
        raise UserError("--num-frames, --steps and --num-samples must be at least 1")
    return num_frames, num_steps


def _scene(pipeline: RGBDNPipeline, first_frame: df.Episode, instruction: str, camera: str | None,
           schedule: list[Segment] | None = None):
    """(first-frame episode, instruction, camera name, its frames, model-space frame 0 (1, 7, H, W),
    instruction schedule or None)."""
    if schedule is not None:
        check_schedule(schedule)
    if not isinstance(instruction, str) or not instruction.strip():
        raise UserError("the instruction is empty; say what should happen, e.g. --instruction \"pick up the red cube\"")
    cam_name, cam = _first_frame_arrays(first_frame, camera)
    h, w = cam.rgb.shape[1:3]
    if (h, w) != tuple(pipeline.resolution):
        H, W = pipeline.resolution
        if resize_factor((h, w), (H, W)) is None:
            raise UserError(f"the first frame is {h}x{w} but the model predicts {H}x{W}; it is resized for the model "
                            f"only by a whole factor on both axes (e.g. {2 * H}x{2 * W} or {H // 2}x{W // 2}): crop or "
                            f"render it to such a size, scaling K with it")
        # A whole factor: the first frame at the model's resolution (resize.py), the prediction there.
        first_frame = episode_at_resolution(first_frame, cam_name, (H, W))
        first_frame = dataclasses.replace(first_frame, metadata={**first_frame.metadata, RESIZED_FROM: [h, w]})
        cam = first_frame.cameras[cam_name]
    x = pipeline.model_space.encode(cam.rgb[:1], cam.depth_m[:1], cam.normal_cam[:1])  # (1, 7, H, W)
    return first_frame, instruction.strip(), cam_name, cam, x, schedule


def _clip_words(pipeline: RGBDNPipeline, scenes: list, num_frames: int) -> list[list[str]] | None:
    """Per clip of the rollout, each scene's words (its schedule's, else its instruction); None when
    no scene has a schedule."""
    if all(s[5] is None for s in scenes):
        return None
    history = pipeline.preset.history_frames
    num_clips = len(clip_new_frames(num_frames, pipeline.num_frames, history))
    per_scene = [[s[1]] * num_clips if s[5] is None else clip_instructions(s[5], num_frames, pipeline.num_frames,
                                                                            history)
                 for s in scenes]
    return [list(words) for words in zip(*per_scene)]


def _predict_batch(pipeline: RGBDNPipeline, scenes: list, sample_indices: list[int], *, num_frames: int,
                   num_steps: int, text_guidance, image_guidance, seed: int, generator: torch.Generator,
                   latents: torch.Tensor | None = None, progress=None, start=None,
                   on_clip: Callable[[int, df.Episode], None] | None = None) -> list[df.Episode]:
    """One pipeline call for the given scenes (from :func:`_scene`), returned as predicted episodes.
    ``on_clip(k, episode)``: the first scene's rollout so far, after each decoded clip."""
    x = torch.cat([s[4] for s in scenes])  # (n, 7, H, W)
    clip_words = _clip_words(pipeline, scenes, num_frames)
    decoded: list[torch.Tensor] = []

    def stream(k: int, frames: torch.Tensor) -> None:  # frames (n, t_k, 7, H, W)
        decoded.append(frames[:1])
        so_far = torch.cat(decoded, dim=1)[0]  # (t, 7, H, W)
        on_clip(k, _episodes(pipeline, scenes[:1], so_far[None], [sample_indices[0]], num_steps, text_guidance,
                             image_guidance, seed, start, clip_words)[0])

    clips = pipeline(x, [s[1] for s in scenes], num_frames=num_frames, num_inference_steps=num_steps,
                     text_guidance=text_guidance, image_guidance=image_guidance, generator=generator,
                     progress=progress, latents=latents, start=start, clip_instructions=clip_words,
                     on_clip=None if on_clip is None else stream)  # (n, T, 7, H, W)
    return _episodes(pipeline, scenes, clips, sample_indices, num_steps, text_guidance, image_guidance, seed, start,
                     clip_words)


def _episodes(pipeline: RGBDNPipeline, scenes: list, clips: torch.Tensor, sample_indices: list[int], num_steps: int,
              text_guidance, image_guidance, seed: int, start, clip_words: list[list[str]] | None) -> list[df.Episode]:
    """Model-space clips (n, T, 7, H, W) of ``scenes`` as predicted episodes."""
    num_frames = clips.shape[1]
    out = []
    for k, (first_frame, instruction, cam_name, cam, _, schedule) in enumerate(scenes):
        rgb, depth_m, normal_cam = pipeline.model_space.decode(clips[k])
        # Frame 0 is the given first frame, exactly.
        rgb[0], depth_m[0], normal_cam[0] = cam.rgb[0], cam.depth_m[0], cam.normal_cam[0]
        frames = df.CameraFrames(
            rgb=rgb, depth_m=depth_m, normal_cam=normal_cam,
            K=np.repeat(np.asarray(cam.K[:1], np.float64), num_frames, 0),
            T_world_cam=np.repeat(np.asarray(cam.T_world_cam[:1], np.float64), num_frames, 0),
        )
        out.append(df.Episode(
            env_id=first_frame.env_id, seed=first_frame.seed, instruction=instruction, cameras={cam_name: frames},
            frame_steps=np.arange(num_frames, dtype=np.int32), env_kwargs=dict(first_frame.env_kwargs),
            control_mode=first_frame.control_mode, fps=PREDICTED_CLIP_FPS, source="prediction",
            metadata={"prediction": {
                "checkpoint_preset": pipeline.preset.name, "sample_seed": int(seed), "sample_index": sample_indices[k],
                "num_steps": int(num_steps), "text_guidance": text_guidance, "image_guidance": image_guidance,
                **({} if start is None else {"started_from_clip_at_noise": float(start[1])}),
                **({RESIZED_FROM: first_frame.metadata[RESIZED_FROM]} if RESIZED_FROM in first_frame.metadata else {}),
                "depth_range_m": [pipeline.model_space.near_m, pipeline.model_space.far_m],
                "training": pipeline.config.get("training"),
                **({} if schedule is None else {"clip_instructions": [words[k] for words in clip_words]}),
            }, **({} if schedule is None else {SCHEDULE_KEY: [seg.to_dict() for seg in schedule]})},
        ))
    return out


def write_prediction(episode: df.Episode, out_dir: str | os.PathLike) -> Path:
    """Write a predicted episode as a one-episode dataset folder (``out_dir``) with its MP4 preview
    (RGB | depth | normal); returns the episode's .h5 path."""
    path = df.write_episode_dataset(out_dir, episode)
    write_preview(out_dir, episode)
    return path
