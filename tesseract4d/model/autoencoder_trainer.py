"""Training of the RGB-D-N autoencoder (``model/autoencoder.py``), per frame.

Loss per frame, each term a per-pixel weighted mean with weight ``w = 1 + (object_weight - 1) *
robot_or_object + edge_weight * depth_edge`` (robot and object pixels come from the dataset's
segmentation; depth edges from the target's depth gradient), so small things and discontinuities
survive compression:

    rgb_weight    * |rgb_hat - rgb|
  + depth_weight  * |depth_hat - depth|            (model space, i.e. metric over a fixed range)
  + normal_weight * (|n_hat - n| + (1 - cos(n_hat / |n_hat|, n)))
  + grad_weight   * (|grad depth_hat - grad depth| + |grad n_hat - grad n|)   (finite differences)
  + kl_weight     * KL(posterior || N(0, I)) per latent element

Everything random in a step (frames, posterior sample) comes from a generator seeded by
(seed, step), so a resumed run continues exactly. The loop (stop signals, schedule, checkpoints,
logs) is the project's one training loop (``training/loop.py``); every checkpoint also exports
RUN/autoencoder and measures its fidelity gate.

``decoder_only`` fine-tunes only the decoder of an ``init`` autoencoder: its encoder and latent
statistics stay bit-identical, so the latents (and a latent model trained on them, its latent
caches' contents) stay valid and the new decoder can replace the old one in a latent checkpoint
(``checkpoint_copies.replace_decoder``).

Run folder::

    RUN/ae_train_config.json               the resolved AutoencoderTrainConfig
    RUN/logs/                              TensorBoard (loss terms, lr, steps/s, fidelity gate)
    RUN/checkpoint-XXXXXX/                 training state: model/ (raw weights), model_ema/,
                                           optimizer.safetensors + optimizer.json, trainer_state.json
    RUN/autoencoder/                       the exported autoencoder (EMA weights, latent statistics,
                                           fidelity.json): what latent caches and the latent model use
"""

from __future__ import annotations

import json
import os
import shutil
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import torch
import torch.nn.functional as F

from tesseract4d import dataset_format as df
from tesseract4d.configs import config_dict, folder_list
from tesseract4d.errors import UserError
from tesseract4d.precision import announce, precision_field, resolve_precision
from tesseract4d.segments import robot_object_mask
from tesseract4d.training.checkpoints import (list_checkpoints, load_optimizer, resume_newest, save_optimizer,
                                              write_checkpoint)
from tesseract4d.training.config import TrainingLoopConfig, option
from tesseract4d.training.loop import (check_finite, learning_rate, loop_state, restore_loop_state, run_loop,
                                       set_learning_rate, write_config_file)
from tesseract4d.model.autoencoder import (
    FIDELITY_FILE, WEIGHTS_FILE, AutoencoderConfig, RGBDNAutoencoder, get_autoencoder_preset, read_autoencoder_config,
    save_autoencoder,
)
from tesseract4d.model.model_space import ModelSpace, channel_slices
from tesseract4d.model.trainer import EMA
from tesseract4d.outputs import claim_folder

CONFIG_FILE = "ae_train_config.json"
EXPORT_DIR = "autoencoder"
DEPTH_EDGE_THRESHOLD = 0.02  # model-space depth step between neighbours (~13 mm over 0.2-1.5 m)
LATENT_STATS_FRAMES = 256


