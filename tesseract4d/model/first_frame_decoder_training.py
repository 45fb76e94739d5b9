"""Training of the first-frame decoder (``first_frame_decoder.py``) from a shipped autoencoder, on a CPU.

The encoder and the latent statistics are frozen (the latents stay the shipped ones); the first-frame
path is trained, and the shipped decoder's own weights too when ``decoder_lr`` > 0 (off by default: see
the field's comment). Each step decodes ``frames_per_clip`` frames of ``clips_per_step``
episodes from their latents, each clip's frame 0 given as the reference, and charges

    sum over pixels of w * (|rgb_hat - rgb| + depth_weight |d_hat - d| + normal_weight (|n_hat - n| + 1 - cos))
    / sum of w
  + moved_loss * the same error's plain mean over the moved object's pixels
  + permanence_loss * mean over (object, frame) of mean over the object's true pixels of
        max(0, |rgb_hat - rgb| - permanence_margin) / OBJECT_COLOUR_TOL      (RGB distance, 0-255)
        (the pixels an object left since frame 0 count as one more object of each frame)

with ``w = 1 + (object_weight - 1) * robot_or_object + contact_weight * contact + moved_weight * moved``
from the dataset's segmentation: *contact* pixels lie within ``CONTACT_PX`` of both the robot and a
scene object (the gripper at a cube), *moved* pixels are those of scene objects that move more than
``MOVED_M`` during the episode (the object the instruction moves, from the stored object poses).

The last term is the permanence test made differentiable (``believability.objects_present`` counts an
object present where its pixels lie within ``OBJECT_COLOUR_TOL`` of its true colours): a hinge on each
true object pixel's colour distance, averaged per object and frame, so a lost 10-pixel cube costs as much
as a lost large one, and a pixel already well inside the tolerance (``permanence_margin``) costs nothing,
whereas the L1 terms spend most of their weight on the table's grain. A decoder that copies the given
frame can also fail the other way, drawing a moved object where it stood in frame 0 as well (a second copy,
which fails "found whole"): the pixels that showed an object in frame 0 and show none now (*vacated*) are
charged by the same hinge as one more object.

*Predicted latents* (``predicted_latents``, a cache written by ``predicted_latents.py``): a decoder trained only
on the truth's latents meets the transformer's at prediction time (a smeared object, the arm elsewhere), and its
copy gate then pastes frame 0's look where a predicted latent is ambiguous. Each clip of a step takes its latents
from the cache with probability ``predicted_share`` (one of its noise seeds), its target still the truth's frames.
Where the prediction is not what the truth shows (the arm or an object elsewhere), a truth target would teach the
decoder to hallucinate or blur, so a predicted clip is charged only where its latent *agrees* with the truth's:
the latent cells whose RMS difference over channels (normalised latents) is below ``agree_tol``, each cell its
``f`` × ``f`` pixels; elsewhere every term is weighted by ``disagree_weight`` (0: not charged). There the
lost-object hinge counts only an object's agreeing pixels, and the vacated pixels only where they agree. Measured
on the 120 training clips with the default ``v2-2step`` (two noise seeds, frames 1-15): cells whose truth stays
within 0.3 of frame 0 agree at 0.75 in 99.3 %, cells whose truth changes by more than 1.0 (the arm, a moved
object) in 54 %; a changed cell that agrees is closer to the truth than the truth is to frame 0.

Run folder::

    RUN/ff_train_config.json       the resolved FirstFrameTrainConfig
    RUN/latents.pt                 the training clips' latents (the frozen encoder's; reused on resume)
    RUN/state.pt                   trained weights, optimiser, step, loss log (written every ckpt_every steps)
    RUN/autoencoder/               the exported autoencoder (load_autoencoder builds a FirstFrameAutoencoder)

Everything random in a step comes from a generator seeded by (seed, step), so a resumed run continues
exactly. It trains on a CUDA GPU when one is visible (the clips stay in host memory; each step's batch
moves), else on the CPU. ``python -m tesseract4d.model.first_frame_decoder_training --help`` runs it.
"""

