"""Predict the RGB-D-N future of a scene from its first frame and an instruction.

The first frame comes from one of:
  --task PickCube-v1 --seed 100000        rendered by ManiSkill (the checkpoint's camera preset)
  --episode DIR/ENV_ID/SEED | FILE.h5     frame 0 of a dataset episode
  --rgb IMG --depth DEPTH --K K           your own files: depth as .npy (metres) or 16-bit PNG (mm);
                                          K as .npy/.txt (3x3) or .json; normals (--normal .npy) are
                                          derived from depth when not given

A first frame at a whole multiple or divisor of the model's resolution (e.g. 256x256 or 64x64 for
the shipped 128x128 models) is resized to it, K with it, and predicted there; other sizes are
refused with the sizes that work.

  tesseract4d predict --checkpoint runs/tiny/final --task PickCube-v1 --seed 100000 \\
      --instruction "pick up the red cube" --out out/pred

A chained --episode (datagen `--set chain_skills=N`) is predicted with its instruction schedule and
length: each clip of the rollout gets the words of the segment it continues; `--set schedule=...`
gives a schedule of your own. Each clip's time is printed as it is decoded.

Writes OUT as a dataset folder (episodes/<env>/seed_*.h5 + previews/*.mp4), one folder per sample
(OUT/sample_XX) with --num-samples > 1, and OUT/predict_config.json.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from tesseract4d.cli.argument_types import number, seed, whole
from tesseract4d.cli.config_args import PRECISION_MOVED, add_moved_to_set, add_set_option, dataclass_from_args
from tesseract4d.configs import knob
from tesseract4d.dataset_format import HELDOUT_SEED_START
from tesseract4d.errors import UserError
from tesseract4d.precision import precision_field
from tesseract4d.model.checkpoint import SHIPPED_CHECKPOINT


@dataclass
class PredictConfig:
    checkpoint: Path = SHIPPED_CHECKPOINT
    instruction: str | None = None
    task: str | None = None
    seed: int | None = None
    episode: str | None = None
    rgb: Path | None = None
    depth: Path | None = None
    K: Path | None = None
    normal: Path | None = None
    out: Path = Path("prediction")
    num_frames: int | None = knob(None, "frames to predict; more than one clip continues autoregressively "
                                        "(none: one clip, the checkpoint preset's length; a chained --episode's "
                                        "length when it has a schedule)")
    schedule: str | None = knob(None, "instructions by frame, 'FRAME:WORDS;FRAME:WORDS' from frame 0, e.g. "
                                      "'0:push the red cube left;30:lift the blue cylinder': each clip of a long "
                                      "rollout gets the words of the segment it continues (none: a chained "
                                      "--episode's own schedule, unless --instruction is given)")
    steps: int | None = None  # None: the checkpoint preset's
    draws: int | None = knob(None, "noise draws per sample, the one whose objects keep their colours best kept; N "
                                   "times the sampling (none: the checkpoint preset's; 1 = a single draw)")
    sample_seed: int = 0
    num_samples: int = knob(1, "samples to draw in one batch")
    text_guidance: float | None = None
    image_guidance: float | None = knob(None, "first-frame guidance scale (none: the checkpoint preset's; 1 = none)")
    device: str = knob("cpu", "torch device")
    precision: str = precision_field()


def add_arguments(parser: argparse.ArgumentParser) -> None:
    d = PredictConfig()
    parser.add_argument("--checkpoint", type=Path, default=d.checkpoint,
                        help="inference checkpoint folder (RUN/final or `checkpoint export` output; default: the shipped v2-2step; tesseract4d/checkpoints/v2 is its 10-step teacher)")
    parser.add_argument("--instruction", help="what should happen (default: the episode's / scene's own instruction)")
    src = parser.add_argument_group("first frame (one of)")
    src.add_argument("--task", help="ManiSkill task id to render, with --seed")
    src.add_argument("--seed", type=seed(), help="scene seed for --task")
    src.add_argument("--episode", help="dataset episode: FILE.h5, DIR/ENV_ID/SEED or a one-episode dataset folder")
    src.add_argument("--rgb", type=Path, help="RGB image file")
    src.add_argument("--depth", type=Path, help="depth: .npy in metres or 16-bit PNG in millimetres")
    src.add_argument("--K", type=Path, help="3x3 pixel intrinsics: .npy, .txt or .json")
    src.add_argument("--normal", type=Path, help="optional (H, W, 3) .npy unit normals, OpenCV camera frame")
    parser.add_argument("--out", type=Path, default=d.out, help="output folder (default %(default)s)")
    parser.add_argument("--steps", type=whole(1), help="sampler steps (default: the checkpoint preset's)")
    parser.add_argument("--sample-seed", type=seed(), default=d.sample_seed, help="noise seed (default %(default)s)")
    parser.add_argument("--text-guidance", type=number(0, above=True, hint=" (1: no guidance)"), help="text guidance scale (default: the checkpoint preset's)")
    parser.add_argument("--overwrite", action="store_true",
                        help="write into a folder holding other files (only this command's files are replaced)")
    add_set_option(parser, PredictConfig)
    add_moved_to_set(parser, PredictConfig, [
        ("--num-frames", "num_frames", whole(1)), ("--draws", "draws", whole(1, hint=" (1: a single draw)")),
        ("--image-guidance", "image_guidance", number(0, above=True, hint=" (1: no guidance)")),
        ("--device", "device"), ("--num-samples", "num_samples", whole(1)), PRECISION_MOVED,
    ])


def _read_K(path: Path) -> np.ndarray:
    fix = ("write the 3x3 pixel intrinsics [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] as 3 rows of 3 numbers (.txt), "
           "a nested list (.json) or a (3, 3) array (.npy)")
    try:
        if path.suffix == ".json":
            K = np.asarray(json.loads(path.read_text()), np.float64)
        elif path.suffix == ".npy":
            K = np.load(path).astype(np.float64)
        else:
            K = np.loadtxt(path, dtype=np.float64, ndmin=2)
    except (ValueError, TypeError, OSError) as e:  # unparsable text, JSON or .npy; a dict or strings in the JSON
        raise UserError(f"{path}: cannot read K ({str(e).splitlines()[0]}); {fix}") from None
    if K.shape != (3, 3):
        raise UserError(f"{path}: K must be a 3x3 matrix, got shape {K.shape}; {fix}")
    if not np.isfinite(K).all() or K[0, 0] <= 0 or K[1, 1] <= 0:
        raise UserError(f"{path}: K needs finite numbers and focal lengths fx = K[0][0], fy = K[1][1] > 0; {fix}")
    return K


def _read_depth(path: Path) -> np.ndarray:
    if path.suffix == ".npy":
        depth = _read_npy(path, f"{path}: cannot read depth", "pass an (H, W) .npy in metres or a 16-bit PNG in millimetres")
    else:
        depth = _read_image(path, "--depth", "a 16-bit PNG in millimetres, or an (H, W) .npy in metres")
        if depth.dtype != np.uint16:
            raise UserError(f"{path}: a depth PNG must be 16-bit millimetres (got {depth.dtype}); or pass a .npy in metres")
        depth = depth.astype(np.float32) / 1000.0
    if depth.ndim != 2:
        raise UserError(f"{path}: depth must be one (H, W) image, got shape {depth.shape}")
    if not np.isfinite(depth).all() or (depth < 0).any() or not (depth > 0).any():
        finite = depth[np.isfinite(depth)]
        got = f"{finite.min()} .. {finite.max()}" if finite.size else "no finite value"
        raise UserError(f"{path}: depth must be finite metres >= 0 (0: no reading) with some pixels > 0; got {got}")
    return depth


def _read_normals(path: Path, size: tuple[int, int]) -> np.ndarray:
    normal_cam = _read_npy(path, f"--normal {path}: cannot read it", "pass an (H, W, 3) .npy of unit normals in the "
                           "OpenCV camera frame, or leave --normal out to derive them from the depth")
    if normal_cam.shape != (*size, 3) or not np.isfinite(normal_cam).all():
        raise UserError(f"--normal {path}: expected finite (H, W, 3) = {(*size, 3)} unit normals, got shape "
                        f"{normal_cam.shape}; or leave --normal out to derive them from the depth")
    return normal_cam


def _read_npy(path: Path, what: str, fix: str) -> np.ndarray:
    """A .npy array as float32, or a UserError: ``what`` (the reason numpy gives); ``fix``."""
    try:
        return np.load(path).astype(np.float32)
    except (ValueError, TypeError, OSError) as e:
        raise UserError(f"{what} ({str(e).splitlines()[0]}); {fix}") from None


def _read_image(path: Path, flag: str, what: str) -> np.ndarray:
    """An image file's pixels, or a UserError saying what the flag takes."""
    import imageio.v2 as imageio

    try:
        return np.asarray(imageio.imread(path))
    except (ValueError, OSError) as e:
        raise UserError(f"{flag} {path} is not an image file imageio can read ({str(e).splitlines()[0]}); "
                        f"pass {what}") from None