@dataclass
class AutoencoderTrainConfig(TrainingLoopConfig):
    """Options of `tesseract4d train-autoencoder`: the loop's (``TrainingLoopConfig``) and the autoencoder's."""

    data: Path | list[Path] | None = option(None, "dataset folder(s) written by `tesseract4d datagen --resolution 128`, "
                                                  "trained as one set")
    heldout: Path | None = option(None, "held-out dataset folder for the fidelity gate (e.g. seeds >= 100000)")
    out: Path = option(Path("runs/autoencoder"), "the run folder (checkpoints, logs, autoencoder/)")
    init: Path | None = option(None, "start from this exported autoencoder (fine-tuning) instead of random weights")
    decoder_only: bool = option(False, "with init: train only the decoder (encoder and latent statistics frozen), so "
                                       "a latent model trained on them keeps working")
    frame_stride: int = option(1, "train on every k-th frame of each episode")
    preset: str = option("ae-f8c32", "autoencoder architecture (model/autoencoder.py)")
    camera: str | None = option(None, "camera of the dataset (default: its first)")
    max_steps: int | str = option(20000, "optimiser steps; the cosine learning-rate decay ends here; 'auto' (with "
                                         "max_minutes) fits it to the time budget")
    ckpt_every: int = option(1000, "write a checkpoint, export RUN/autoencoder and measure its fidelity gate every "
                                   "N steps (0: only at the end)")
    lr: float = option(4e-4, "peak learning rate")
    warmup_steps: int = option(300, "linear learning-rate warm-up steps")
    batch_size: int = option(8, "frames per step")
    weight_decay: float = option(0.0, "AdamW weight decay")
    ema_decay: float = option(0.999, "decay of the exported EMA weights")
    grad_clip: float = option(1.0, "gradient-norm clip")
    rgb_weight: float = option(1.0, "loss weight of colour")
    depth_weight: float = option(3.0, "loss weight of depth")
    normal_weight: float = option(2.0, "loss weight of normals")
    grad_weight: float = option(1.0, "loss weight of the depth and normal gradient differences")
    object_weight: float = option(5.0, "loss weight of robot/object pixels relative to scenery")
    edge_weight: float = option(2.0, "added loss weight of depth-edge pixels")
    kl_weight: float = option(1e-4, "weight of the KL term")
    precision: str = precision_field()
    heldout_frames: int = option(96, "held-out frames in the fidelity gate")

    @property
    def data_folders(self) -> list[Path]:
        return folder_list(self.data)

    def to_dict(self) -> dict:
        return config_dict(self)


# --------------------------------------------------------------------------- data


