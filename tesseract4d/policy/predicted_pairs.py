"""IDM training pairs whose future frame is the world model's prediction, not the truth.

In the world-model arm of a rollout the IDM reads predicted frames: torn, smeared and late where
the model is wrong. Trained only on true futures it has never seen such frames. Here the world model
predicts clips from frames of the training episodes, exactly as the policy loop does
(``WorldModelFuture``), and each predicted frame ``m`` of a clip started at step ``s`` is paired
with the true frame at step ``s + (m - 1) G`` and the true actions from there to ``s + m G``
(``G`` = episode steps / 15, the clip spacing the true pairs use). The IDM thus learns what the
robot did while the model drew this.

Clips start at ``starts`` evenly spaced steps of each episode (0, L/n, 2L/n, ...): the first
like a rollout's first prediction, the others like its replans from mid-episode frames.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from tesseract4d import dataset_format as df
from tesseract4d.errors import UserError
from tesseract4d.policy.idm import clip_gap, encode_target
from tesseract4d.policy.points import frame_points
from tesseract4d.model.checkpoint import weights_digest
from tesseract4d.model.predict import load_pipeline
from tesseract4d.policy.loop import LoopConfig, WorldModelFuture
from datagen.capture import Frame

@dataclass
class PredictedPair:
    now: int  # frame index (in the episode) of the current, true frame
    points: np.ndarray  # (N, 6) the predicted future frame's cloud
    target: np.ndarray  # encode_target of the true actions between them


def clip_starts(num_steps: int, starts: int) -> list[int]:
    """The steps ``starts`` clips are predicted from: 0, L/n, 2L/n, ... (distinct, each < L)."""
    return sorted({(k * num_steps) // starts for k in range(starts)} - {num_steps})


class PredictedFutures:
    """The world model of ``checkpoint`` predicting clips from frames of training episodes."""

    def __init__(self, checkpoint: str, *, starts: int = 3, sample_steps: int | None = None, sample_seed: int = 0,
                 precision: str = "auto"):
        if starts < 1:
            raise UserError(f"--predicted-starts must be at least 1, got {starts}")
        self.checkpoint = str(checkpoint)
        self.pipeline = load_pipeline(checkpoint, precision=precision)
        self.digest = weights_digest(checkpoint)
        self.starts = starts
        self.sample_steps = sample_steps
        self.sample_seed = sample_seed
        self._future = None  # WorldModelFuture, made for the dataset's camera and resolution on first use

    def describe(self) -> dict:
        return {"checkpoint": self.checkpoint, "weights_digest": self.digest, "starts": self.starts,
                "sample_steps": self.sample_steps, "sample_seed": self.sample_seed}

    def _world_model(self, camera: str, resolution: tuple[int, int]):
        if self._future is None:
            config = LoopConfig(camera=camera, resolution=tuple(resolution), sample_steps=self.sample_steps,
                                sample_seed=self.sample_seed)
            self._future = WorldModelFuture(self.pipeline, config)  # refuses another camera / resolution
        return self._future

    def pairs(self, ep: df.Episode, camera: str, num_points: int, chunk_len: int,
              rng: np.random.Generator) -> list[PredictedPair]:
        """The predicted pairs of one episode rendered at every step."""
        cam = ep.cameras[camera]
        num_steps = len(ep.actions)
        if not np.array_equal(ep.frame_steps, np.arange(num_steps + 1)):
            raise UserError(f"{ep.episode_id}: predicted futures need episodes rendered at every step; "
                            f"write the dataset with `tesseract4d datagen --frames 0`")
        wm = self._world_model(camera, tuple(cam.rgb.shape[1:3]))
        gap = clip_gap(num_steps)
        out = []
        for s in clip_starts(num_steps, self.starts):
            frame = Frame(rgb=cam.rgb[s], depth_m=cam.depth_m[s], normal_cam=cam.normal_cam[s],
                          segmentation=np.zeros(cam.depth_m.shape[1:], np.int32), K=cam.K[s],
                          T_world_cam=cam.T_world_cam[s])
            clip = wm.clip(frame, ep.env_id, ep.seed, ep.instruction, s)
            for m in range(1, len(clip.rgb)):
                i, j = s + (m - 1) * gap, min(s + m * gap, num_steps)
                if i >= num_steps:
                    break
                pts = frame_points(clip.rgb[m], clip.depth_m[m], clip.K[m], clip.T_world_cam[m], num_points, rng)
                out.append(PredictedPair(i, pts, encode_target(ep.actions[i:j], ep.qpos[i], chunk_len)))
        return out
