"""Inverse dynamics model (IDM): current point cloud + future point cloud + instruction + joint
positions -> the action chunk that takes the robot from the current frame to the future one.

TesserAct's design at our scale: a PointNet (shared per-point MLP + max pool) encodes the
current and the future cloud; their features, their difference, a sentence embedding of the
instruction and the robot's joint positions go through an MLP to the chunk. The behaviour-cloning
baseline (``use_future=False``) is the same network without the future branch.

Action space (stored in the config, checked against the rollout's env):
``pd_joint_pos`` for the Panda: 7 absolute arm joint targets (rad) + 1 gripper command
(-1 closed .. 1 open). The chunk is ``chunk_len`` actions sampled evenly over the steps between
the two frames; arm targets are predicted relative to the current arm joint positions. One more
output is log(steps between the frames), so the chunk can be replayed at the right speed when a
predicted clip moves faster or slower than the training episodes.

Files: ``idm_config.json`` (IDMConfig) + ``model.safetensors`` (weights and target normalisation).
"""

from __future__ import annotations

import json
import os
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import torch
from torch import nn

from tesseract4d.errors import UserError
from tesseract4d.outputs import files_as_created
from tesseract4d.policy.points import POINT_CHANNELS
from tesseract4d.resize import resize_factor

CONFIG_FILE = "idm_config.json"
WEIGHTS_FILE = "model.safetensors"
FORMAT = "tesseract4d-idm"
ARM_JOINTS = 7  # Panda arm joints; the rest of the action vector is the gripper


@dataclass
class IDMConfig:
    """Everything that rebuilds an IDM and says what it was trained for."""

    use_future: bool = True  # False = behaviour cloning (observation + instruction -> action)
    num_points: int = 512
    chunk_len: int = 8
    action_dim: int = 8
    qpos_dim: int = 9
    text_dim: int = 384
    point_widths: list[int] = field(default_factory=lambda: [32, 64, 128])
    head_width: int = 512
    control_mode: str = "pd_joint_pos"
    camera: str = "close"
    resolution: list[int] = field(default_factory=lambda: [64, 64])
    text_encoder: str = "minilm"
    frame_gap: str = "episode_steps/15"  # steps between the two frames of a training pair
    training: dict = field(default_factory=dict)

    @property
    def output_dim(self) -> int:
        return self.chunk_len * self.action_dim + 1  # chunk + log(steps)


class PointNetEncoder(nn.Module):
    """(B, N, 6) points -> (B, width) by a shared per-point MLP and a max over points."""

    def __init__(self, widths: list[int]):
        super().__init__()
        layers, last = [], POINT_CHANNELS
        for w in widths:
            layers += [nn.Linear(last, w), nn.ReLU()]
            last = w
        self.mlp = nn.Sequential(*layers[:-1])  # no activation before the max
        self.out_dim = last

    def forward(self, points: torch.Tensor) -> torch.Tensor:
        return self.mlp(points).amax(dim=1)  # (B, N, w) -> (B, w)


