"""The tesseract4d dataset format (version 2): one writer, one reader, documented here.

Layout of a dataset folder::

    DIR/
      info.json                                   DatasetInfo (format version, conventions)
      episodes/<env_id>/seed_<seed:06d>.h5         one HDF5 file per episode (the shard unit)
      episodes/<env_id>/seed_<seed:06d>_k<k>.h5    future k of a counterfactual group (skill datagen)
      previews/<env_id>/seed_<seed:06d>[_k<k>].mp4 RGB | depth | normal side by side (browser-playable)

Counterfactual groups: the K episodes of one (env_id, seed) start from the same initial state
(their first frames are identical bit for bit) and differ only in the instruction and what the
robot does. ``group_id`` = ``<env_id>/seed_<seed:06d>``; splits (train / held-out) keep whole
groups together because they are drawn by seed.

Every episode file is a self-contained shard: parallel workers write different files, so no
locking is needed, and a file appears under its final name only once it is complete (written
to a temporary name in the same folder, flushed, then atomically renamed). Anything named
``*.partial.h5`` is an interrupted write and is ignored (and removed) by writers.

Inside an episode file (all arrays chunked per frame and gzip-compressed)::

    attrs: format_version, episode_id, env_id, seed, instruction, success (-1 unknown / 0 / 1),
           control_mode, env_kwargs (JSON), fps, source ("simulation" | "prediction"),
           metadata (JSON: package versions, instruction attributes, anything extra),
           group_id, variant (-1 = not part of a group), intent (JSON or "null"; version 2):
           the structured intent of a skill episode: skill, variant, target, other, direction,
           distance_m, commanded_displacement_world_m, gripper_goal_world_m, criterion,
           objects_present, achieved_displacement_world_m, others_max_displacement_m,
           gripper_displacement_m, target_grasped_at_end, success (see datagen/skills.py)
    frame_steps              (T,)          int32   simulator step index of each stored frame
    actions                  (S, A)        float32 the action applied at every sim step (S may be 0)
    qpos                     (T, D)        float32 robot joint positions at each frame (D may be 0)
    object_poses/<name>      (T, 7)        float32 world pose, xyz + quaternion wxyz
    cameras/<cam>/rgb          (T, H, W, 3)  uint8
    cameras/<cam>/depth_m      (T, H, W)     float32 metres along the OpenCV +z axis, 0 = no hit
    cameras/<cam>/normal_cam   (T, H, W, 3)  float16 unit normals, OpenCV camera frame, 0 = no hit
    cameras/<cam>/segmentation (T, H, W)     int32   per-pixel id (optional), attr seg_id_to_name (JSON)
    cameras/<cam>/K            (T, 3, 3)     float64 pixel intrinsics
    cameras/<cam>/T_world_cam  (T, 4, 4)     float64 camera→world, OpenCV axes

Re-simulation: ``gym.make(env_id, **env_kwargs, control_mode=control_mode)``, ``reset(seed=seed)``,
then apply ``actions`` in order (the project's own scene ``Tesseract4dTabletop-v1`` is registered
by ``datagen.tabletop.register()``).

Versions: 2 added ``group_id``, ``variant`` and ``intent``. Version-1 files and folders (no
groups) are still read: their episodes have ``variant=None`` and ``intent=None``. Writers only
write version 2 and do not append to a version-1 folder.
"""

from __future__ import annotations

import dataclasses
import json
import os
import re
import uuid
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from tesseract4d.errors import UserError
from tesseract4d.outputs import MARKER, safe_name, signals_held

FORMAT_VERSION = 2
READABLE_VERSIONS = (1, 2)
INFO_FILE = "info.json"
EPISODES_DIR = "episodes"
PREVIEWS_DIR = "previews"
EPISODE_TEMPLATE = "episodes/{env_id}/seed_{seed:06d}[_k{variant}].h5"  # see episode_path
PREVIEW_TEMPLATE = "previews/{env_id}/seed_{seed:06d}[_k{variant}].mp4"  # see preview_path
PARTIAL_SUFFIX = ".partial.h5"
# Scene seeds: training data uses seeds below this; the demo and held-out evaluation use seeds
# from here on (`datagen --seed-start HELDOUT_SEED_START --instruction-split heldout`).
HELDOUT_SEED_START = 100_000
LOCK_FILE = ".datagen.lock"  # the pid of the datagen writing the folder