from __future__ import annotations

import argparse
import json
import os
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from tesseract4d import dataset_format as df
from tesseract4d.configs import config_dict, folder_list
from tesseract4d.errors import UserError
from tesseract4d.object_colours import MIN_OBJECT_PIXELS, OBJECT_COLOUR_TOL, dilate
from tesseract4d.segments import robot_object_mask, scene_object_ids
from tesseract4d.model.model_space import channel_slices
from tesseract4d.model.autoencoder import save_autoencoder
from tesseract4d.model.autoencoder_loading import load_autoencoder
from tesseract4d.model.first_frame_decoder import INJECTIONS, from_autoencoder
from tesseract4d.model.predicted_latents import load_predicted_latents
from tesseract4d.outputs import claim_folder
from tesseract4d.precision import resolve_precision
from tesseract4d.training.schedule import lr_factor

CONFIG_FILE = "ff_train_config.json"
STATE_FILE = "state.pt"
LATENTS_FILE = "latents.pt"
EXPORT_DIR = "autoencoder"
CONTACT_PX = 3  # a pixel within this many pixels of both the robot and a scene object is contact
MOVED_M = 0.01  # a scene object whose position leaves its start by more than this in the episode moved


@dataclass
class FirstFrameTrainConfig:
    """Options of the first-frame decoder's training."""

    data: list[Path] = field(default_factory=list)  # dataset folders (segmentation and object poses stored)
    out: Path = Path("runs/first_frame_decoder")
    # The shipped autoencoder whose latents are kept; a first-frame autoencoder of ``injection`` continues its path.
    init: Path = Path("tesseract4d/checkpoints/v2/autoencoder")
    injection: str = "attention"  # one of first_frame_decoder.INJECTIONS
    camera: str | None = None
    max_steps: int = 300
    clips_per_step: int = 2
    frames_per_clip: int = 4  # decoded frames per clip and step, drawn from frames min_frame.. of the episode
    min_frame: int = 1  # 0: frame 0 too (its latent is the reference's own: the path can learn to copy there)
    lr: float = 1e-3  # the first-frame path's (new, zero-output) weights
    # The shipped decoder's weights (0: frozen). Fine-tuned at 2e-4 they drifted (the online loss on the
    # training batches rose 15 % above the shipped decoder's on the same batches within 100 steps); at 2e-5
    # the training loss fell 10 % but held-out permanence fell from 0.784 to 0.758 (tabletop), the same with
    # the first-frame path held at zero: so they stay frozen by default (docs/research/first_frame_decoder.md).
    decoder_lr: float = 0.0
    warmup_steps: int = 10
    min_lr_ratio: float = 0.1
    grad_clip: float = 1.0
    depth_weight: float = 3.0
    normal_weight: float = 2.0
    object_weight: float = 5.0
    contact_weight: float = 5.0
    moved_weight: float = 10.0
    moved_loss: float = 1.0
    # Weight of the lost-object hinge (module docstring; 0: off) and its margin (RGB distance, 0-255).
    permanence_loss: float = 0.0
    permanence_margin: float = OBJECT_COLOUR_TOL / 2
    precision: str = "auto"
    ckpt_every: int = 20
    # Stop with a checkpoint and the export after this many minutes of this invocation (the schedule still
    # ends at max_steps, so resuming goes on from there); None: run to max_steps.
    max_minutes: float | None = None
    seed: int = 0
    # A cache of the default model's predicted latents of the same episodes (predicted_latents.py; None: off),
    # the share of clips that take their latents from it, the agreement tolerance (RMS over channels of the
    # normalised latents' difference per cell) and the weight of the cells beyond it (module docstring).
    predicted_latents: Path | None = None
    predicted_share: float = 0.5
    agree_tol: float = 0.75
    disagree_weight: float = 0.0

    def to_dict(self) -> dict:
        return config_dict(self)