class InverseDynamics(nn.Module):
    """The IDM (or, with ``use_future=False``, the behaviour-cloning policy)."""

    def __init__(self, config: IDMConfig):
        super().__init__()
        self.config = config
        self.encoder = PointNetEncoder(config.point_widths)
        w = self.encoder.out_dim
        in_dim = (3 * w if config.use_future else w) + 128 + 64
        self.text_proj = nn.Sequential(nn.Linear(config.text_dim, 128), nn.GELU())
        self.qpos_proj = nn.Sequential(nn.Linear(config.qpos_dim, 64), nn.GELU())
        h = config.head_width
        self.head = nn.Sequential(nn.Linear(in_dim, h), nn.GELU(), nn.Linear(h, h), nn.GELU(),
                                  nn.Linear(h, config.output_dim))
        # Target normalisation (training-set mean/std of the raw outputs), saved with the weights.
        self.register_buffer("target_mean", torch.zeros(config.output_dim))
        self.register_buffer("target_std", torch.ones(config.output_dim))
        self.register_buffer("qpos_mean", torch.zeros(config.qpos_dim))
        self.register_buffer("qpos_std", torch.ones(config.qpos_dim))

    def forward(self, points_now: torch.Tensor, points_next: torch.Tensor | None, text: torch.Tensor,
                qpos: torch.Tensor) -> torch.Tensor:
        """points_*: (B, N, 6); text: (B, text_dim) sentence embeddings; qpos: (B, qpos_dim).
        Returns (B, output_dim) normalised outputs (see ``decode``)."""
        f_now = self.encoder(points_now)
        feats = [f_now]
        if self.config.use_future:
            if points_next is None:
                raise ValueError("this IDM needs the future point cloud")
            f_next = self.encoder(points_next)
            feats += [f_next, f_next - f_now]
        q = (qpos - self.qpos_mean) / self.qpos_std
        return self.head(torch.cat(feats + [self.text_proj(text), self.qpos_proj(q)], dim=-1))

    def decode(self, out: torch.Tensor, qpos: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Normalised outputs (B, output_dim) -> (actions (B, chunk_len, action_dim) absolute, steps (B,) float)."""
        raw = out * self.target_std + self.target_mean
        c = self.config
        chunk = raw[:, :-1].reshape(-1, c.chunk_len, c.action_dim).clone()  # (B, C, A)
        chunk[..., :ARM_JOINTS] += qpos[:, None, :ARM_JOINTS]
        return chunk, raw[:, -1].exp()


# --------------------------------------------------------------------------- targets


def chunk_indices(num_steps: int, chunk_len: int) -> np.ndarray:
    """Indices into ``num_steps`` actions of ``chunk_len`` evenly spaced samples ending at the last one."""
    return np.clip(np.ceil(np.arange(1, chunk_len + 1) * num_steps / chunk_len).astype(np.int64) - 1, 0, num_steps - 1)


CLIP_INTERVALS = 15  # a predicted clip is 16 frames = 15 intervals over the episode


def clip_gap(num_steps: int, scale: float = 1.0) -> int:
    """Env steps between two frames of a predicted clip over an episode of ``num_steps`` steps
    (``scale`` times episode steps / 15, at least 1): the spacing of the IDM's training pairs."""
    return max(1, int(round(scale * num_steps / CLIP_INTERVALS)))


def encode_target(actions: np.ndarray, qpos_now: np.ndarray, chunk_len: int) -> np.ndarray:
    """The raw training target of the ``actions`` (n, A) between two frames, from joint positions
    ``qpos_now``: (chunk_len * A + 1,) = chunk with arm targets relative to qpos_now, log(n)."""
    chunk = actions[chunk_indices(len(actions), chunk_len)].astype(np.float32).copy()  # (C, A)
    chunk[:, :ARM_JOINTS] -= qpos_now[:ARM_JOINTS]
    return np.concatenate([chunk.reshape(-1), [np.log(len(actions))]]).astype(np.float32)


def expand_chunk(chunk: np.ndarray, num_steps: int) -> np.ndarray:
    """A chunk (C, A) replayed over ``num_steps`` env steps: (num_steps, A), sample at the same fraction."""
    idx = np.clip(np.ceil(np.arange(1, num_steps + 1) * len(chunk) / num_steps).astype(np.int64) - 1, 0, len(chunk) - 1)
    return chunk[idx]


# --------------------------------------------------------------------------- text


def sentence_embeddings(encoder, instructions: list[str]) -> torch.Tensor:
    """(B, d) L2-normalised mean of the encoder's token embeddings (padding rows are zero)."""
    tokens = encoder.encode(instructions)  # (B, L, d), zero rows = padding
    mask = (tokens.abs().sum(-1, keepdim=True) > 0).float()
    mean = (tokens * mask).sum(1) / mask.sum(1).clamp(min=1.0)
    return torch.nn.functional.normalize(mean, dim=-1)


# --------------------------------------------------------------------------- files


def save_idm(model: InverseDynamics, folder: str | os.PathLike) -> Path:
    from safetensors.torch import save_file

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    save_file({k: v.detach().contiguous() for k, v in model.state_dict().items()}, str(folder / WEIGHTS_FILE))
    files_as_created(folder / WEIGHTS_FILE)  # safetensors writes 0600
    (folder / CONFIG_FILE).write_text(json.dumps({"format": FORMAT, **asdict(model.config)}, indent=2))
    return folder


def load_idm(folder: str | os.PathLike) -> InverseDynamics:
    """Rebuild an IDM from its folder; UserError when the folder is not one."""
    from safetensors.torch import load_file

    folder = Path(folder)
    if not (folder / CONFIG_FILE).is_file() or not (folder / WEIGHTS_FILE).is_file():
        raise UserError(f"{folder} is not an inverse dynamics model: it needs {CONFIG_FILE} and {WEIGHTS_FILE} "
                        f"(written by `tesseract4d train-idm --out RUN`, in RUN/final)")
    cfg = json.loads((folder / CONFIG_FILE).read_text())
    if cfg.pop("format", None) != FORMAT:
        raise UserError(f"{folder / CONFIG_FILE} is not a {FORMAT} config")
    model = InverseDynamics(IDMConfig(**cfg))
    model.load_state_dict(load_file(str(folder / WEIGHTS_FILE)))
    return model.eval()


def check_compatible(config: IDMConfig, *, control_mode: str, action_dim: int, camera: str,
                     resolution: tuple[int, int], what: str) -> None:
    """UserError naming both sides when the IDM was trained for another action space or camera."""
    if config.control_mode != control_mode or config.action_dim != action_dim:
        raise UserError(f"the IDM was trained on actions {config.control_mode} ({config.action_dim}-d) but {what} "
                        f"uses {control_mode} ({action_dim}-d); train an IDM on data of that control mode")

    # Frames of another resolution reach the IDM resized to its own, by a whole factor (the policy loop).
    if config.camera != camera or resize_factor(resolution, config.resolution) is None:
        raise UserError(f"the IDM was trained on camera {config.camera!r} at {config.resolution[0]}x{config.resolution[1]} "
                        f"but {what} renders camera {camera!r} at {resolution[0]}x{resolution[1]}; "
                        f"pass --camera/--resolution to match (a whole multiple or divisor of its resolution), "
                        f"or train an IDM on that camera")