DEPTH_ENCODING = "float32 metres along the OpenCV camera +z axis; 0 = no measurement"
NORMAL_CONVENTION = "float16 unit vectors in the OpenCV camera frame (x right, y down, z forward); 0 = no measurement"
POSE_CONVENTION = "T_world_cam: 4x4 camera-to-world, OpenCV camera axes"
# Content checks (CameraFrames.check_content): float16 storage and the renderer's interpolated
# normals stay well within these.
NORMAL_LENGTH_TOLERANCE = 0.05
NORMAL_ZERO_TOLERANCE = 1e-3
RIGID_TOLERANCE = 1e-4


class DatasetFormatError(UserError):
    """A dataset folder or episode file that this version of tesseract4d cannot use."""


@dataclass
class DatasetInfo:
    """Dataset-level facts, written to ``DIR/info.json``."""

    format_version: int = FORMAT_VERSION
    fps: float = 20.0
    height: int = 128
    width: int = 128
    cameras: list[str] = field(default_factory=lambda: ["base_camera"])
    depth_encoding: str = DEPTH_ENCODING
    normal_convention: str = NORMAL_CONVENTION
    pose_convention: str = POSE_CONVENTION
    source: str = "simulation"
    extra: dict = field(default_factory=dict)

    def to_json(self) -> str:
        return json.dumps(dataclasses.asdict(self), indent=2, sort_keys=True)

    @classmethod
    def from_dict(cls, d: dict) -> "DatasetInfo":
        known = {f.name for f in dataclasses.fields(cls)}
        return cls(**{k: v for k, v in d.items() if k in known})