@dataclass
class Clips:
    """Training clips: model-space frames, latents and per-pixel region masks."""

    frames: torch.Tensor  # (E, T, 7, H, W) float16 model space
    latents: torch.Tensor  # (E, T, C, h, w) float32 normalised latents of the frozen encoder
    regions: torch.Tensor  # (E, T, 3, H, W) bool: robot_or_object, contact, moved
    episode_ids: list[str]
    objects: torch.Tensor  # (E, T, H, W) uint8: k > 0 on the k-th scene object's true pixels, 0 elsewhere
    predicted: torch.Tensor | None = None  # (E, S, T, C, h, w) float16 predicted latents, S noise seeds


def episode_regions(cam: df.CameraFrames, object_poses: dict[str, np.ndarray]) -> np.ndarray:
    """(T, 3, H, W) bool: robot-or-object pixels, contact pixels, moved-object pixels (module docstring)."""
    seg = np.asarray(cam.segmentation)
    names = cam.seg_id_to_name
    robot_or_object = robot_object_mask(seg, names)
    objects = scene_object_ids(names)
    object_px = np.isin(seg, np.asarray(objects, seg.dtype))
    robot_px = np.isin(seg, np.asarray([i for i, n in names.items() if str(n).startswith("panda_")] or [-1], seg.dtype))
    contact = dilate(robot_px, CONTACT_PX) & dilate(object_px, CONTACT_PX)
    moved_ids = []
    for i in objects:
        pose = object_poses.get(names[i])
        if pose is not None and float(np.linalg.norm(pose[:, :3] - pose[:1, :3], axis=1).max()) > MOVED_M:
            moved_ids.append(i)
    moved = dilate(np.isin(seg, np.asarray(moved_ids or [-1], seg.dtype)), 1)
    return np.stack([robot_or_object, contact, moved], axis=1)


def episode_objects(cam: df.CameraFrames) -> np.ndarray:
    """(T, H, W) uint8: k on the pixels of the episode's k-th scene object (k = 1, 2, ...), 0 elsewhere."""
    seg = np.asarray(cam.segmentation)
    out = np.zeros(seg.shape, np.uint8)
    for k, oid in enumerate(scene_object_ids(cam.seg_id_to_name)[:255], start=1):
        out[seg == oid] = k
    return out


def load_clips(folders: list[Path], model, camera: str | None = None, cache: Path | None = None) -> Clips:
    """Every episode of ``folders`` with its latents (from ``cache`` when it holds these episodes)."""
    files = [f for folder in folders for f in df.list_episode_files(folder)]
    if not files:
        raise UserError(f"{', '.join(map(str, folders))} hold no episodes; write some with `tesseract4d datagen`")
    frames, regions, objects, ids = [], [], [], []
    for path in files:
        ep = df.read_episode(path)
        cam = ep.cameras[camera or next(iter(ep.cameras))]
        if cam.segmentation is None:
            raise UserError(f"{path} has no segmentation; regenerate it with `tesseract4d datagen`")
        frames.append(model.model_space.encode(cam.rgb, cam.depth_m, cam.normal_cam).half())
        regions.append(torch.from_numpy(episode_regions(cam, ep.object_poses)))
        objects.append(torch.from_numpy(episode_objects(cam)))
        ids.append(ep.episode_id)
    lengths = {len(f) for f in frames}
    if len(lengths) != 1:
        raise UserError(f"episodes of different lengths {sorted(lengths)}; train on datasets of one --frames")
    x = torch.stack(frames)  # (E, T, 7, H, W)
    if cache is not None and cache.is_file():
        saved = torch.load(cache, map_location="cpu")
        if saved["episode_ids"] == ids:
            return Clips(x, saved["latents"], torch.stack(regions), ids, torch.stack(objects))
    with torch.no_grad():
        z = torch.stack([model.encode(f.float()).cpu() for f in x])  # (E, T, C, h, w), fp32 as the pipeline encodes
    if cache is not None:
        torch.save({"episode_ids": ids, "latents": z}, cache)
    return Clips(x, z, torch.stack(regions), ids, torch.stack(objects))


