"""Recipe levers of diffusion training: each a ``TrainConfig`` switch, measured by
``benchmarks/ablate_latent.py``.

- ``condition_noise``: Gaussian noise of std ``U(0, condition_noise)`` per sample on the conditioning
  first frame during training (sampling uses the clean frame). The known fix for image-to-video
  models that copy their condition and stay static ("conditional image leakage").
- ``moving_weight`` / ``object_weight``: the loss of cells that move (differ from the clip's first
  frame by more than ``MOVING_TOL`` on average over channels, in model-space or normalised-latent
  units) or hold the robot/objects (latent presets: share of robot/object pixels per latent cell, from
  the cached segmentation) is weighted up.
- ``scene_object_weight``: the loss of the cells that hold the scene's objects alone (cubes,
  cylinders; not the robot: share of their pixels per latent cell, from the cached segmentation) is
  weighted up on top, by their share of each cell. The scene's objects hold 1.5 % of the pixels of
  the training clips and, under v2's recipe, 1.9 % of the loss weight (the robot 25 %; weight 10:
  6 %), and v2 turns a moved object into a smear at middle noise (docs/research/evaluation.md, "Where a
  model fails").
- ``time_logit_normal``: with a standard deviation ``m > 0``, the diffusion time ``t`` is drawn
  logit-normal instead of uniform (``t = sigmoid(m n)``, ``n ~ N(0, 1)``; SD3's sampling of training
  times), which trains most at middle noise: v2 started from the true future loses moved objects
  there, at noise 0.3-0.8 (docs/research/evaluation.md, "Where a model fails"). 0 keeps the uniform draw.
- ``group_batches``: every batch is made of whole counterfactual groups (one scene under several
  instructions, ``clips.draw_group_batch``) that share one noise and one diffusion time, so within a
  group the only thing that tells the futures apart is the words.
- ``counterfactual_swap`` (with group batches): with this probability, a clip whose diffusion time is
  at least ``SWAP_MIN_T`` is shown the noisy sample of another future of its group (same noise, same
  time) and must still predict its own instruction's future. It trains the network to side with the
  words where the noisy sample points elsewhere, as a sampler's intermediate samples do when they
  drift back towards the first frame (docs/research/evaluation.md, "Where a model fails"). Below ``SWAP_MIN_T``
  the noisy sample pins the future, and the swap would ask for the impossible.
- ``rephrase``: with this probability, a clip's instruction is replaced by another training wording
  of the same meaning (same object, direction and distance; the paraphrases come from the datagen's
  train templates, ``datagen.paraphrases``, handed to the trainer by the command line). It trains the
  network to read what the words say rather than which of a few sentences it saw: a model trained
  long on three wordings per skill kept still only under those three (docs/research/training.md,
  "Words").
- ``text_noise``: Gaussian noise on the instruction's token embeddings during training, of std
  ``U(0, text_noise)`` per sample times each token's own root-mean-square (padding stays zero;
  sampling uses the clean words). Long training on a few hundred sentences learns those sentences:
  a held-out wording whose embedding sits between two training meanings was lost (docs/research/training.md,
  "Words"); noise fills the space around each training sentence so
  that nearby wordings read the same.
- ``history_share`` / ``history_noise`` (with ``history_frames`` k > 1): with probability ``history_share``
  a clip's first k true frames become its history (the first k latent frames of its condition, as
  the sampler gives a clip after the first the last k frames of the rollout so far), noised as
  diffusion forcing does, ``x_h = (1 - s) x + s noise`` with ``s ~ U(0, history_noise)`` per clip, and
  its loss counts frames k.. only. The level s is not given to the network: at sampling time the
  history is the model's own earlier frames, whose error is of no known level, so the network learns
  to read history of any quality up to ``history_noise`` rather than to trust a stated one (and the
  network keeps its inputs, so a k = 1 checkpoint such as v2 fine-tunes into it unchanged).
- ``text_dropout`` (TrainConfig) and the guidance scales (``tesseract4d predict``) already exist.

The network always predicts the clean clip (``x0``, as "first frame + correction"). Levers that
were measured and removed (docs/research/removed_features.md): a velocity target, a time shift
towards high noise, a loss weight on the cells where a group's futures differ. Checkpoints and
recipes that record them at their no-op values (``REMOVED_LEVERS``) read as before.

Also here: which data a preset trains on (pixels, or a latent cache of an autoencoder).
"""

from __future__ import annotations

import math

import torch

from tesseract4d.errors import UserError
from tesseract4d.model.presets import AUTOENCODER, PIXEL, ModelPreset
from tesseract4d.model.clips import ClipDataset, merge_clip_datasets
from tesseract4d import dataset_format as df
from tesseract4d.model.latent_cache import LatentClipDataset, ensure_latent_cache