@dataclass
class CameraFrames:
    """All frames of one camera. T frames of H x W pixels."""

    rgb: np.ndarray  # (T, H, W, 3) uint8
    depth_m: np.ndarray  # (T, H, W) float32, 0 = no hit
    normal_cam: np.ndarray  # (T, H, W, 3) float32 unit, OpenCV camera frame, 0 = no hit
    K: np.ndarray  # (T, 3, 3) float64
    T_world_cam: np.ndarray  # (T, 4, 4) float64
    segmentation: np.ndarray | None = None  # (T, H, W) int32
    seg_id_to_name: dict[int, str] = field(default_factory=dict)

    @property
    def num_frames(self) -> int:
        return int(self.rgb.shape[0])

    def validate(self, name: str = "camera") -> None:
        """Raise DatasetFormatError if shapes/dtypes break the contract (content: ``check_content``)."""
        images = {"rgb": (self.rgb, 4), "depth_m": (self.depth_m, 3), "normal_cam": (self.normal_cam, 4)}
        # Frames x height x width, taken from whichever two image arrays agree, so the odd one is named.
        sizes = [tuple(a.shape[:3]) for a, ndim in images.values() if a is not None and a.ndim == ndim]
        T, H, W = max(sizes, key=sizes.count) if sizes else (0, 0, 0)
        expect = {
            "rgb": (T, H, W, 3),
            "depth_m": (T, H, W),
            "normal_cam": (T, H, W, 3),
            "K": (T, 3, 3),
            "T_world_cam": (T, 4, 4),
        }
        for key, shape in expect.items():
            arr = getattr(self, key)
            if arr is None or tuple(arr.shape) != shape:
                got = None if arr is None else tuple(arr.shape)
                raise DatasetFormatError(f"{name}: {key} must have shape {shape}, got {got}")
        if self.rgb.dtype != np.uint8:
            raise DatasetFormatError(f"{name}: rgb must be uint8, got {self.rgb.dtype}")
        if self.segmentation is not None and tuple(self.segmentation.shape) != (T, H, W):
            raise DatasetFormatError(f"{name}: segmentation must have shape {(T, H, W)}, got {self.segmentation.shape}")
        if not np.all(np.isfinite(self.depth_m)):
            raise DatasetFormatError(f"{name}: depth_m contains NaN/inf; use 0 for 'no measurement'")

    def check_content(self, name: str = "camera", zero_normals_anywhere: bool = False) -> None:
        """Raise DatasetFormatError naming the first value that breaks the conventions: depth finite
        and >= 0 (0 = no measurement); normals finite and of unit length (within
        ``NORMAL_LENGTH_TOLERANCE``), or zero where depth is 0 (anywhere with
        ``zero_normals_anywhere``: a prediction's "no normal" where its length collapsed); K finite
        with positive focal lengths and last row (0, 0, 1); ``T_world_cam`` rigid (rotation
        orthonormal with determinant +1, last row (0, 0, 0, 1)); every segmentation id named in
        ``seg_id_to_name``. Call ``validate`` first."""

        def where(mask: np.ndarray) -> str:
            idx = tuple(int(i) for i in np.argwhere(mask)[0])
            return f"{int(mask.sum())} value(s), the first at frame {idx[0]}" + (
                f" pixel (row {idx[1]}, column {idx[2]})" if len(idx) >= 3 else "")

        depth = np.asarray(self.depth_m, np.float32)
        bad = ~np.isfinite(depth) | (depth < 0)
        if bad.any():
            raise DatasetFormatError(f"{name}: depth_m must be finite and >= 0 metres (0 = no measurement); "
                                     f"{where(bad)} is {float(depth[tuple(np.argwhere(bad)[0])])}")
        normal = np.asarray(self.normal_cam, np.float32)
        finite = np.isfinite(normal).all(axis=-1)
        length = np.linalg.norm(np.where(finite[..., None], normal, 0.0), axis=-1)
        unit = np.abs(length - 1.0) <= NORMAL_LENGTH_TOLERANCE
        zero_ok = (length <= NORMAL_ZERO_TOLERANCE) & ((depth == 0) | zero_normals_anywhere)
        bad = ~finite | ~(unit | zero_ok)
        if bad.any():
            first = tuple(np.argwhere(bad)[0])
            got = "NaN/inf" if not finite[first] else f"of length {float(length[first]):.3f}"
            raise DatasetFormatError(f"{name}: normal_cam must hold unit vectors (length 1 +- {NORMAL_LENGTH_TOLERANCE}), "
                                     f"or zero where depth_m is 0; {where(bad)} is {got}")
        K = np.asarray(self.K, np.float64)
        bad = ~np.isfinite(K).all(axis=(1, 2)) | ~(K[:, 0, 0] > 0) | ~(K[:, 1, 1] > 0)
        bad |= np.abs(K[:, 2] - [0.0, 0.0, 1.0]).max(axis=1) > 1e-9
        if bad.any():
            t = int(np.argwhere(bad)[0][0])
            raise DatasetFormatError(f"{name}: K must be finite pixel intrinsics with positive focal lengths and last row "
                                     f"(0, 0, 1); frame {t} has {K[t].tolist()}")
        T = np.asarray(self.T_world_cam, np.float64)
        R = T[:, :3, :3]
        with np.errstate(invalid="ignore"):
            bad = ~np.isfinite(T).all(axis=(1, 2))
            bad |= np.abs(T[:, 3] - [0.0, 0.0, 0.0, 1.0]).max(axis=1) > 1e-6
            bad |= np.abs(np.einsum("tji,tjk->tik", R, R) - np.eye(3)).max(axis=(1, 2)) > RIGID_TOLERANCE
            bad |= np.abs(np.linalg.det(np.where(np.isfinite(R), R, 0.0)) - 1.0) > RIGID_TOLERANCE
        if bad.any():
            t = int(np.argwhere(bad)[0][0])
            raise DatasetFormatError(f"{name}: T_world_cam must be a rigid camera-to-world pose (orthonormal rotation "
                                     f"with determinant +1, last row 0 0 0 1); frame {t} has {T[t].tolist()}")
        if self.segmentation is not None:
            ids = np.unique(self.segmentation)
            unknown = sorted(set(ids.tolist()) - set(self.seg_id_to_name))
            if unknown:
                raise DatasetFormatError(f"{name}: segmentation ids {unknown[:5]} have no name in seg_id_to_name "
                                         f"(it names {sorted(self.seg_id_to_name)[:10]})")