@dataclass
class FrameSet:
    """Frames of a dataset folder, in model space, with their robot/object masks."""

    frames: torch.Tensor  # (N, 7, H, W) float16 model space
    masks: torch.Tensor  # (N, H, W) bool robot/object pixels
    episode_ids: list[str] = field(default_factory=list)

    def __len__(self) -> int:
        return int(self.frames.shape[0])

    @classmethod
    def load(cls, root: str | os.PathLike, *, height: int, width: int, model_space: ModelSpace,
             camera: str | None = None, frame_stride: int = 1, max_frames: int | None = None,
             progress: bool = False) -> "FrameSet":
        info = df.read_info(root)
        if (info.height, info.width) != (height, width):
            raise UserError(f"{root} holds {info.height}x{info.width} episodes but the autoencoder works at "
                            f"{height}x{width}; generate data with `tesseract4d datagen --resolution {height}` "
                            f"or pick a matching autoencoder preset")
        camera = camera or info.cameras[0]
        if camera not in info.cameras:
            raise UserError(f"{root} has no camera {camera!r}; it has {', '.join(info.cameras)}")
        files = df.list_episode_files(root)
        if not files:
            raise UserError(f"{root} holds no episodes; write some with `tesseract4d datagen --out {root}`")
        if progress:
            from tqdm import tqdm

            files = tqdm(files, desc=f"loading {Path(root).name}", unit="ep")
        frames, masks, ids = [], [], []
        for path in files:
            ep = df.read_episode(path, cameras=[camera], check=True)
            cam = ep.cameras[camera]
            if cam.segmentation is None:
                raise UserError(f"{path} has no segmentation; regenerate the dataset with `tesseract4d datagen` "
                                f"(the autoencoder weights robot and object pixels by it)")
            sel = slice(None, None, frame_stride)
            frames.append(model_space.encode(cam.rgb[sel], cam.depth_m[sel], cam.normal_cam[sel]).half())
            masks.append(torch.from_numpy(robot_object_mask(cam.segmentation[sel], cam.seg_id_to_name)))
            ids.extend([ep.episode_id] * len(masks[-1]))
        out = cls(torch.cat(frames), torch.cat(masks), ids)
        if max_frames is not None and len(out) > max_frames:
            keep = torch.linspace(0, len(out) - 1, max_frames).round().long()
            out = cls(out.frames[keep], out.masks[keep], [out.episode_ids[i] for i in keep.tolist()])
        return out

    @classmethod
    def concat(cls, sets: list["FrameSet"]) -> "FrameSet":
        if len(sets) == 1:
            return sets[0]
        return cls(torch.cat([s.frames for s in sets]), torch.cat([s.masks for s in sets]),
                   [i for s in sets for i in s.episode_ids])

    def batch(self, batch_size: int, generator: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
        """(b, 7, H, W) float32 frames and (b, H, W) masks at random indices."""
        idx = torch.randint(len(self), (batch_size,), generator=generator)
        return self.frames[idx].float(), self.masks[idx]


# --------------------------------------------------------------------------- loss


def _grad_xy(x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Forward differences of (n, c, H, W) along x and y: (n, c, H, W-1), (n, c, H-1, W)."""
    return x[..., :, 1:] - x[..., :, :-1], x[..., 1:, :] - x[..., :-1, :]


def pixel_weights(target: torch.Tensor, mask: torch.Tensor, cfg: AutoencoderTrainConfig) -> torch.Tensor:
    """(n, 1, H, W) loss weight per pixel: robot/object pixels and depth edges count more."""
    depth = target[:, channel_slices()["depth"]]  # (n, 1, H, W)
    gx, gy = _grad_xy(depth)
    edge = torch.zeros_like(depth)
    edge[..., :, 1:] = torch.maximum(edge[..., :, 1:], (gx.abs() > DEPTH_EDGE_THRESHOLD).float())
    edge[..., 1:, :] = torch.maximum(edge[..., 1:, :], (gy.abs() > DEPTH_EDGE_THRESHOLD).float())
    edge = F.max_pool2d(edge, 3, stride=1, padding=1)  # both sides of an edge
    return 1.0 + (cfg.object_weight - 1.0) * mask[:, None].float() + cfg.edge_weight * edge


def _gradient_error(pairs: list[tuple[torch.Tensor, torch.Tensor]], w: torch.Tensor) -> torch.Tensor:
    """Sum over (prediction, target) pairs of the weighted mean |forward difference error| along x and y."""
    total = 0.0
    for pred, target in pairs:
        for gp, gt in zip(_grad_xy(pred), _grad_xy(target)):
            total = total + _wmean((gp - gt).abs(), w)
    return total


def _wmean(err: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
    """Weighted mean of (n, c, h, w) errors with (n, 1, h, w) weights (cropped to match)."""
    w = w[..., : err.shape[-2], : err.shape[-1]]
    return (err.mean(dim=1, keepdim=True) * w).sum() / w.sum().clamp_min(1e-6)


def reconstruction_loss(pred: torch.Tensor, target: torch.Tensor, mask: torch.Tensor, kl: torch.Tensor,
                        cfg: AutoencoderTrainConfig) -> tuple[torch.Tensor, dict[str, float]]:
    """pred, target (n, 7, H, W) model space (pred before renormalisation); mask (n, H, W); kl (n,) summed
    over latent elements divided by their count. Returns the total and its terms."""
    s = channel_slices()
    pred, target = pred.float(), target.float()
    w = pixel_weights(target, mask, cfg)
    parts = {
        "rgb": _wmean((pred[:, s["rgb"]] - target[:, s["rgb"]]).abs(), w),
        "depth": _wmean((pred[:, s["depth"]] - target[:, s["depth"]]).abs(), w),
    }
    n_hat, n = pred[:, s["normal"]], target[:, s["normal"]]
    cos = F.cosine_similarity(n_hat, n, dim=1, eps=1e-6)[:, None]  # (n, 1, H, W)
    parts["normal"] = _wmean((n_hat - n).abs(), w) + _wmean(1.0 - cos, w)
    parts["grad"] = _gradient_error([(pred[:, s[k]], target[:, s[k]]) for k in ("depth", "normal")], w)
    parts["kl"] = kl.mean()
    total = (cfg.rgb_weight * parts["rgb"] + cfg.depth_weight * parts["depth"] + cfg.normal_weight * parts["normal"]
             + cfg.grad_weight * parts["grad"] + cfg.kl_weight * parts["kl"])
    return total, {k: float(v.detach()) for k, v in parts.items()}


# --------------------------------------------------------------------------- trainer


@torch.no_grad()
def measure_latent_stats(model: RGBDNAutoencoder, frames: torch.Tensor, chunk: int = 32) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-channel mean and std of the posterior means of ``frames`` (n, 7, H, W)."""
    z = torch.cat([model.posterior(frames[i:i + chunk].float()).mean for i in range(0, len(frames), chunk)])
    return z.mean(dim=(0, 2, 3)), z.std(dim=(0, 2, 3))  # (C,), (C,)


class AutoencoderTrainer:
    """Owns the autoencoder, its EMA, the optimiser, the frames and the loss.

    ``fidelity_fn(model) -> dict`` (given by the command line, from the evaluation floor) measures the
    exported autoencoder on held-out frames; its result is printed and stored as fidelity.json.
    """

    def __init__(self, cfg: AutoencoderTrainConfig, fidelity_fn: Callable[[RGBDNAutoencoder], dict] | None = None,
                 format_fn: Callable[[dict], str] | None = None):
        if not cfg.data_folders:
            raise UserError("--data is required: a dataset folder written by `tesseract4d datagen --resolution 128`")
        if cfg.frame_stride < 1:
            raise UserError(f"--frame-stride must be at least 1, got {cfg.frame_stride}")
        cfg.check_loop()
        if cfg.decoder_only and cfg.init is None:
            raise UserError("--decoder-only fine-tunes the decoder of an existing autoencoder: pass --init AE "
                            "(e.g. tesseract4d/checkpoints/v2/autoencoder)")
        self.cfg = cfg
        self.fidelity_fn = fidelity_fn
        self.format_fn = format_fn or (lambda d: json.dumps(d))
        self.out = Path(cfg.out)
        # The GPU when torch sees one, as the diffusion trainer (accelerate) does; CUDA_VISIBLE_DEVICES=
        # keeps a run on the CPU.
        self.device = torch.device("cuda" if torch.cuda.is_available() else "cpu")
        chosen = resolve_precision(cfg.precision, self.device.type)
        announce(chosen)
        self.precision = chosen.name
        self._check_run_folder()

        ae_cfg: AutoencoderConfig = get_autoencoder_preset(cfg.preset)
        torch.manual_seed(cfg.seed)
        self.model = RGBDNAutoencoder(ae_cfg)
        if cfg.init is not None and (cfg.decoder_only or not cfg.resume):
            self._load_init(cfg.init)  # on --resume of a decoder-only run too: it keeps the init's latent statistics
        self.model.to(self.device)
        for module in self.frozen_modules():
            module.requires_grad_(False)
        self.ema = EMA(self.model, cfg.ema_decay)
        self.optimizer = torch.optim.AdamW(self.trained_parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay,
                                           betas=(0.9, 0.99))
        self.frames = FrameSet.concat([
            FrameSet.load(folder, height=ae_cfg.height, width=ae_cfg.width, model_space=self.model.model_space,
                          camera=cfg.camera, frame_stride=cfg.frame_stride, progress=not cfg.quiet)
            for folder in cfg.data_folders])

        # Claimed once the inputs have loaded, so a mistake leaves nothing behind; the checkpoints
        # and export this trainer replaces then live only in a folder that is its own.
        claim_folder(self.out, "train-autoencoder", inputs=[*cfg.data_folders, cfg.heldout, cfg.init],
                     legacy_marker=CONFIG_FILE)
        self.step = 0
        self.elapsed_s = 0.0
        self.last_loss: float | None = None
        self.stopped_by: int | None = None  # the signal that stopped train(), if one did
        self._gate: dict = {}  # the fidelity gate of the newest export
        if cfg.resume:
            self.load_checkpoint()

    def _load_init(self, folder: Path) -> None:
        """Start from an exported autoencoder of the same preset (fine-tuning, e.g. on new scenes)."""
        from safetensors.torch import load_file

        saved = read_autoencoder_config(folder)
        mine = self.model.config
        if (saved.height, saved.width, saved.latent_shape) != (mine.height, mine.width, mine.latent_shape):
            raise UserError(f"--init {folder} is a {saved.height}x{saved.width} autoencoder with latents "
                            f"{tuple(saved.latent_shape)}, not preset {self.cfg.preset!r} "
                            f"({mine.height}x{mine.width}, {tuple(mine.latent_shape)}); pass the matching --preset")
        state = {k: v.float() for k, v in load_file(str(Path(folder) / WEIGHTS_FILE)).items()}
        try:
            self.model.load_state_dict(state)
        except RuntimeError as e:
            raise UserError(f"--init {folder} does not fit preset {self.cfg.preset!r} ({str(e).splitlines()[0]}); "
                            f"pass the preset it was trained with") from e
        if self.cfg.decoder_only:
            if saved.latent_mean is None or saved.latent_std is None:
                raise UserError(f"--init {folder} has no latent statistics; export it with `tesseract4d train-autoencoder` first")
            self.model.set_latent_stats(torch.tensor(saved.latent_mean), torch.tensor(saved.latent_std))

    def frozen_modules(self) -> list[torch.nn.Module]:
        """What --decoder-only keeps fixed: everything that maps frames to latents."""
        # autoencoder.ENCODER_PREFIXES names the same modules' weights.
        return [self.model.vae.encoder, self.model.vae.quant_conv] if self.cfg.decoder_only else []

    def trained_parameters(self) -> list[torch.nn.Parameter]:
        return [p for p in self.model.parameters() if p.requires_grad]

    def _check_run_folder(self) -> None:
        cfg_path = self.out / CONFIG_FILE
        if self.cfg.resume:
            if not list_checkpoints(self.out) or not cfg_path.is_file():
                raise UserError(f"--resume: {self.out} holds no autoencoder checkpoint (and {CONFIG_FILE}); "
                                f"start without --resume")
            saved = json.loads(cfg_path.read_text())
            if saved.get("preset") != self.cfg.preset:
                raise UserError(f"--resume: {self.out} trains preset {saved.get('preset')!r}, not {self.cfg.preset!r}; "
                                f"pass --preset {saved.get('preset')}")
            if saved.get("decoder_layers_per_block") is not None or saved.get("rgb_grad_weight", 0.0) != 0.0:
                raise UserError(f"--resume: {self.out} trains with a lighter decoder or an RGB gradient loss, which "
                                f"this tesseract4d no longer has; resume it with an older version, or start a new --out")
        elif self.out.exists() and any(self.out.iterdir()):
            raise UserError(f"{self.out} is not empty; continue it with --resume or choose a new --out")

    # ------------------------------------------------------------------ state
    def _write_checkpoint(self) -> Path:
        """RUN/checkpoint-XXXXXX of the current step (training/checkpoints.py)."""
        def write(tmp: Path) -> None:
            save_autoencoder(self.model, tmp / "model")
            save_autoencoder(self.ema.model, tmp / "model_ema")
            save_optimizer(self.optimizer, tmp)

        return write_checkpoint(self.out, self.step, {**loop_state(self), "precision": self.precision}, write,
                                keep=self.cfg.keep_checkpoints)

    def save_checkpoint(self) -> Path:
        """The checkpoint, and with it RUN/autoencoder and its fidelity gate (logged and shown)."""
        ckpt = self._write_checkpoint()
        self._gate = self._export()
        log = getattr(self, "run_log", None)
        if log is not None:
            log.scalars({f"fidelity/{k}": v for k, v in self._gate.items() if k != "step"}, self.step)
            log.say(f"step {self.step}: checkpoint + {self.out / EXPORT_DIR}\n{self.format_fn(self._gate)}")
        return ckpt

    def load_checkpoint(self) -> None:
        """Continue from the newest intact checkpoint (its step and, with ``--max-steps auto``, its schedule)."""
        from safetensors.torch import load_file

        run_config = json.loads((self.out / CONFIG_FILE).read_text())

        def load(ckpt: Path, state: dict) -> None:
            self.model.load_state_dict(load_file(str(ckpt / "model" / "model.safetensors")))
            self.ema.model.load_state_dict(load_file(str(ckpt / "model_ema" / "model.safetensors")))
            load_optimizer(self.optimizer, ckpt)
            # older checkpoints: the schedule from the run's config
            restore_loop_state(self, {"max_steps": run_config.get("max_steps"),
                                      "max_steps_fit": run_config.get("max_steps_fit"), **state})

        resume_newest(self.out, load)
        print(f"resumed {self.out} at step {self.step}", flush=True)

    def export(self) -> dict:
        """RUN/autoencoder of the current step with its fidelity gate (written once per step)."""
        if self._gate.get("step") != self.step:
            self._gate = self._export()
        return self._gate

    def write_config(self) -> None:
        write_config_file(self.out / CONFIG_FILE, self.cfg)

    def _export(self) -> dict:
        """Write RUN/autoencoder (EMA weights + latent statistics + fidelity.json) atomically; return the gate."""
        model = self.ema.model
        if not self.cfg.decoder_only:  # a frozen encoder keeps the init's statistics (set at load)
            g = torch.Generator().manual_seed(12345)
            idx = torch.randperm(len(self.frames), generator=g)[:LATENT_STATS_FRAMES]
            mean, std = measure_latent_stats(model, self.frames.frames[idx])
            model.set_latent_stats(mean, std)
        fidelity = self.fidelity_fn(model) if self.fidelity_fn is not None else {}
        fidelity = {"step": self.step, **fidelity}
        final = self.out / EXPORT_DIR
        tmp = self.out / f".{EXPORT_DIR}.tmp"
        shutil.rmtree(tmp, ignore_errors=True)
        save_autoencoder(model, tmp)
        (tmp / FIDELITY_FILE).write_text(json.dumps(fidelity, indent=2))
        if final.exists():
            shutil.rmtree(final)
        os.replace(tmp, final)
        return fidelity

    # ------------------------------------------------------------------ loop
    def train_step(self) -> dict[str, float]:
        cfg = self.cfg
        g = torch.Generator().manual_seed(cfg.seed * 1_000_003 + self.step)
        x, mask = self.frames.batch(cfg.batch_size, g)
        x, mask = x.to(self.device), mask.to(self.device)
        lr = learning_rate(self)
        set_learning_rate(self.optimizer, lr)
        self.model.train()
        for module in self.frozen_modules():
            module.eval()
        with torch.autocast(self.device.type, dtype=torch.bfloat16, enabled=self.precision == "bf16"):
            with torch.set_grad_enabled(not cfg.decoder_only):
                post = self.model.posterior(x)
            z = post.sample(generator=g)
            pred = self.model.decode_raw(z)
        kl = post.kl().float() / z[0].numel()  # (b,) per latent element
        loss, parts = reconstruction_loss(pred, x, mask, kl, cfg)
        self.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        grad_norm = torch.nn.utils.clip_grad_norm_(self.trained_parameters(), cfg.grad_clip)
        check_finite(float(loss.detach()), float(grad_norm), step=self.step + 1, run=self.out)
        self.optimizer.step()
        self.ema.update(self.model, self.step)
        self.step += 1
        self.last_loss = float(loss.detach())
        return {"loss": self.last_loss, "lr": lr, "grad_norm": float(grad_norm), **parts}

    def train(self) -> dict:
        """Train until max_steps or max_minutes, or a stop signal (training/loop.py); always ends with a
        checkpoint and RUN/autoencoder. Returns the last fidelity gate."""
        self.out.mkdir(parents=True, exist_ok=True)
        # Written on a resume too, so the folder says how the run continued (e.g. a longer --max-steps).
        self.write_config()
        print(f"autoencoder {self.cfg.preset}: {sum(p.numel() for p in self.model.parameters()) / 1e6:.2f} M params, "
              f"{len(self.frames)} training frames, {self.device.type}, precision {self.precision}, "
              f"{self.model.config.spatial_compression}x -> latent {self.model.config.latent_shape}")
        return run_loop(self, "train-autoencoder")


def load_heldout_frames(root: str | os.PathLike, model: RGBDNAutoencoder, count: int, camera: str | None = None) -> FrameSet:
    """Up to ``count`` evenly spread frames of a held-out dataset, for the fidelity gate."""
    return FrameSet.load(root, height=model.config.height, width=model.config.width, model_space=model.model_space,
                         camera=camera, max_frames=count)


__all__ = ["AutoencoderTrainConfig", "AutoencoderTrainer", "FrameSet", "reconstruction_loss"]