MOVING_TOL = 0.1
SWAP_MIN_T = 0.3
DISAGREE_SHARE = 0.10  # the share of a group's cells where its futures differ most (instruction discrimination)
# Recipe levers this version no longer has, at the values that made them no-ops: a recorded recipe
# (a checkpoint's ``recipe``) that holds one at another value was trained or samples otherwise.
REMOVED_LEVERS = {"prediction": "x0", "time_shift": 1.0, "difference_weight": 1.0}


def removed_levers_in_use(recipe: dict) -> dict:
    """The removed levers a recorded recipe uses (at a value other than their no-op one)."""
    return {k: recipe[k] for k, no_op in REMOVED_LEVERS.items() if k in recipe and recipe[k] != no_op}


def without_removed_levers(recipe: dict, source) -> dict:
    """A recorded recipe without the removed levers (recorded at their no-op values); a UserError naming
    ``source`` when it uses one, since this version cannot train it again."""
    used = removed_levers_in_use(recipe)
    if used:
        raise UserError(f"{source} was trained with {', '.join(f'{k} {v!r}' for k, v in used.items())}, which this "
                        f"tesseract4d no longer has (docs/research/removed_features.md); take its other options "
                        f"without these")
    return {k: v for k, v in recipe.items() if k not in REMOVED_LEVERS}


def check_samples_as_trained(recipe: dict, source) -> None:
    """UserError for a checkpoint whose network predicts a velocity (the removed ``prediction
    velocity``): this sampler reads every output as the clean clip, so it would sample noise."""
    if recipe.get("prediction", "x0") != "x0":
        raise UserError(f"{source} predicts {recipe['prediction']!r}; this tesseract4d samples only networks that "
                        f"predict the clean clip (x0): retrain it, or use an older tesseract4d for it")


def check_recipe(cfg, preset: ModelPreset) -> None:
    """UserError for recipe values that cannot work with this preset."""
    if cfg.condition_noise < 0 or cfg.moving_weight <= 0 or cfg.object_weight <= 0:
        raise UserError("--condition-noise must be >= 0 and --moving-weight/--object-weight > 0")
    if not (math.isfinite(cfg.scene_object_weight) and cfg.scene_object_weight > 0):
        raise UserError(f"--scene-object-weight must be a finite number > 0 (1 = off), got {cfg.scene_object_weight}")
    if not (math.isfinite(cfg.time_logit_normal) and cfg.time_logit_normal >= 0):
        raise UserError(f"--time-logit-normal must be a finite number >= 0 (0 = uniform diffusion times), "
                        f"got {cfg.time_logit_normal}")
    if not 0.0 <= cfg.counterfactual_swap <= 1.0:
        raise UserError(f"--counterfactual-swap is a probability in [0, 1], got {cfg.counterfactual_swap}")
    if not (math.isfinite(cfg.text_noise) and cfg.text_noise >= 0):
        raise UserError(f"--text-noise must be a finite number >= 0 (0 = off), got {cfg.text_noise}")
    if not 0.0 <= cfg.rephrase <= 1.0:
        raise UserError(f"--rephrase is a probability in [0, 1], got {cfg.rephrase}")
    if not 0.0 <= cfg.history_share <= 1.0 or not 0.0 <= cfg.history_noise <= 1.0:
        raise UserError(f"--set history_share and history_noise are in [0, 1], got {cfg.history_share} and "
                        f"{cfg.history_noise}")
    if not 1 <= preset.history_frames < preset.num_frames:
        raise UserError(f"--set history_frames={preset.history_frames}: a clip of {preset.num_frames} frames continues "
                        f"from 1 .. {preset.num_frames - 1} of them")
    if preset.history_frames > 1 and preset.space not in (AUTOENCODER, PIXEL):
        raise UserError(f"--set history_frames needs one latent frame per frame; preset {preset.name!r} encodes "
                        f"frames in groups (a video VAE): keep history_frames=1")
    if cfg.history_share > 0 and preset.history_frames == 1:
        raise UserError("--set history_share trains clips that continue from history frames: add --set "
                        "history_frames=K with K > 1 (e.g. 4)")
    if not cfg.group_batches and cfg.counterfactual_swap > 0:
        raise UserError("--counterfactual-swap compares the futures of a counterfactual group: add --group-batches")
    if preset.space == AUTOENCODER and cfg.autoencoder is None:
        raise UserError(f"preset {preset.name!r} works in an RGB-D-N autoencoder's latent space: pass --autoencoder DIR "
                        f"(RUN/autoencoder of `tesseract4d train-autoencoder --data DATA --out RUN`)")
    if preset.space != AUTOENCODER and (cfg.object_weight != 1.0 or cfg.scene_object_weight != 1.0):
        raise UserError("--object-weight and --scene-object-weight need the segmentation of a latent cache: use a "
                        "latent preset (latent-128)")