@dataclass
class Episode:
    """One episode: frames of every camera plus what is needed to re-simulate it."""

    env_id: str
    seed: int
    instruction: str
    cameras: dict[str, CameraFrames]
    frame_steps: np.ndarray  # (T,) int32
    actions: np.ndarray = field(default_factory=lambda: np.zeros((0, 0), np.float32))  # (S, A)
    qpos: np.ndarray = field(default_factory=lambda: np.zeros((0, 0), np.float32))  # (T, D)
    object_poses: dict[str, np.ndarray] = field(default_factory=dict)  # name -> (T, 7)
    success: bool | None = None
    control_mode: str = ""
    env_kwargs: dict = field(default_factory=dict)
    fps: float = 20.0
    source: str = "simulation"
    metadata: dict = field(default_factory=dict)
    variant: int | None = None  # index k within a counterfactual group; None = no group
    intent: dict | None = None  # structured intent of a skill episode (see the module docstring)

    @property
    def episode_id(self) -> str:
        return f"{self.env_id}/{episode_stem(self.seed, self.variant)}"

    @property
    def group_id(self) -> str:
        """Episodes sharing it start from the same initial state (same env_id and seed)."""
        return f"{self.env_id}/seed_{self.seed:06d}"

    @property
    def num_frames(self) -> int:
        return int(len(self.frame_steps))

    def validate(self) -> None:
        if not self.cameras:
            raise DatasetFormatError(f"{self.episode_id}: an episode needs at least one camera")
        for name, cam in self.cameras.items():
            cam.validate(f"{self.episode_id}/{name}")
            if cam.num_frames != self.num_frames:
                raise DatasetFormatError(
                    f"{self.episode_id}/{name}: {cam.num_frames} frames but frame_steps has {self.num_frames}"
                )

    def check_content(self) -> None:
        """``validate`` and every camera's ``check_content``: what `dataset check` and the commands that
        read episodes to learn from or predict from (train, predict --episode, reconstruct) apply."""
        self.validate()
        for name, cam in self.cameras.items():
            cam.check_content(f"{self.episode_id}/{name}", zero_normals_anywhere=self.source == "prediction")
        if self.qpos.size and self.qpos.shape[0] != self.num_frames:
            raise DatasetFormatError(f"{self.episode_id}: qpos has {self.qpos.shape[0]} rows, expected {self.num_frames}")
        for name, pose in self.object_poses.items():
            if pose.shape != (self.num_frames, 7):
                raise DatasetFormatError(f"{self.episode_id}: object_poses/{name} must be ({self.num_frames}, 7)")


# --------------------------------------------------------------------------- paths


def episode_stem(seed: int, variant: int | None = None) -> str:
    """File stem of an episode: ``seed_000003`` or, for future k of a group, ``seed_000003_k2``."""
    return f"seed_{int(seed):06d}" if variant is None else f"seed_{int(seed):06d}_k{int(variant)}"


_GROUP_MEMBER_RE = re.compile(r"^(.+/seed_\d{6,})_k\d+$")


def group_of_episode_id(episode_id: str) -> str | None:
    """The counterfactual group (``<env_id>/seed_<seed>``) of an episode id ``<env_id>/seed_<seed>_k<k>``;
    None for an episode that is not part of a group (``<env_id>/seed_<seed>``)."""
    m = _GROUP_MEMBER_RE.match(episode_id)
    return m.group(1) if m else None


def episode_path(root: str | os.PathLike, env_id: str, seed: int, variant: int | None = None) -> Path:
    return Path(root) / EPISODES_DIR / safe_name(env_id, "env_id") / f"{episode_stem(seed, variant)}.h5"


