"""Latent cache: a dataset encoded once per autoencoder, so a diffusion training step never runs
the encoder.

A cache folder (default ``DATASET/latent_cache/<camera>/``) holds::

    cache.json            autoencoder hash, dataset fingerprint (episode files, sizes, mtimes), shapes
    latents.safetensors   per episode: "<i>.latents" (T, C, h, w) float16 normalised latents,
                          "<i>.objects" (T, h, w) float16 share of robot/object pixels per latent cell
                          and "<i>.scene_objects" (T, h, w) float16 share of the scene's objects'
                          pixels (cubes, cylinders; not the robot: ``segments.scene_object_mask``)

The cache is valid only for the autoencoder whose ``autoencoder_hash`` it records (or a decoder-only
fine-tune of it: the same ``latents_hash``, so `swap-decoder` keeps the caches) and the dataset
files it was built from; ``ensure_latent_cache`` rebuilds it when either changed (or when it
predates the scene objects' shares), writing into a
temporary sibling that is renamed into place (never half-written). A dataset folder copied with
only its ``info.json`` and its cache (no episodes: training on another machine) uses the cache as it
is, for its own autoencoder only. ``open_latent_cache`` only
reads and refuses a cache of another autoencoder with a message saying what to run.
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import tempfile
from dataclasses import dataclass
from pathlib import Path

import torch
import torch.nn.functional as F

from tesseract4d import dataset_format as df
from tesseract4d.errors import UserError
from tesseract4d.outputs import files_as_created, note_leftovers
from tesseract4d.model.autoencoder import autoencoder_hash, latents_hash
from tesseract4d.model.autoencoder_loading import load_autoencoder
from tesseract4d.segments import robot_object_mask, scene_object_mask
from tesseract4d.model.clips import grouped_batch_plan, spread_over_tasks

CACHE_FILE = "cache.json"
LATENTS_FILE = "latents.safetensors"
CACHE_DIR = "latent_cache"
FORMAT = "tesseract4d-latent-cache"


def default_cache_dir(dataset: str | os.PathLike, camera: str) -> Path:
    return Path(dataset) / CACHE_DIR / camera


def dataset_fingerprint(dataset: str | os.PathLike) -> list[list]:
    """[relative path, size, mtime_ns] of every episode file: changes when episodes are added or rewritten."""
    root = Path(dataset)
    return [[str(p.relative_to(root)), p.stat().st_size, p.stat().st_mtime_ns] for p in df.list_episode_files(root)]


@dataclass
class LatentEpisode:
    episode_id: str
    instruction: str
    latents: torch.Tensor  # (T, C, h, w) float16, normalised latents
    objects: torch.Tensor  # (T, h, w) float16, share of robot/object pixels per latent cell
    scene_objects: torch.Tensor | None = None  # (T, h, w) float16, share of the scene's objects' pixels (None: an older cache)


@dataclass
class LatentCache:
    folder: Path
    meta: dict
    episodes: list[LatentEpisode]

    @property
    def autoencoder_hash(self) -> str:
        return self.meta["autoencoder_hash"]


def _build(dataset: Path, autoencoder_dir: Path, camera: str, folder: Path, progress: bool) -> None:
    from safetensors.torch import save_file

    model = load_autoencoder(autoencoder_dir)
    info = df.read_info(dataset)
    if (info.height, info.width) != (model.config.height, model.config.width):
        raise UserError(f"{dataset} holds {info.height}x{info.width} episodes but the autoencoder {autoencoder_dir} "
                        f"works at {model.config.height}x{model.config.width}; generate data with "
                        f"`tesseract4d datagen --resolution {model.config.height} --out DIR`")
    files = df.list_episode_files(dataset)
    if not files:
        raise UserError(f"{dataset} holds no episodes; write some with `tesseract4d datagen --out {dataset}`")
    f = model.config.spatial_compression
    tensors, episodes = {}, []
    iterator = files
    if progress:
        from tqdm import tqdm

        iterator = tqdm(files, desc="encoding latents", unit="ep")
    for i, path in enumerate(iterator):
        ep = df.read_episode(path, cameras=[camera], check=True)
        cam = ep.cameras[camera]
        x = model.model_space.encode(cam.rgb, cam.depth_m, cam.normal_cam)  # (T, 7, H, W)
        z = torch.cat([model.encode(x[k:k + 16]) for k in range(0, len(x), 16)])  # (T, C, h, w)
        masks = torch.zeros(x.shape[0], 2, x.shape[2], x.shape[3])  # (T, 2, H, W): robot/objects, scene objects
        if cam.segmentation is not None:
            masks[:, 0] = torch.from_numpy(robot_object_mask(cam.segmentation, cam.seg_id_to_name))
            masks[:, 1] = torch.from_numpy(scene_object_mask(cam.segmentation, cam.seg_id_to_name))
        shares = F.avg_pool2d(masks, f)  # (T, 2, h, w)
        tensors[f"{i}.latents"] = z.half().contiguous()
        tensors[f"{i}.objects"] = shares[:, 0].half().contiguous()
        tensors[f"{i}.scene_objects"] = shares[:, 1].half().contiguous()
        episodes.append({"episode_id": ep.episode_id, "instruction": ep.instruction, "file": str(path.relative_to(dataset))})
    folder.mkdir(parents=True)
    save_file(tensors, str(folder / LATENTS_FILE))
    files_as_created(folder / LATENTS_FILE)  # safetensors writes 0600
    meta = {
        "format": FORMAT, "autoencoder_hash": autoencoder_hash(autoencoder_dir), "autoencoder_dir": str(autoencoder_dir),
        "latents_hash": latents_hash(autoencoder_dir),
        "camera": camera, "latent_shape": list(model.config.latent_shape), "resolution": [info.height, info.width],
        "dataset_fingerprint": dataset_fingerprint(dataset), "episodes": episodes, "scene_objects": True,
    }
    (folder / CACHE_FILE).write_text(json.dumps(meta, indent=1))


def _read_meta(folder: Path) -> dict | None:
    path = folder / CACHE_FILE
    if not path.is_file() or not (folder / LATENTS_FILE).is_file():
        return None
    meta = json.loads(path.read_text())
    return meta if meta.get("format") == FORMAT else None


def _made_by(meta: dict, autoencoder_dir: str | os.PathLike, ae_hash: str) -> bool:
    """Whether a cache's latents are those ``autoencoder_dir`` (hash ``ae_hash``) makes: it built the
    cache, or it is a decoder-only fine-tune of the one that did (``latents_hash``: same encoder,
    statistics and config; read only when the hashes differ)."""
    if meta["autoencoder_hash"] == ae_hash:
        return True
    return meta.get("latents_hash") is not None and meta["latents_hash"] == latents_hash(autoencoder_dir)


def open_latent_cache(folder: str | os.PathLike, autoencoder_dir: str | os.PathLike | None = None) -> LatentCache:
    """Read a cache; with ``autoencoder_dir``, refuse one built by another autoencoder."""
    from safetensors.torch import load_file

    folder = Path(folder)
    meta = _read_meta(folder)
    if meta is None:
        raise UserError(f"{folder} is not a latent cache; build one with "
                        f"`tesseract4d encode-latents --data DATASET --autoencoder AE_DIR`")
    if autoencoder_dir is not None:
        want = autoencoder_hash(autoencoder_dir)
        if not _made_by(meta, autoencoder_dir, want):
            raise UserError(f"the latent cache {folder} was built by autoencoder {meta['autoencoder_hash']} "
                            f"({meta.get('autoencoder_dir')}), not {want} ({autoencoder_dir}); rebuild it with "
                            f"`tesseract4d encode-latents --data DATASET --autoencoder {autoencoder_dir} --rebuild`")
    tensors = load_file(str(folder / LATENTS_FILE))
    episodes = [LatentEpisode(e["episode_id"], e["instruction"], tensors[f"{i}.latents"], tensors[f"{i}.objects"],
                              tensors.get(f"{i}.scene_objects")) for i, e in enumerate(meta["episodes"])]
    return LatentCache(folder, meta, episodes)


def ensure_latent_cache(dataset: str | os.PathLike, autoencoder_dir: str | os.PathLike, *, camera: str | None = None,
                        folder: str | os.PathLike | None = None, rebuild: bool = False,
                        progress: bool = False) -> tuple[LatentCache, bool]:
    """The valid cache of ``dataset`` for ``autoencoder_dir``, built (or rebuilt) when needed.

    Returns (cache, built): ``built`` is False when an existing valid cache was reused.
    """
    dataset, autoencoder_dir = Path(dataset), Path(autoencoder_dir)
    info = df.read_info(dataset)
    camera = camera or info.cameras[0]
    if camera not in info.cameras:
        raise UserError(f"{dataset} has no camera {camera!r}; it has {', '.join(info.cameras)}")
    folder = Path(folder) if folder is not None else default_cache_dir(dataset, camera)
    meta = _read_meta(folder)
    if folder.exists() and meta is None and any(folder.iterdir()):
        raise UserError(f"{folder} exists and is not a latent cache; choose another cache folder")
    want = autoencoder_hash(autoencoder_dir)
    if meta is not None and not rebuild and not df.list_episode_files(dataset):
        # A cache that travelled without its episodes (e.g. to a GPU machine): nothing to check it
        # against or rebuild it from, so it is used as it is, if the autoencoder is its own.
        if not _made_by(meta, autoencoder_dir, want) or meta["camera"] != camera:
            raise UserError(f"{dataset} holds no episodes, only a latent cache of autoencoder "
                            f"{meta['autoencoder_hash']} (camera {meta['camera']}), not of {autoencoder_dir} ({want}, "
                            f"camera {camera}); copy the episodes there too, or pass the autoencoder it was built with")
        return open_latent_cache(folder), False
    valid = (meta is not None and not rebuild and meta["camera"] == camera and _made_by(meta, autoencoder_dir, want)
             and meta["dataset_fingerprint"] == dataset_fingerprint(dataset) and meta.get("scene_objects", False))
    if valid:
        return open_latent_cache(folder), False
    # Build in a fresh temporary sibling of our own, then move its two files into place: the cache
    # file last, so an interruption leaves an invalid (rebuilt next time) cache, never a mixed one;
    # anything else in the folder is left alone.

    made_parent = not folder.parent.exists()
    folder.parent.mkdir(parents=True, exist_ok=True)
    note_leftovers(folder)
    tmp = Path(tempfile.mkdtemp(dir=folder.parent, prefix=f".{folder.name}.tmp-"))
    try:
        _build(dataset, autoencoder_dir, camera, tmp / "cache", progress)
        folder.mkdir(exist_ok=True)
        (folder / CACHE_FILE).unlink(missing_ok=True)
        os.replace(tmp / "cache" / LATENTS_FILE, folder / LATENTS_FILE)
        os.replace(tmp / "cache" / CACHE_FILE, folder / CACHE_FILE)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)  # the temporary folder made above, nothing else
        if made_parent and not folder.exists():
            with contextlib.suppress(OSError):
                folder.parent.rmdir()  # the empty folder made above for it: a refused build leaves nothing
        raise
    shutil.rmtree(tmp, ignore_errors=True)
    return open_latent_cache(folder), True


class LatentClipDataset:
    """Clips of ``num_frames`` latent frames from a latent cache; the same interface as
    ``clips.ClipDataset`` (``encoded = True``: batches are latents, not model-space pixels)."""

    encoded = True

    def __init__(self, cache: LatentCache, *, num_frames: int):
        self.cache = cache
        self.camera = cache.meta["camera"]
        self.num_frames = num_frames
        self.sources = [e for e in cache.episodes if e.latents.shape[0] >= num_frames]
        if not self.sources:
            raise UserError(f"no episode in the latent cache {cache.folder} has {num_frames} frames (the preset's clip "
                            f"length); regenerate the dataset with `tesseract4d datagen --frames {num_frames}`")
        self.skipped = len(cache.episodes) - len(self.sources)

    def __len__(self) -> int:
        return len(self.sources)

    def clip(self, index: int, start: int = 0) -> tuple[torch.Tensor, str]:
        """One clip of latents (T, C, h, w) float32 and its instruction."""
        src = self.sources[index]
        return src.latents[start:start + self.num_frames].float(), src.instruction

    @property
    def has_scene_objects(self) -> bool:
        """Whether every episode carries the scene objects' shares (caches built before them do not)."""
        return all(s.scene_objects is not None for s in self.sources)

    def objects(self, index: int, start: int = 0) -> torch.Tensor:
        """(T, 2, h, w) float32 shares per latent cell of one clip: the robot and objects (channel 0)
        and the scene's objects alone (channel 1; zeros where the cache predates them)."""
        src, end = self.sources[index], start + self.num_frames
        scene = src.scene_objects[start:end] if src.scene_objects is not None else torch.zeros_like(src.objects[start:end])
        return torch.stack([src.objects[start:end], scene], dim=1).float()

    def frame_count(self, index: int) -> int:
        return int(self.sources[index].latents.shape[0])

    def sample_group_batch(self, batch_size: int, generator: torch.Generator):
        """(b, T, C, h, w) latent clips of whole counterfactual groups, their instructions, the
        (b, T, 2, h, w) shares of :meth:`objects` and each clip's group leader (``clips.draw_group_batch``)."""
        indices, starts, leaders = grouped_batch_plan(self, batch_size, generator)
        clips = torch.stack([self.clip(i, s)[0] for i, s in zip(indices, starts)])
        objects = torch.stack([self.objects(i, s) for i, s in zip(indices, starts)])
        return clips, [self.sources[i].instruction for i in indices], objects, leaders

    def sample_batch(self, batch_size: int, generator: torch.Generator,
                     with_objects: bool = False):
        """(b, T, C, h, w) latent clips at random episodes and starts, their instructions and, with
        ``with_objects``, the (b, T, 2, h, w) shares of :meth:`objects`."""
        idx = torch.randint(len(self.sources), (batch_size,), generator=generator).tolist()
        clips, texts, objects = [], [], []
        for i in idx:
            n = self.sources[i].latents.shape[0] - self.num_frames + 1
            start = int(torch.randint(n, (1,), generator=generator))
            clip, text = self.clip(i, start)
            clips.append(clip)
            texts.append(text)
            objects.append(self.objects(i, start))
        if with_objects:
            return torch.stack(clips), texts, torch.stack(objects)
        return torch.stack(clips), texts

    def validation_indices(self, count: int) -> list[int]:
        """Up to ``count`` fixed episodes, spread over the tasks."""
        return spread_over_tasks([s.episode_id for s in self.sources], count)
