"""Training clips: fixed-length RGB-D-N clips cut from dataset episodes at random starts.

All episodes of one camera are read once into memory in model space (float16, ~0.9 MB per 16-frame
64x64 episode). Batches are drawn with an explicit ``torch.Generator``, so the trainer can make
every step's batch a pure function of (seed, step): a resumed run sees exactly the same batches.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import torch

from tesseract4d import dataset_format as df
from tesseract4d.errors import UserError
from tesseract4d.model.model_space import ModelSpace


@dataclass
class ClipSource:
    episode_id: str
    camera: str
    instruction: str
    frames: torch.Tensor  # (T, 7, H, W) float16 model space


class ClipDataset:
    """Clips of ``num_frames`` frames from every episode (of one camera) of a dataset folder.

    Raises UserError when the dataset is missing, its resolution is not the preset's, or no episode
    is long enough.
    """

    def __init__(self, root: str | os.PathLike, *, num_frames: int, height: int, width: int,
                 model_space: ModelSpace, camera: str | None = None, show_progress: bool = False):
        info = df.read_info(root)
        if (info.height, info.width) != (height, width):
            raise UserError(f"{root} holds {info.height}x{info.width} episodes but the preset trains on {height}x{width}; "
                            f"generate data with `tesseract4d datagen --height {height} --width {width}` or pick the matching preset")
        self.camera = camera or info.cameras[0]
        if self.camera not in info.cameras:
            raise UserError(f"{root} has no camera {self.camera!r}; it has {', '.join(info.cameras)}")
        files = df.list_episode_files(root)
        if not files:
            raise UserError(f"{root} holds no episodes; write some with `tesseract4d datagen --out {root}`")
        self.num_frames = num_frames
        self.root = Path(root)
        self.sources: list[ClipSource] = []
        skipped = 0
        iterator = files
        if show_progress:
            from tqdm import tqdm

            iterator = tqdm(files, desc="loading episodes", unit="ep")
        for path in iterator:
            ep = df.read_episode(path, cameras=[self.camera])
            if ep.num_frames < num_frames:
                skipped += 1
                continue
            cam = ep.cameras[self.camera]
            x = model_space.encode(cam.rgb, cam.depth_m, cam.normal_cam).half()  # (T, 7, H, W)
            self.sources.append(ClipSource(ep.episode_id, self.camera, ep.instruction, x))
        if not self.sources:
            raise UserError(f"no episode in {root} has {num_frames} frames (the preset's clip length); "
                            f"regenerate with `tesseract4d datagen --frames {num_frames}`")
        self.skipped = skipped

    def __len__(self) -> int:
        return len(self.sources)

    def clip(self, index: int, start: int = 0) -> tuple[torch.Tensor, str]:
        """One clip (T, 7, H, W) float32 and its instruction."""
        src = self.sources[index]
        return src.frames[start:start + self.num_frames].float(), src.instruction

    def sample_batch(self, batch_size: int, generator: torch.Generator) -> tuple[torch.Tensor, list[str]]:
        """(b, T, 7, H, W) float32 clips at random episodes and starts, plus their instructions."""
        idx = torch.randint(len(self.sources), (batch_size,), generator=generator).tolist()
        clips, texts = [], []
        for i in idx:
            n = self.sources[i].frames.shape[0] - self.num_frames + 1
            start = int(torch.randint(n, (1,), generator=generator))
            clip, text = self.clip(i, start)
            clips.append(clip)
            texts.append(text)
        return torch.stack(clips), texts

    def validation_indices(self, count: int) -> list[int]:
        """Up to ``count`` fixed episodes for validation videos, spread over the tasks."""
        return spread_over_tasks([s.episode_id for s in self.sources], count)


def merge_clip_datasets(datasets: list):
    """One clip dataset over the episodes of several (``ClipDataset`` or latent ``LatentClipDataset``
    of the same kind, camera and clip length); a single dataset is returned as it is."""
    first = datasets[0]
    for other in datasets[1:]:
        if type(other) is not type(first) or other.num_frames != first.num_frames:
            raise UserError("the training datasets must be of one kind and clip length")
        if other.camera != first.camera:
            raise UserError(f"the training datasets use cameras {first.camera!r} and {other.camera!r}; pass --camera "
                            f"NAME to pick one that every dataset has")
        ids = {s.episode_id for s in first.sources}
        clash = next((s.episode_id for s in other.sources if s.episode_id in ids), None)
        if clash is not None:
            raise UserError(f"episode {clash} is in two of the training datasets; pass each dataset folder once")
        first.sources = first.sources + other.sources
        first.skipped += other.skipped
    return first


def spread_over_tasks(episode_ids: list[str], count: int) -> list[int]:
    """Indices of up to ``count`` episodes (ids ``TASK/...``), taking the tasks in turn."""
    by_task: dict[str, list[int]] = {}
    for i, episode_id in enumerate(episode_ids):
        by_task.setdefault(episode_id.split("/")[0], []).append(i)
    out: list[int] = []
    while len(out) < min(count, len(episode_ids)):
        for ids in by_task.values():
            taken = [i for i in ids if i not in out]
            if taken and len(out) < count:
                out.append(taken[0])
    return out