def preview_path(root: str | os.PathLike, env_id: str, seed: int, variant: int | None = None) -> Path:
    return Path(root) / PREVIEWS_DIR / safe_name(env_id, "env_id") / f"{episode_stem(seed, variant)}.mp4"


_EPISODE_RE = re.compile(r"^seed_(\d{6,})(_k\d+)?\.h5$")


def list_episode_files(root: str | os.PathLike) -> list[Path]:
    """Complete episode files of a dataset, sorted (partial writes are excluded)."""
    base = Path(root) / EPISODES_DIR
    if not base.is_dir():
        return []
    return sorted(p for p in base.glob("*/seed_*.h5") if _EPISODE_RE.match(p.name))


# --------------------------------------------------------------------------- dataset info


def read_info(root: str | os.PathLike) -> DatasetInfo:
    """Read ``DIR/info.json``; fail with a fix if it is missing, corrupt or another version."""
    root = Path(root)
    path = root / INFO_FILE
    if not root.exists():
        raise DatasetFormatError(f"{root} does not exist. Pass a dataset folder written by `tesseract4d datagen`.")
    if not path.is_file():
        raise DatasetFormatError(f"{root} has no {INFO_FILE}; it is not a tesseract4d dataset (write one with `tesseract4d datagen`).")
    try:
        d = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise DatasetFormatError(f"{path} is corrupt ({e}). Restore it or regenerate the dataset.") from e
    version = d.get("format_version")
    if version not in READABLE_VERSIONS:
        raise DatasetFormatError(
            f"{root} holds dataset format version {version}, but this tesseract4d reads versions "
            f"{', '.join(map(str, READABLE_VERSIONS))}. Write to a new folder, or regenerate the dataset with this version."
        )
    return DatasetInfo.from_dict(d)


def init_dataset(root: str | os.PathLike, info: DatasetInfo) -> DatasetInfo:
    """Create a dataset folder, or reopen an existing one of the same version.

    Existing data is never touched; returns the info that is on disk (the existing one when
    reopening, so resolution/cameras stay those of the data already written).
    """
    root = Path(root)
    if (root / INFO_FILE).exists():
        existing = read_info(root)
        if existing.format_version != info.format_version:
            raise DatasetFormatError(
                f"{root} holds format version {existing.format_version} episodes; this tesseract4d writes version "
                f"{info.format_version} and does not mix them in one folder. Write to a new --out folder "
                f"(version-1 data stays readable as it is)."
            )
        if (existing.height, existing.width) != (info.height, info.width):
            raise DatasetFormatError(
                f"{root} already holds {existing.height}x{existing.width} episodes; requested "
                f"{info.height}x{info.width}. Use another --out folder or the same resolution."
            )
        return existing
    if root.exists() and any(p.name not in (MARKER, LOCK_FILE) for p in root.iterdir()):
        raise DatasetFormatError(f"{root} exists, is not empty and is not a tesseract4d dataset; choose an empty or new folder.")
    root.mkdir(parents=True, exist_ok=True)
    atomic_write_text(root / INFO_FILE, info.to_json())
    return info


def atomic_write_text(path: str | os.PathLike, text: str) -> None:
    """Write a text file so that readers see the old or the new content, never a partial one."""
    path = Path(path)
    tmp = path.with_name(f".{path.name}.{uuid.uuid4().hex}.tmp")
    tmp.write_text(text)
    os.replace(tmp, path)


# --------------------------------------------------------------------------- writer