def latent_agreement(z_pred: torch.Tensor, z_true: torch.Tensor, tol: float, factor: int) -> torch.Tensor:
    """(n, 1, h * factor, w * factor) float, 1 on the pixels of the latent cells where the predicted and the true
    normalised latents (n, C, h, w) differ by less than ``tol`` (RMS over channels), else 0."""
    rms = (z_pred.float() - z_true.float()).square().mean(1, keepdim=True).sqrt()  # (n, 1, h, w)
    return F.interpolate((rms < tol).float(), scale_factor=factor, mode="nearest")


def draw_batch(clips: Clips, eps: torch.Tensor, ts: torch.Tensor, cfg: FirstFrameTrainConfig, g: torch.Generator,
               factor: int) -> tuple[torch.Tensor, torch.Tensor, list[bool]]:
    """The latents of a step's clips ``eps`` at frames ``ts`` (k, f): (k f, C, h, w), each clip's from the
    predicted cache with probability ``cfg.predicted_share`` (one noise seed at random, from ``g``), else the
    truth's; the pixel weights (k f, 1, H, W) of :func:`latent_agreement` (1 on a truth clip, ``disagree_weight``
    beyond the agreeing cells of a predicted one); and which clips were predicted."""
    zs, weights, predicted = [], [], []
    for e, t in zip(eps, ts):
        z_true = clips.latents[e, t].float()  # (f, C, h, w)
        use = clips.predicted is not None and float(torch.rand((), generator=g)) < cfg.predicted_share
        if use:
            s = int(torch.randint(clips.predicted.shape[1], (), generator=g))
            z = clips.predicted[e, s, t].float()
            agree = latent_agreement(z, z_true, cfg.agree_tol, factor)
            weights.append(agree + cfg.disagree_weight * (1.0 - agree))
        else:
            z = z_true
            h, w = z.shape[-2:]
            weights.append(torch.ones(len(t), 1, h * factor, w * factor))
        zs.append(z)
        predicted.append(use)
    return torch.cat(zs), torch.cat(weights), predicted


def lost_object_loss(pred_rgb: torch.Tensor, target_rgb: torch.Tensor, objects: torch.Tensor,
                     margin: float, vacated: torch.Tensor | None = None) -> torch.Tensor:
    """The permanence hinge (module docstring). pred_rgb, target_rgb (n, 3, H, W) model space ([-1, 1]);
    objects (n, H, W) uint8 object index (0: none); vacated (n, H, W) bool, the pixels an object left
    since frame 0 (one more object of each frame), or None. Mean over the (object, frame) pairs that show
    at least ``MIN_OBJECT_PIXELS`` of the object; 0 when there is none."""
    dist = (pred_rgb.float() - target_rgb.float()).square().sum(1).add(1e-6).sqrt() * 127.5  # (n, H, W), 0-255
    hinge = F.relu(dist - margin) / OBJECT_COLOUR_TOL
    k = int(objects.max())
    if k == 0 and (vacated is None or not vacated.any()):
        return hinge.sum() * 0.0
    onehot = F.one_hot(objects.long(), k + 1)[..., 1:].permute(0, 3, 1, 2).float()  # (n, k, H, W)
    if vacated is not None:
        onehot = torch.cat([onehot, vacated[:, None].float()], dim=1)  # (n, k + 1, H, W)
    count = onehot.sum((2, 3))  # (n, k)
    per_object = (onehot * hinge[:, None]).sum((2, 3)) / count.clamp_min(1.0)
    judged = count >= MIN_OBJECT_PIXELS
    return per_object[judged].sum() / judged.sum().clamp_min(1)


