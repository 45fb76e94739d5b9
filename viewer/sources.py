"""What the viewer can open, turned into one in-memory type: :class:`Recon4D`.

* a reconstruction folder (``manifest.json`` + ``recon4d.npz``) is loaded as is;
* a dataset episode (a ``.h5`` file, ``DIR/ENV_ID/SEED``, or a dataset folder holding one
  episode, which is how predictions are written) is back-projected on the fly, frame by frame,
  without any refinement (:func:`reconstruction.backproject.recon_from_episode`).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from reconstruction.backproject import recon_from_episode
from reconstruction.recon4d import MANIFEST, Recon4D
from tesseract4d.dataset_format import CameraFrames, Episode, read_episode, resolve_episode, samples_hint
from tesseract4d.errors import UserError


def load_source(path: str | os.PathLike, camera: str | None = None) -> Recon4D:
    """Open PATH as a reconstruction folder or a dataset episode; raise UserError with the fix."""
    p = Path(path)
    if p.is_dir() and (p / MANIFEST).is_file():
        recon = Recon4D.load(p)
        made_from = recon.metadata.get("camera")
        if camera is not None and camera != made_from:
            raise UserError(f"{p} is a reconstruction of {'camera ' + repr(made_from) if made_from else 'one camera'}; "
                            f"--camera chooses among an episode's cameras: drop it, or reconstruct the episode with "
                            f"--camera {camera}")
        return recon
    if not p.exists() and not (p.parent.parent / "episodes").is_dir():
        raise UserError(
            f"{p} does not exist. Pass a reconstruction folder (from `tesseract4d reconstruct`), an episode "
            ".h5 file, a dataset/prediction folder with one episode, or DIR/ENV_ID/SEED."
        )
    if p.is_file() and p.suffix != ".h5":
        raise UserError(
            f"{p} is not something the viewer opens: expected a reconstruction folder (with {MANIFEST}) or a "
            "dataset episode (.h5 file, dataset folder with one episode, or DIR/ENV_ID/SEED)."
        )
    if p.is_dir() and not (p / "episodes").is_dir():
        if hint := samples_hint(p):
            raise UserError(hint)
        raise UserError(
            f"{p} is neither a reconstruction folder (no {MANIFEST}) nor a dataset folder (no episodes/); "
            "pass the folder written by `tesseract4d reconstruct`, `predict` or `datagen`."
        )
    episode_file = resolve_episode(p)
    episode = read_episode(episode_file)
    recon = recon_from_episode(episode, camera=camera)
    recon.metadata["episode_path"] = str(episode_file)
    return recon


def first_frame_episode(recon: Recon4D) -> Episode:
    """The first frame of a source as a one-frame episode (the model's conditioning input).

    Uses the original episode file when the source was opened from one, so the simulator
    metadata travels along; otherwise rebuilds the frame from the reconstruction's images.
    """
    path = recon.metadata.get("episode_path")
    if path and Path(path).is_file():
        return read_episode(path, frames=slice(0, 1))
    meta = recon.metadata
    return Episode(
        env_id=str(meta.get("env_id", meta.get("task", "unknown"))),
        seed=int(meta.get("seed", 0)),
        instruction=str(meta.get("instruction", "")),
        cameras={str(meta.get("camera", "base_camera")): CameraFrames(
            rgb=recon.rgb[:1], depth_m=recon.depth_m[:1], normal_cam=recon.normal_cam[:1],
            K=recon.K[:1], T_world_cam=recon.T_world_cam[:1],
        )},
        frame_steps=np.zeros(1, np.int32),
        fps=recon.fps,
    )