def write_episode(root: str | os.PathLike, episode: Episode, compression_level: int = 4) -> Path:
    """Write one episode atomically to its shard file; returns the final path."""
    import h5py

    episode.validate()
    final = episode_path(root, episode.env_id, episode.seed, episode.variant)
    final.parent.mkdir(parents=True, exist_ok=True)
    tmp = final.with_name(f".{final.stem}.{uuid.uuid4().hex}{PARTIAL_SUFFIX}")
    # Fletcher-32 checksums on every non-empty array: a flipped byte fails the read (naming the file)
    # instead of becoming a wrong pixel or camera pose.
    gz = dict(compression="gzip", compression_opts=compression_level, shuffle=True, fletcher32=True)

    def frames(group, name, data):
        data = np.ascontiguousarray(data)
        chunks = (1,) + data.shape[1:] if data.ndim >= 3 and data.shape[0] > 0 else None
        group.create_dataset(name, data=data, chunks=chunks, **(gz if chunks else {"fletcher32": data.size > 0}))

    def small(group, name, data):
        data = np.ascontiguousarray(data)
        group.create_dataset(name, data=data, fletcher32=data.size > 0)

    try:
        # An interrupt waits for the shard to be written and renamed (h5py's closing would swallow it).
        with signals_held(), h5py.File(tmp, "w") as f:
            f.attrs["format_version"] = FORMAT_VERSION
            f.attrs["episode_id"] = episode.episode_id
            f.attrs["env_id"] = episode.env_id
            f.attrs["seed"] = int(episode.seed)
            f.attrs["instruction"] = episode.instruction
            f.attrs["success"] = -1 if episode.success is None else int(bool(episode.success))
            f.attrs["control_mode"] = episode.control_mode
            f.attrs["env_kwargs"] = json.dumps(episode.env_kwargs, sort_keys=True)
            f.attrs["fps"] = float(episode.fps)
            f.attrs["source"] = episode.source
            f.attrs["metadata"] = json.dumps(episode.metadata, sort_keys=True, default=str)
            f.attrs["group_id"] = episode.group_id
            f.attrs["variant"] = -1 if episode.variant is None else int(episode.variant)
            f.attrs["intent"] = json.dumps(episode.intent, sort_keys=True)
            small(f, "frame_steps", np.asarray(episode.frame_steps, np.int32))
            small(f, "actions", np.asarray(episode.actions, np.float32))
            small(f, "qpos", np.asarray(episode.qpos, np.float32))
            og = f.create_group("object_poses")
            for name, pose in episode.object_poses.items():
                small(og, name, np.asarray(pose, np.float32))
            cg = f.create_group("cameras")
            for cam_name, cam in episode.cameras.items():
                g = cg.create_group(cam_name)
                frames(g, "rgb", cam.rgb.astype(np.uint8))
                frames(g, "depth_m", cam.depth_m.astype(np.float32))
                frames(g, "normal_cam", cam.normal_cam.astype(np.float16))
                if cam.segmentation is not None:
                    frames(g, "segmentation", cam.segmentation.astype(np.int32))
                g.attrs["seg_id_to_name"] = json.dumps({str(k): v for k, v in cam.seg_id_to_name.items()})
                small(g, "K", np.asarray(cam.K, np.float64))
                small(g, "T_world_cam", np.asarray(cam.T_world_cam, np.float64))
            f.flush()
            os.replace(tmp, final)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return final


def write_episode_dataset(root: str | os.PathLike, episode: Episode) -> Path:
    """Write one episode as a dataset of its own (created if needed, info taken from the episode).

    For single-episode outputs: a rendered first frame, a prediction. Returns the episode file.
    """
    first = next(iter(episode.cameras.values()))
    height, width = first.rgb.shape[1:3]
    init_dataset(root, DatasetInfo(fps=float(episode.fps), height=int(height), width=int(width),
                                   cameras=list(episode.cameras), source=episode.source))
    return write_episode(root, episode)


def remove_partial_files(root: str | os.PathLike) -> list[Path]:
    """Delete leftovers of interrupted writes; returns what was removed."""
    base = Path(root) / EPISODES_DIR
    removed = sorted(base.glob(f"*/.*{PARTIAL_SUFFIX}")) if base.is_dir() else []
    for p in removed:
        p.unlink(missing_ok=True)
    return removed


# --------------------------------------------------------------------------- reader


def _data_name(value: str, field: str) -> str:
    """A name read from a file, checked before it can become a path component."""
    try:
        return safe_name(value, field)
    except UserError as e:
        raise DatasetFormatError(str(e)) from None


