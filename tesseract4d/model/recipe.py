"""Recipe levers of diffusion training: each a ``TrainConfig`` switch, measured by
``benchmarks/ablate_latent.py``.

- ``condition_noise``: Gaussian noise of std ``U(0, condition_noise)`` per sample on the conditioning
  first frame during training (sampling uses the clean frame). The known fix for image-to-video
  models that copy their condition and stay static ("conditional image leakage").
- ``moving_weight`` / ``object_weight``: the loss of cells that move (differ from the clip's first
  frame by more than ``MOVING_TOL`` on average over channels, in model-space or normalised-latent
  units) or hold the robot/objects (latent presets: share of robot/object pixels per latent cell, from
  the cached segmentation) is weighted up.
- ``prediction``: the network's target. ``x0`` (the clean clip as "first frame + correction") or
  ``velocity`` (``noise - x0``, the same output read as a velocity after removing the first frame).
- ``time_shift``: where training draws the diffusion time. ``t = s u / (1 + (s - 1) u)`` with
  ``u ~ U(0, 1)`` (the resolution shift of SD3 / flow-matching video models): ``s = 1`` is uniform,
  ``s > 1`` trains more at high noise, where the instruction decides the coarse motion, and less
  near the clean clip, where the noisy sample already shows it. Sampling is unchanged.
- ``text_dropout`` (TrainConfig) and the guidance scales (``tesseract4d predict``) already exist.

Also here: which data a preset trains on (pixels, or a latent cache of an autoencoder).
"""

from __future__ import annotations

import math

import torch

from tesseract4d.errors import UserError
from tesseract4d.model.presets import AUTOENCODER, ModelPreset

PREDICTIONS = ("x0", "velocity")
MOVING_TOL = 0.1


def check_recipe(cfg, preset: ModelPreset) -> None:
    """UserError for recipe values that cannot work with this preset."""
    if cfg.prediction not in PREDICTIONS:
        raise UserError(f"--prediction must be one of {', '.join(PREDICTIONS)}, got {cfg.prediction!r}")
    if cfg.condition_noise < 0 or cfg.moving_weight <= 0 or cfg.object_weight <= 0:
        raise UserError("--condition-noise must be >= 0 and --moving-weight/--object-weight > 0")
    if not (math.isfinite(cfg.time_shift) and cfg.time_shift > 0):
        raise UserError(f"--time-shift must be a finite number > 0 (1 = uniform diffusion times), got {cfg.time_shift}")
    if preset.space == AUTOENCODER and cfg.autoencoder is None:
        raise UserError(f"preset {preset.name!r} works in an RGB-D-N autoencoder's latent space: pass --autoencoder DIR "
                        f"(RUN/autoencoder of `tesseract4d train-autoencoder --data DATA --out RUN`)")
    if preset.space != AUTOENCODER and cfg.object_weight != 1.0:
        raise UserError("--object-weight needs the segmentation of a latent cache: use a latent preset (latent-128)")


def load_training_data(cfg, preset: ModelPreset, model_space, codec, progress: bool = False):
    """The preset's clip dataset over every folder of ``cfg.data``: model-space pixel clips, or latent
    clips from each folder's (re)built cache."""
    from tesseract4d.model.clips import merge_clip_datasets

    return merge_clip_datasets([_load_folder(folder, cfg, preset, model_space, codec, progress)
                                for folder in cfg.data_folders])


def _load_folder(folder, cfg, preset: ModelPreset, model_space, codec, progress: bool):
    from tesseract4d import dataset_format as df

    if preset.space != AUTOENCODER:
        from tesseract4d.model.clips import ClipDataset

        return ClipDataset(folder, num_frames=preset.num_frames, height=preset.height, width=preset.width,
                           model_space=model_space, camera=cfg.camera, show_progress=progress)
    from tesseract4d.model.latent_cache import LatentClipDataset, ensure_latent_cache

    info = df.read_info(folder)
    if (info.height, info.width) != (preset.height, preset.width):
        raise UserError(f"{folder} holds {info.height}x{info.width} episodes but preset {preset.name!r} trains on "
                        f"{preset.height}x{preset.width}; generate data with `tesseract4d datagen --resolution "
                        f"{preset.height} --out DIR` or pick a matching preset")
    ae_cfg = codec.autoencoder.config
    if (ae_cfg.height, ae_cfg.width) != (preset.height, preset.width):
        raise UserError(f"the autoencoder {cfg.autoencoder} works at {ae_cfg.height}x{ae_cfg.width}, preset "
                        f"{preset.name!r} at {preset.height}x{preset.width}; train a matching one with "
                        f"`tesseract4d train-autoencoder`")
    cache, built = ensure_latent_cache(folder, cfg.autoencoder, camera=cfg.camera, progress=progress)
    if progress:
        print(f"{'built' if built else 'reused'} latent cache {cache.folder} (autoencoder {cache.autoencoder_hash})")
    return LatentClipDataset(cache, num_frames=preset.num_frames)


def augment_condition(first: torch.Tensor, max_std: float, generator: torch.Generator) -> torch.Tensor:
    """First frames (b, 1, c, h, w) plus noise of std U(0, max_std) per sample (unchanged when 0)."""
    if max_std <= 0:
        return first
    b = first.shape[0]
    std = torch.rand(b, generator=generator) * max_std
    noise = torch.randn(first.shape, generator=generator)
    return first + (std[:, None, None, None, None] * noise).to(first.device)


def sample_times(b: int, shift: float, generator: torch.Generator) -> torch.Tensor:
    """(b,) diffusion times in [0, 1]: ``s u / (1 + (s - 1) u)`` of ``u ~ U(0, 1)``. At ``shift`` 1 every
    operation is exact in floating point, so the uniform recipe draws exactly what it always drew."""
    u = torch.rand(b, generator=generator)
    return shift * u / (1.0 + (shift - 1.0) * u)


def cell_weights(x0: torch.Tensor, objects: torch.Tensor | None, cfg) -> torch.Tensor | None:
    """(b, t, 1, h, w) loss weights of clean clips ``x0`` (b, t, c, h, w): moving and robot/object
    cells count more; None when both weights are 1."""
    if cfg.moving_weight == 1.0 and cfg.object_weight == 1.0:
        return None
    moving = ((x0 - x0[:, :1]).abs().mean(dim=2, keepdim=True) > MOVING_TOL).float()
    w = 1.0 + (cfg.moving_weight - 1.0) * moving
    if objects is not None and cfg.object_weight != 1.0:
        w = w + (cfg.object_weight - 1.0) * objects[:, :, None].to(w)
    return w


def recipe_loss(out: torch.Tensor, cond: torch.Tensor, x0: torch.Tensor, noise: torch.Tensor,
                channels: dict[str, slice], weights: torch.Tensor | None, prediction: str) -> dict[str, torch.Tensor]:
    """Per-group mean squared error of the network output ``out`` = first frame + correction
    (b, t, c, h, w) against the target of ``prediction``, weighted per cell."""
    if prediction == "velocity":
        err = (out - cond[:, :1] - (noise - x0)) ** 2
    else:
        err = (out - x0) ** 2
    parts = {}
    for name, s in channels.items():
        e = err[:, :, s]
        parts[name] = e.mean() if weights is None else (e * weights).sum() / (weights.sum() * e.shape[2])
    return parts
