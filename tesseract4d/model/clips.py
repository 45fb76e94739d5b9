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
            ep = df.read_episode(path, cameras=[self.camera], check=True)
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

    def frame_count(self, index: int) -> int:
        return int(self.sources[index].frames.shape[0])

    def sample_group_batch(self, batch_size: int, generator: torch.Generator) -> tuple[torch.Tensor, list[str], list[int]]:
        """(b, T, 7, H, W) clips of whole counterfactual groups, their instructions and each clip's
        group leader (see :func:`draw_group_batch`)."""
        indices, starts, leaders = grouped_batch_plan(self, batch_size, generator)
        pairs = [self.clip(i, s) for i, s in zip(indices, starts)]
        return torch.stack([c for c, _ in pairs]), [t for _, t in pairs], leaders

    def batch_plan(self, batch_size: int, generator: torch.Generator) -> tuple[list[int], list[int]]:
        """The episode indices and clip starts of :meth:`sample_batch` (the same draws from ``generator``)."""
        idx = torch.randint(len(self.sources), (batch_size,), generator=generator).tolist()
        starts = []
        for i in idx:
            n = self.sources[i].frames.shape[0] - self.num_frames + 1
            starts.append(int(torch.randint(n, (1,), generator=generator)))
        return idx, starts

    def sample_batch(self, batch_size: int, generator: torch.Generator) -> tuple[torch.Tensor, list[str]]:
        """(b, T, 7, H, W) float32 clips at random episodes and starts, plus their instructions."""
        pairs = [self.clip(i, s) for i, s in zip(*self.batch_plan(batch_size, generator))]
        return torch.stack([c for c, _ in pairs]), [t for _, t in pairs]

    def validation_indices(self, count: int) -> list[int]:
        """Up to ``count`` fixed episodes for validation videos, spread over the tasks."""
        return spread_over_tasks([s.episode_id for s in self.sources], count)


def group_units(episode_ids: list[str]) -> list[list[int]]:
    """The units of a grouped batch: the episodes of each counterfactual group (same scene, one
    instruction each; ids ``<env>/seed_N_kK``), and every episode outside a group alone."""
    units: dict[str, list[int]] = {}
    for i, episode_id in enumerate(episode_ids):
        units.setdefault(df.group_of_episode_id(episode_id) or f"#{i}", []).append(i)
    return list(units.values())


def draw_group_batch(units: list[list[int]], lengths: list[int], num_frames: int, batch_size: int,
                     generator: torch.Generator, unit_weights: torch.Tensor | None = None
                     ) -> tuple[list[int], list[int], list[int]]:
    """A batch of whole counterfactual groups: a group is drawn uniformly (so each episode, one clip
    per draw of its group, is as likely as any other, in a group or alone, as in an ungrouped batch),
    or in proportion to ``unit_weights`` (one per unit) where given, and joins whole, its episodes in
    random order with one clip start for all of them, until ``batch_size`` clips (the last group is
    cut to fit). Returns the episode indices, the clip starts and, for each clip, the batch position of
    its group's first clip (the index to share noise and diffusion time by)."""
    indices: list[int] = []
    starts: list[int] = []
    leaders: list[int] = []
    while len(indices) < batch_size:
        if unit_weights is None:
            unit = units[int(torch.randint(len(units), (1,), generator=generator))]
        else:
            unit = units[int(torch.multinomial(unit_weights, 1, generator=generator))]
        order = torch.randperm(len(unit), generator=generator).tolist()
        members = [unit[k] for k in order][:batch_size - len(indices)]
        n = min(lengths[i] for i in members) - num_frames + 1
        start = int(torch.randint(n, (1,), generator=generator))
        leader = len(indices)
        indices += members
        starts += [start] * len(members)
        leaders += [leader] * len(members)
    return indices, starts, leaders


def _group_plan(dataset) -> tuple[list[list[int]], list[int]]:
    """The group units and episode lengths of a clip dataset, worked out once per list of episodes (a
    merge of datasets makes a new list) rather than in every training step."""
    key = (id(dataset.sources), len(dataset.sources))
    if getattr(dataset, "_group_plan_key", None) != key:
        dataset._group_plan = (group_units([s.episode_id for s in dataset.sources]),
                               [dataset.frame_count(i) for i in range(len(dataset.sources))])
        dataset._group_plan_key = key
    return dataset._group_plan


def dataset_units(dataset) -> list[list[int]]:
    """:func:`group_units` of a clip dataset (``ClipDataset`` or ``LatentClipDataset``); a UserError when
    it holds no counterfactual group."""
    units, _ = _group_plan(dataset)
    if all(len(u) == 1 for u in units):
        raise UserError("--group-batches needs counterfactual groups (episodes seed_N_kK of one scene under several "
                        "instructions) and the training data has none; generate some with `tesseract4d datagen "
                        "--instructions-per-scene 4`")
    return units


def grouped_batch_plan(dataset, batch_size: int, generator: torch.Generator) -> tuple[list[int], list[int], list[int]]:
    """:func:`draw_group_batch` over a clip dataset."""
    units = dataset_units(dataset)
    return draw_group_batch(units, _group_plan(dataset)[1], dataset.num_frames, batch_size, generator)


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