def read_episode(
    path: str | os.PathLike,
    cameras: list[str] | None = None,
    frames: slice | np.ndarray | None = None,
    check: bool = False,
) -> Episode:
    """Read an episode file (optionally only some cameras and a frame slice/index array). With
    ``check``, its shapes and content are validated too (``Episode.check_content``), and a failure
    names the file and `tesseract4d dataset check`."""
    episode = _read_episode(path, cameras, frames)
    if check:
        try:
            episode.check_content()
        except DatasetFormatError as e:
            raise DatasetFormatError(f"{path} is not a valid episode ({e}); regenerate it, or list every such file of "
                                     f"its dataset with `tesseract4d dataset check`") from None
    return episode


def _read_episode(path, cameras, frames) -> Episode:
    import h5py

    path = Path(path)
    if not path.is_file():
        raise DatasetFormatError(f"episode file {path} does not exist")
    sel = slice(None) if frames is None else frames
    try:
        with h5py.File(path, "r") as f:
            version = int(f.attrs.get("format_version", -1))
            if version not in READABLE_VERSIONS:
                raise DatasetFormatError(
                    f"{path} is format version {version}; this tesseract4d reads versions "
                    f"{', '.join(map(str, READABLE_VERSIONS))}. Regenerate it."
                )
            cams = {}
            names = list(f["cameras"].keys()) if cameras is None else cameras
            for name in names:
                _data_name(name, f"{path}: camera name")
                if name not in f["cameras"]:
                    raise DatasetFormatError(f"{path} has no camera {name!r}; it has {sorted(f['cameras'].keys())}")
                g = f["cameras"][name]
                cams[name] = CameraFrames(
                    rgb=g["rgb"][sel],
                    depth_m=g["depth_m"][sel],
                    normal_cam=g["normal_cam"][sel].astype(np.float32),
                    K=g["K"][sel],
                    T_world_cam=g["T_world_cam"][sel],
                    segmentation=g["segmentation"][sel] if "segmentation" in g else None,
                    seg_id_to_name={int(k): v for k, v in json.loads(g.attrs.get("seg_id_to_name", "{}")).items()},
                )
            qpos = f["qpos"][()]
            success = int(f.attrs["success"])
            return Episode(
                env_id=_data_name(str(f.attrs["env_id"]), f"{path}: env_id"),
                seed=int(f.attrs["seed"]),
                instruction=str(f.attrs["instruction"]),
                cameras=cams,
                frame_steps=f["frame_steps"][sel],
                actions=f["actions"][()],
                qpos=qpos[sel] if qpos.size else qpos,
                object_poses={k: v[sel] for k, v in f["object_poses"].items()},
                success=None if success < 0 else bool(success),
                control_mode=str(f.attrs["control_mode"]),
                env_kwargs=json.loads(f.attrs["env_kwargs"]),
                fps=float(f.attrs["fps"]),
                source=str(f.attrs["source"]),
                metadata=json.loads(f.attrs["metadata"]),
                **_group_fields(f.attrs, version),
            )
    except DatasetFormatError:
        raise
    except (OSError, KeyError, ValueError) as e:
        raise DatasetFormatError(_unreadable(path, e)) from e


_HDF5_SIGNATURE = b"\x89HDF\r\n\x1a\n"


def _unreadable(path: Path, e: Exception) -> str:
    """Why an episode file could not be read: not an HDF5 file at all (a user's other file), an HDF5
    file of something else, or one of ours that is damaged."""
    try:
        with open(path, "rb") as f:
            head = f.read(len(_HDF5_SIGNATURE))
    except OSError:
        head = b""
    if head != _HDF5_SIGNATURE:
        return (f"{path} is not an episode file (not HDF5); pass an episode .h5 written by `tesseract4d datagen` "
                f"or `predict`, or the folder holding one")
    if isinstance(e, KeyError):
        return f"{path} is an HDF5 file but not a tesseract4d episode ({e}); pass an episode written by datagen or predict"
    return (f"{path} is corrupt or truncated ({type(e).__name__}: {e}); regenerate it with the command that wrote it "
            f"(`tesseract4d dataset check` lists every such file of a dataset)")