def first_frame_from_files(rgb: Path, depth: Path, K: Path, normal: Path | None = None):
    """A one-frame Episode (env_id "user", identity camera pose) from user files."""
    from tesseract4d.dataset_format import CameraFrames, Episode
    from tesseract4d.geometry import normals_from_depth

    for name, p in (("--rgb", rgb), ("--depth", depth), ("--K", K)):
        if p is None:
            raise UserError("--rgb, --depth and --K go together: pass all three")
        if not Path(p).is_file():
            raise UserError(f"{name} {p} does not exist")
    image = _read_image(rgb, "--rgb", "a PNG or JPEG colour image")
    if image.ndim != 3 or image.shape[-1] not in (3, 4):
        raise UserError(f"{rgb}: expected an RGB image, got shape {image.shape}")
    if image.dtype == np.uint16:  # a 16-bit PNG: its top 8 bits
        image = (image // 257).astype(np.uint8)
    elif image.dtype != np.uint8:
        raise UserError(f"{rgb}: expected 8- or 16-bit colour, got {image.dtype}; save it as an 8-bit PNG")
    image = np.ascontiguousarray(image[..., :3])
    depth_m = _read_depth(depth)
    if depth_m.shape != image.shape[:2]:
        raise UserError(f"depth {depth_m.shape} and rgb {image.shape[:2]} differ in size")
    K_mat = _read_K(K)
    normal_cam = _read_normals(normal, depth_m.shape) if normal is not None else normals_from_depth(depth_m, K_mat)
    cam = CameraFrames(rgb=image[None], depth_m=depth_m[None], normal_cam=normal_cam[None], K=K_mat[None],
                       T_world_cam=np.eye(4)[None])
    return Episode(env_id="user", seed=0, instruction="", cameras={"user": cam}, frame_steps=np.zeros(1, np.int32))


def load_first_frame(cfg: PredictConfig, resolution: tuple[int, int], camera: str | None):
    sources = [cfg.task is not None, cfg.episode is not None, any(x is not None for x in (cfg.rgb, cfg.depth, cfg.K))]
    if sum(sources) != 1:
        raise UserError("give the first frame in exactly one way: --task ID --seed S, --episode PATH, or --rgb/--depth/--K")
    if cfg.task is not None:
        if cfg.seed is None:
            raise UserError(f"--task needs --seed (scene seeds from {HELDOUT_SEED_START} on are never used in training)")
        from datagen.simulate import render_first_frame

        return render_first_frame(cfg.task, cfg.seed, height=resolution[0], width=resolution[1], camera=camera or "close")
    if cfg.episode is not None:
        from tesseract4d import dataset_format as df

        return df.read_episode(df.resolve_episode(cfg.episode), frames=slice(0, 1), check=True)
    return first_frame_from_files(cfg.rgb, cfg.depth, cfg.K, cfg.normal)


def check_device(device: str) -> None:
    """One-line errors for a device torch does not know or this machine does not have."""
    import torch

    try:
        kind = torch.device(device).type
    except (RuntimeError, ValueError):
        raise UserError(f"--device {device!r} is not a torch device; use cpu, cuda or cuda:N") from None
    if kind == "cuda" and not torch.cuda.is_available():
        raise UserError(f"--device {device}: CUDA is not available on this machine; use --device cpu")
    if kind == "cuda" and torch.device(device).index is not None and torch.device(device).index >= torch.cuda.device_count():
        raise UserError(f"--device {device}: this machine has {torch.cuda.device_count()} CUDA device(s)")
    if kind == "mps" and not torch.backends.mps.is_available():
        raise UserError(f"--device {device}: MPS is not available on this machine; use --device cpu")


def _input_paths(cfg: PredictConfig) -> list:
    from tesseract4d import dataset_format as df

    paths = [cfg.checkpoint, cfg.rgb, cfg.depth, cfg.K, cfg.normal]
    if cfg.episode is not None:
        paths += [cfg.episode, df.resolve_episode(cfg.episode)]
    return paths


def _schedule_and_instruction(cfg: PredictConfig, first) -> tuple[list | None, str | None]:
    """The instruction schedule (``--set schedule``, else a chained episode's own unless --instruction
    is given) and the episode's one instruction."""
    from tesseract4d.instruction_schedule import chained_instruction, parse_schedule, schedule_of

    if cfg.schedule is not None:
        schedule = parse_schedule(cfg.schedule)
        return schedule, cfg.instruction or chained_instruction([s.instruction for s in schedule])
    if cfg.instruction is not None:
        return None, cfg.instruction
    return schedule_of(first.metadata), first.instruction


def run(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from tesseract4d.model.predict import instruction_budget_note, load_pipeline, predict_episodes, write_prediction
    from tesseract4d.model.text_encoder import check_instruction
    from tesseract4d.outputs import OutputDir

    cfg = dataclass_from_args(PredictConfig, args)
    check_instruction(cfg.instruction)
    check_device(cfg.device)
    output = OutputDir(cfg.out, "predict", inputs=_input_paths(cfg), overwrite=args.overwrite)
    pipe = load_pipeline(cfg.checkpoint, device=cfg.device, precision=cfg.precision)
    frames_given = cfg.num_frames is not None
    # The resolved config: frames and steps the checkpoint's preset gives when not set.
    cfg = dataclasses.replace(cfg, num_frames=cfg.num_frames or pipe.num_frames, steps=cfg.steps or pipe.preset.num_steps,
                              draws=pipe.preset.draws if cfg.draws is None else cfg.draws)
    first = load_first_frame(cfg, pipe.resolution, pipe.camera_name)
    schedule, instruction = _schedule_and_instruction(cfg, first)
    if schedule is not None and not frames_given and schedule[-1].frame_end is not None:
        cfg = dataclasses.replace(cfg, num_frames=schedule[-1].frame_end + 1)  # the chained episode's own length
    # The words that reach the model: each segment's with a schedule, else the one instruction.
    for words in ([s.instruction for s in schedule] if schedule is not None else [instruction]):
        if isinstance(words, str) and (note := instruction_budget_note(pipe, words.strip())):
            print(note, file=sys.stderr)
    bars = []  # made at the first step, so that a first frame refused before sampling leaves no empty bar

    def progress(step: int, total: int) -> None:
        if not bars:
            bars.append(tqdm(desc="predict", unit="step", total=total))
        bars[0].total = total
        bars[0].update(step - bars[0].n)

    started = time.perf_counter()

    def clip_done(k: int, so_far) -> None:  # streaming: each clip's frames are final once it is decoded
        tqdm.write(f"clip {k + 1}: frames 0-{so_far.num_frames - 1} ready after {time.perf_counter() - started:.2f} s",
                   file=sys.stderr)  # above the progress bar

    episodes = predict_episodes(pipe, first, instruction, num_samples=cfg.num_samples, num_frames=cfg.num_frames,
                                seed=cfg.sample_seed, num_steps=cfg.steps, text_guidance=cfg.text_guidance,
                                image_guidance=cfg.image_guidance, progress=progress, draws=cfg.draws,
                                schedule=schedule, on_clip=clip_done if cfg.num_frames > pipe.num_frames else None)
    for bar in bars:
        bar.close()
    if resized := episodes[0].metadata["prediction"].get("first_frame_resized_from"):
        print(f"note: the {resized[0]}x{resized[1]} first frame was resized to the model's "
              f"{pipe.resolution[0]}x{pipe.resolution[1]} (K scaled with it); the prediction is at "
              f"{pipe.resolution[0]}x{pipe.resolution[1]}", file=sys.stderr)
    if cfg.draws > 1 and not any(ep.metadata["prediction"].get("draws") for ep in episodes):
        print(f"note: {cfg.draws} noise draws are chosen among by the scene's objects, and none was found in this "
              f"first frame (no segmentation names one, and none stands out by its colour): one draw was sampled",
              file=sys.stderr)
    for k, ep in enumerate(episodes):
        if chosen := ep.metadata["prediction"].get("draws"):
            scores = ", ".join("n/a" if s != s else f"{s:.2f}" for s in chosen["objects_kept"])
            print(f"{'' if len(episodes) == 1 else f'sample {k}: '}kept draw {chosen['kept']} of {chosen['count']} "
                  f"(objects kept per draw: {scores})")
    out = Path(cfg.out)
    resolved = {k: (str(v) if isinstance(v, Path) else v) for k, v in dataclasses.asdict(cfg).items()}
    written = []
    with output as stage:  # the files appear in OUT only when this block ends without an error
        for k, ep in enumerate(episodes):
            sub = Path() if len(episodes) == 1 else Path(f"sample_{k:02d}")
            path = write_prediction(ep, stage / sub)
            written.append(out / sub / path.relative_to(stage / sub))
        (stage / "predict_config.json").write_text(json.dumps({**resolved, "instruction": instruction}, indent=2))
    for path in written:
        print(f"wrote {path}")
    if len(episodes) > 1:
        print(f"each sample is its own prediction folder: reconstruct, evaluate or view {out / 'sample_00'} and the others")
    return 0