def decoder_loss(pred: torch.Tensor, target: torch.Tensor, regions: torch.Tensor,
                 cfg: FirstFrameTrainConfig, objects: torch.Tensor | None = None,
                 objects0: torch.Tensor | None = None,
                 pixel_weight: torch.Tensor | None = None) -> tuple[torch.Tensor, dict[str, float]]:
    """pred, target (n, 7, H, W) model space (pred before renormalisation); regions (n, 3, H, W) bool
    (robot_or_object, contact, moved); objects, objects0 (n, H, W) uint8 object index of each frame and of
    its clip's frame 0 (objects needed when ``cfg.permanence_loss`` > 0; objects0 adds the vacated pixels);
    pixel_weight (n, 1, H, W) in [0, 1] (:func:`draw_batch`; None: 1): every term's weight, and the hinge
    counts only pixels whose weight is at least 0.5. Returns the total and its terms (module docstring)."""
    s = channel_slices()
    pred, target = pred.float(), target.float()
    n_hat, n = pred[:, s["normal"]], target[:, s["normal"]]
    cos = F.cosine_similarity(n_hat, n, dim=1, eps=1e-6)[:, None]  # (n, 1, H, W)
    err = ((pred[:, s["rgb"]] - target[:, s["rgb"]]).abs().mean(1, keepdim=True)
           + cfg.depth_weight * (pred[:, s["depth"]] - target[:, s["depth"]]).abs()
           + cfg.normal_weight * ((n_hat - n).abs().mean(1, keepdim=True) + 1.0 - cos))  # (n, 1, H, W)
    r = regions.float()
    w = 1.0 + (cfg.object_weight - 1.0) * r[:, 0:1] + cfg.contact_weight * r[:, 1:2] + cfg.moved_weight * r[:, 2:3]
    if pixel_weight is not None:
        w = w * pixel_weight
    weighted = (err * w).sum() / w.sum().clamp_min(1e-6)
    moved = r[:, 2:3] if pixel_weight is None else r[:, 2:3] * pixel_weight
    moved_term = (err * moved).sum() / moved.sum().clamp_min(1.0)
    total = weighted + cfg.moved_loss * moved_term
    parts = {"weighted": float(weighted.detach()), "moved": float(moved_term.detach())}
    if cfg.permanence_loss > 0:
        if objects is None:
            raise ValueError("permanence_loss > 0 needs the clips' object masks")
        vacated = (objects0 > 0) & (objects == 0) if objects0 is not None else None
        if pixel_weight is not None:
            charged = pixel_weight[:, 0] >= 0.5  # (n, H, W)
            objects = objects * charged
            vacated = vacated & charged if vacated is not None else None
        lost = lost_object_loss(pred[:, s["rgb"]], target[:, s["rgb"]], objects, cfg.permanence_margin, vacated)
        total = total + cfg.permanence_loss * lost
        parts["lost"] = float(lost.detach())
    return total, parts


def trained_parameters(model) -> tuple[list[torch.nn.Parameter], list[torch.nn.Parameter]]:
    """(the shipped decoder's parameters, the first-frame path's); the encoder and quant_conv stay frozen."""
    decoder = list(model.vae.decoder.parameters())
    if model.vae.post_quant_conv is not None:
        decoder += list(model.vae.post_quant_conv.parameters())
    return decoder, list(model.first_frame.parameters())