def _group_fields(attrs, version: int) -> dict:
    """variant and intent of an episode file (version 1 files have neither)."""
    if version < 2:
        return {"variant": None, "intent": None}
    variant = int(attrs["variant"])
    return {"variant": None if variant < 0 else variant, "intent": json.loads(attrs["intent"])}


def read_episode_attrs(path: str | os.PathLike) -> dict:
    """Cheap metadata read (no frames): env_id, seed, instruction, success, num_frames, cameras, shape."""
    import h5py

    try:
        with h5py.File(path, "r") as f:
            cams = [_data_name(c, f"{path}: camera name") for c in f["cameras"].keys()]
            _data_name(str(f.attrs["env_id"]), f"{path}: env_id")
            shape = f["cameras"][cams[0]]["rgb"].shape if cams else (0, 0, 0, 3)
            version = int(f.attrs.get("format_version", -1))
            group = _group_fields(f.attrs, version)
            return {
                "format_version": version,
                "group_id": f"{f.attrs['env_id']}/seed_{int(f.attrs['seed']):06d}",
                "variant": group["variant"],
                "intent": group["intent"],
                "env_id": str(f.attrs["env_id"]),
                "seed": int(f.attrs["seed"]),
                "instruction": str(f.attrs["instruction"]),
                "success": int(f.attrs["success"]),
                "num_frames": int(shape[0]),
                "height": int(shape[1]),
                "width": int(shape[2]),
                "cameras": cams,
            }
    except (OSError, KeyError, ValueError, IndexError) as e:
        raise DatasetFormatError(_unreadable(Path(path), e)) from e


def samples_hint(folder: Path) -> str | None:
    """For a folder of `predict --num-samples` (``sample_XX`` prediction folders, no episode of its
    own): the sentence that names them; None for any other folder."""
    samples = sorted(q for q in Path(folder).glob("sample_[0-9]*") if q.is_dir() and list_episode_files(q))
    if not samples:
        return None
    return (f"{folder} holds {len(samples)} samples of `tesseract4d predict --num-samples`, one prediction folder "
            f"each; pass one of them, e.g. {samples[0]}")


def resolve_episode(spec: str | os.PathLike) -> Path:
    """Turn a user's episode reference into a file: a ``.h5`` path, ``DIR/ENV_ID/SEED`` or a
    dataset folder holding exactly one episode (e.g. a prediction output)."""
    p = Path(spec)
    if p.is_file():
        return p
    if p.is_dir():
        files = list_episode_files(p)
        if len(files) == 1:
            return files[0]
        if not files:
            if hint := samples_hint(p):
                raise DatasetFormatError(hint)
            raise DatasetFormatError(f"{p} holds no episodes (expected {EPISODE_TEMPLATE} inside)")
        seed, _, variant = files[0].stem.removeprefix("seed_").partition("_k")
        example = p / files[0].parent.name / (f"{int(seed)}_k{variant}" if variant else str(int(seed)))
        raise DatasetFormatError(f"{p} holds {len(files)} episodes; name one as {p}/<env_id>/<seed> or, for "
                                 f"future K of a counterfactual group, <seed>_k<K> (e.g. {example}), or pass its .h5 file")
    # DIR/ENV_ID/SEED or DIR/ENV_ID/SEED_kK (future k of a group)
    root, env_id = p.parent.parent, p.parent.name
    seed, _, variant = p.name.partition("_k")
    if seed.isdigit() and (variant == "" or variant.isdigit()):
        f = episode_path(root, env_id, int(seed), int(variant) if variant else None)
        if f.is_file():
            return f
    raise DatasetFormatError(f"no episode at {spec}: give an episode .h5 file, a dataset folder with one episode, "
                             f"DIR/ENV_ID/SEED or DIR/ENV_ID/SEED_kK")