def check_scene_objects(data, cfg) -> None:
    """UserError when ``--scene-object-weight`` asks for shares that a latent cache does not carry (a cache
    that travelled without its episodes, built before the shares existed, cannot be rebuilt)."""
    if cfg.scene_object_weight != 1.0 and getattr(data, "encoded", False) and not data.has_scene_objects:
        raise UserError("--scene-object-weight needs the scene objects' shares in every latent cache, and a cache "
                        "without episodes beside it predates them; rebuild it where the episodes are with "
                        "`tesseract4d encode-latents --data DATASET --autoencoder AE_DIR --rebuild` and copy it again")


def load_training_data(cfg, preset: ModelPreset, model_space, codec, progress: bool = False):
    """The preset's clip dataset over every folder of ``cfg.data``: model-space pixel clips, or latent
    clips from each folder's (re)built cache."""
    return merge_clip_datasets([_load_folder(folder, cfg, preset, model_space, codec, progress)
                                for folder in cfg.data_folders])


def _load_folder(folder, cfg, preset: ModelPreset, model_space, codec, progress: bool):
    if preset.space != AUTOENCODER:
        return ClipDataset(folder, num_frames=preset.num_frames, height=preset.height, width=preset.width,
                           model_space=model_space, camera=cfg.camera, show_progress=progress)

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


def per_sample_noise(shape: torch.Size, max_std: float, generator: torch.Generator) -> torch.Tensor:
    """Gaussian noise of ``shape`` (b, ...) with one std drawn from U(0, max_std) per sample (CPU)."""
    std = torch.rand(shape[0], generator=generator) * max_std
    noise = torch.randn(shape, generator=generator)
    return std.view(-1, *[1] * (len(shape) - 1)) * noise


def augment_condition(first: torch.Tensor, max_std: float, generator: torch.Generator) -> torch.Tensor:
    """First frames (b, 1, c, h, w) plus noise of std U(0, max_std) per sample (unchanged when 0)."""
    if max_std <= 0:
        return first
    return first + per_sample_noise(first.shape, max_std, generator).to(first.device)


def augment_text(text: torch.Tensor, max_rel_std: float, generator: torch.Generator) -> torch.Tensor:
    """Token embeddings (b, L, d) plus noise of std ``U(0, max_rel_std)`` per sample times each token's
    root-mean-square over d; zero (padding) tokens stay zero. Unchanged, drawing nothing, when 0."""
    if max_rel_std <= 0:
        return text
    rms = text.pow(2).mean(-1, keepdim=True).sqrt()  # (b, L, 1), 0 on padding
    return text + rms * per_sample_noise(text.shape, max_rel_std, generator).to(text.device)


def sample_times(b: int, generator: torch.Generator, logit_normal: float = 0.0) -> torch.Tensor:
    """(b,) diffusion times in [0, 1]: ``U(0, 1)``, or logit-normal ``sigmoid(logit_normal * n)``,
    ``n ~ N(0, 1)``, when ``logit_normal`` > 0."""
    if logit_normal > 0:
        return torch.sigmoid(logit_normal * torch.randn(b, generator=generator))
    return torch.rand(b, generator=generator)


def share_within_groups(x: torch.Tensor, leaders: list[int] | None) -> torch.Tensor:
    """``x`` (b, ...) with every clip's entry replaced by its group leader's (one noise, one time per
    group); unchanged without groups."""
    return x if leaders is None else x[torch.as_tensor(leaders, device=x.device)]


def disagreement_mask(x0: torch.Tensor, share: float = DISAGREE_SHARE) -> torch.Tensor:
    """(1, t', 1, h, w) float mask of the ``share`` of cells where a group's true futures x0 (n, t', c, h, w)
    spread most (their standard deviation over the group, averaged over channels); never a cell where
    they agree exactly, so futures that differ in fewer cells mark only those."""
    spread = x0.float().std(0, keepdim=True).mean(2, keepdim=True)  # (1, t', 1, h, w)
    threshold = torch.quantile(spread.flatten(), 1.0 - share)
    return ((spread >= threshold) & (spread > 0)).float()