def train(cfg: FirstFrameTrainConfig, log=print) -> Path:
    """Train (or resume) into ``cfg.out``; returns the exported autoencoder folder."""
    out = Path(cfg.out)
    # A folder holding anything but this trainer's own run is refused before its state is read or written.
    inputs = [cfg.init, *folder_list(cfg.data)] + ([cfg.predicted_latents] if cfg.predicted_latents is not None else [])
    claim_folder(out, "first-frame-decoder", inputs=inputs, legacy_marker=CONFIG_FILE)
    (out / CONFIG_FILE).write_text(json.dumps(cfg.to_dict(), indent=2))
    model = from_autoencoder(load_autoencoder(cfg.init), cfg.injection)
    device = torch.device("cuda" if torch.cuda.is_available() else "cpu")
    model.to(device)
    model.requires_grad_(False)
    decoder_params, path_params = trained_parameters(model)
    params = decoder_params + path_params
    for p in params:
        p.requires_grad_(True)
    clips = load_clips(folder_list(cfg.data), model, cfg.camera, out / LATENTS_FILE)
    if cfg.predicted_latents is not None:
        clips.predicted = load_predicted_latents(cfg.predicted_latents, clips.episode_ids)
        if tuple(clips.predicted.shape[3:]) != tuple(clips.latents.shape[2:]) or clips.predicted.shape[2] != clips.latents.shape[1]:
            raise UserError(f"{cfg.predicted_latents} holds latents {tuple(clips.predicted.shape[2:])}, the training "
                            f"clips {tuple(clips.latents.shape[1:])}: sample it with this autoencoder's checkpoint")
    factor = clips.frames.shape[-1] // clips.latents.shape[-1]
    bf16 = resolve_precision(cfg.precision, device.type).bf16
    opt = torch.optim.AdamW([{"params": decoder_params, "peak_lr": cfg.decoder_lr},
                             {"params": path_params, "peak_lr": cfg.lr}], lr=cfg.lr, weight_decay=0.0)
    step, history = 0, []
    if (out / STATE_FILE).is_file():
        state = torch.load(out / STATE_FILE, weights_only=False, map_location=device)  # written by this module (numpy scalars in its history)
        model.load_state_dict(state["model"])
        opt.load_state_dict(state["optimizer"])
        for group, peak in zip(opt.param_groups, (cfg.decoder_lr, cfg.lr)):
            group["peak_lr"] = peak  # this invocation's rates (a run may be continued with others)
        step, history = state["step"], state["history"]
        log(f"resumed at step {step}")
    E, T = clips.frames.shape[:2]
    log(f"{E} clips of {T} frames; injection {cfg.injection}; {device.type}; bf16 {bf16}; "
        f"{sum(p.numel() for p in params) / 1e6:.2f} M trained parameters")
    model.train()

    def save():
        tmp = out / (STATE_FILE + ".tmp")
        torch.save({"model": model.state_dict(), "optimizer": opt.state_dict(), "step": step, "history": history}, tmp)
        os.replace(tmp, out / STATE_FILE)

    t0, step0 = time.time(), step
    while step < cfg.max_steps:
        g = torch.Generator().manual_seed(cfg.seed * 1_000_003 + step)
        eps = torch.randint(E, (cfg.clips_per_step,), generator=g)
        ts = torch.stack([torch.randperm(T - cfg.min_frame, generator=g)[:cfg.frames_per_clip] + cfg.min_frame
                          for _ in eps])  # (k, f)
        z, pixel_weight, predicted = draw_batch(clips, eps, ts, cfg, g, factor)  # (k f, C, h, w), (k f, 1, H, W)
        z, pixel_weight = z.to(device), pixel_weight.to(device)
        target = torch.cat([clips.frames[e, t] for e, t in zip(eps, ts)]).to(device).float()  # (k f, 7, H, W)
        regions = torch.cat([clips.regions[e, t] for e, t in zip(eps, ts)]).to(device)
        objects = torch.cat([clips.objects[e, t] for e, t in zip(eps, ts)]).to(device)  # (k f, H, W)
        objects0 = clips.objects[eps, 0].repeat_interleave(cfg.frames_per_clip, dim=0).to(device)  # (k f, H, W)
        first = clips.frames[eps, 0].to(device).float()  # (k, 7, H, W)
        for group in opt.param_groups:
            group["lr"] = lr_factor(step, cfg) * group["peak_lr"]
        with torch.autocast(device.type, dtype=torch.bfloat16, enabled=bf16):
            reference = model.reference_features(first)
            reference = [r.repeat_interleave(cfg.frames_per_clip, dim=0) for r in reference]
            pred = model.decode_raw_with_reference(z * model.latent_std + model.latent_mean, reference)
        loss, parts = decoder_loss(pred, target, regions, cfg, objects, objects0,
                                   pixel_weight if any(predicted) else None)
        parts["predicted"] = float(sum(predicted))
        opt.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(params, cfg.grad_clip)
        opt.step()
        step += 1
        history.append({"step": step, "loss": float(loss.detach()), **parts, "seconds": time.time() - t0})
        if step % 5 == 0:
            terms = " ".join(f"{k} {v:.4f}" for k, v in parts.items())
            log(f"step {step} loss {history[-1]['loss']:.4f} {terms} ({(time.time() - t0) / max(1, step - step0):.1f} s/step)")
        if step % cfg.ckpt_every == 0 or step == cfg.max_steps:
            save()
        if cfg.max_minutes is not None and time.time() - t0 > 60 * cfg.max_minutes:
            save()
            log(f"stopped at step {step} after {cfg.max_minutes} minutes")
            break
    model.eval().cpu()
    export = out / EXPORT_DIR
    save_autoencoder(model, export)
    return export


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description="Train the first-frame decoder from a shipped autoencoder (CPU).")
    p.add_argument("--data", type=Path, nargs="+", required=True, help="dataset folders with segmentation")
    p.add_argument("--out", type=Path, required=True, help="run folder (resumed if it holds a state)")
    p.add_argument("--init", type=Path, default=FirstFrameTrainConfig.init,
                   help="the autoencoder whose latents are kept (a first-frame one of --injection: its path trains on)")
    p.add_argument("--injection", choices=INJECTIONS, default=FirstFrameTrainConfig.injection)
    p.add_argument("--max-steps", type=int, default=FirstFrameTrainConfig.max_steps)
    p.add_argument("--ckpt-every", type=int, default=FirstFrameTrainConfig.ckpt_every)
    p.add_argument("--max-minutes", type=float, default=None,
                   help="stop with a checkpoint and the export after this many minutes (resume goes on)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--clips-per-step", type=int, default=FirstFrameTrainConfig.clips_per_step,
                   help="episodes per step (a GPU takes 16 or more)")
    p.add_argument("--frames-per-clip", type=int, default=FirstFrameTrainConfig.frames_per_clip,
                   help="decoded frames of each episode per step")
    p.add_argument("--min-frame", type=int, default=FirstFrameTrainConfig.min_frame,
                   help="first frame index drawn for training (0 includes the given frame itself)")
    p.add_argument("--lr", type=float, default=FirstFrameTrainConfig.lr,
                   help="the first-frame path's learning rate (0: the path stays zero, a decoder-only fine-tune)")
    p.add_argument("--decoder-lr", type=float, default=FirstFrameTrainConfig.decoder_lr,
                   help="the shipped decoder's learning rate (0: frozen)")
    p.add_argument("--permanence-loss", type=float, default=FirstFrameTrainConfig.permanence_loss,
                   help="weight of the lost-object colour hinge (0: off)")
    p.add_argument("--predicted-latents", type=Path, default=None,
                   help="a cache of the default model's predicted latents of the same episodes "
                        "(python -m tesseract4d.model.predicted_latents), mixed with the truth's")
    p.add_argument("--predicted-share", type=float, default=FirstFrameTrainConfig.predicted_share,
                   help="share of clips that take their latents from --predicted-latents")
    a = p.parse_args(argv)
    cfg = FirstFrameTrainConfig(data=a.data, out=a.out, init=a.init, injection=a.injection,
                                max_steps=a.max_steps, ckpt_every=a.ckpt_every, seed=a.seed, lr=a.lr,
                                decoder_lr=a.decoder_lr, min_frame=a.min_frame,
                                permanence_loss=a.permanence_loss, clips_per_step=a.clips_per_step,
                                frames_per_clip=a.frames_per_clip, max_minutes=a.max_minutes,
                                predicted_latents=a.predicted_latents, predicted_share=a.predicted_share)
    print(f"exported {train(cfg, log=lambda m: print(m, flush=True))}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