def draw_history(x0: torch.Tensor, k: int, share: float, max_noise: float,
                 generator: torch.Generator) -> tuple[torch.Tensor, torch.Tensor] | None:
    """History of the clips ``x0`` (b, t, c, h, w): (given (b, k, c, h, w), chosen (b,) bool), where
    ``given`` is each clip's first k frames noised at a level ``s ~ U(0, max_noise)`` per clip,
    ``(1 - s) x + s noise``, and ``chosen`` marks the clips (each with probability ``share``) that continue
    from it. None, drawing nothing, when k = 1 or ``share`` = 0 (every clip from its first frame)."""
    if k <= 1 or share <= 0:
        return None
    b = x0.shape[0]
    chosen = torch.rand(b, generator=generator) < share
    s = (torch.rand(b, generator=generator) * max_noise).view(b, 1, 1, 1, 1)
    noise = torch.randn((b, k, *x0.shape[2:]), generator=generator)
    given = (1 - s.to(x0)) * x0[:, :k] + s.to(x0) * noise.to(x0)
    return given, chosen.to(x0.device)


def history_loss_mask(x0: torch.Tensor, k: int, chosen: torch.Tensor, weights: torch.Tensor | None) -> torch.Tensor:
    """(b, t, 1, h, w) loss weights (``weights``, or ones) with frames 0 .. k-1 of the ``chosen`` clips at
    zero: those frames were given as history, so nothing is learnt from predicting them."""
    b, t, _, h, w = x0.shape
    out = torch.ones(b, t, 1, h, w, dtype=x0.dtype, device=x0.device) if weights is None else weights.clone()
    out[chosen.to(out.device), :k] = 0.0
    return out


def cell_weights(x0: torch.Tensor, objects: torch.Tensor | None, cfg) -> torch.Tensor | None:
    """(b, t, 1, h, w) loss weights of clean clips ``x0`` (b, t, c, h, w): moving, robot/object and scene
    object cells count more; None when every weight is 1.
    ``objects``: (b, t, 2, h, w) shares per cell of the robot and objects (channel 0) and of the scene's
    objects alone (channel 1), as ``LatentClipDataset.objects`` gives them; None without a cache."""
    if cfg.moving_weight == 1.0 and cfg.object_weight == 1.0 and cfg.scene_object_weight == 1.0:
        return None
    moving = ((x0 - x0[:, :1]).abs().mean(dim=2, keepdim=True) > MOVING_TOL).float()
    w = 1.0 + (cfg.moving_weight - 1.0) * moving
    if objects is not None and cfg.object_weight != 1.0:
        w = w + (cfg.object_weight - 1.0) * objects[:, :, :1].to(w)
    if objects is not None and cfg.scene_object_weight != 1.0:
        w = w + (cfg.scene_object_weight - 1.0) * objects[:, :, 1:2].to(w)
    return w


def swap_sources(leaders: list[int], t: torch.Tensor, probability: float, generator: torch.Generator) -> list[int]:
    """For each clip, the clip whose noisy sample it is shown: itself, or (with ``probability``, when
    its diffusion time is at least ``SWAP_MIN_T`` and its group has another member) another member of
    its group drawn uniformly. Draws the same random numbers whatever the outcome."""
    u = torch.rand(len(leaders), generator=generator).tolist()
    pick = torch.rand(len(leaders), generator=generator).tolist()
    shown = list(range(len(leaders)))
    for k, leader in enumerate(leaders):
        siblings = [j for j, other in enumerate(leaders) if other == leader and j != k]
        if siblings and u[k] < probability and float(t[k]) >= SWAP_MIN_T:
            shown[k] = siblings[min(int(pick[k] * len(siblings)), len(siblings) - 1)]
    return shown


def rephrase(texts: list[str], paraphrases, probability: float, generator: torch.Generator) -> list[str]:
    """Each instruction, or (with ``probability``) one of ``paraphrases(instruction)`` drawn uniformly
    (the list holds the instruction itself). Draws the same random numbers whatever the outcome."""
    u = torch.rand(len(texts), generator=generator).tolist()
    pick = torch.rand(len(texts), generator=generator).tolist()
    out = []
    for text, uk, pk in zip(texts, u, pick):
        options = paraphrases(text) if uk < probability else [text]
        out.append(options[min(int(pk * len(options)), len(options) - 1)])
    return out


def recipe_loss(out: torch.Tensor, x0: torch.Tensor, channels: dict[str, slice],
                weights: torch.Tensor | None) -> dict[str, torch.Tensor]:
    """Per-group mean squared error of the network output ``out`` = first frame + correction
    (b, t, c, h, w) against the clean clip ``x0``, weighted per cell."""
    err = (out - x0) ** 2
    parts = {}
    for name, s in channels.items():
        e = err[:, :, s]
        parts[name] = e.mean() if weights is None else (e * weights).sum() / (weights.sum() * e.shape[2])
    return parts
