"""Train the inverse dynamics model (or its behaviour-cloning twin) on datagen episodes.

Training pairs come from ground truth: frame i of an episode, the frame about G steps later
(G = episode steps / 15, the spacing of the 16-frame clips the world model predicts) and the
actions between them. Datasets written with ``--frames 0`` (every step) give a pair per step;
16-frame datasets give 15 per episode. The future cloud is corrupted as TesserAct does for
generated frames: ``noise_frac`` of its points get Gaussian noise of ``noise_m`` metres.
With ``predicted_futures`` (a world-model checkpoint) the world model also predicts clips from the
episodes' frames, and ``predicted_share`` of every batch pairs a true frame with the model's
predicted future instead (``predicted_pairs.py``), so the IDM learns to read generated frames.

    RUN/train_idm_config.json     the resolved IDMTrainConfig
    RUN/checkpoint/               model.safetensors + idm_config.json + optimizer + rng + trainer_state.json
    RUN/final/                    the trained IDM (load_idm), with its fit on the training pairs
"""

from __future__ import annotations

import dataclasses
import json
import os
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from tesseract4d import dataset_format as df
from tesseract4d.errors import UserError
from tesseract4d.policy.idm import (
    ARM_JOINTS, IDMConfig, InverseDynamics, clip_gap, encode_target, save_idm, sentence_embeddings,
)
from tesseract4d.policy.points import frame_points
from tesseract4d.stopping import StopSignals

@dataclass
class IDMTrainConfig:
    data: str = ""
    out: str = ""
    use_future: bool = True
    tasks: list[str] | None = None
    max_episodes_per_task: int = 0  # 0 = all
    camera: str | None = None
    steps: int = 2000
    batch_size: int = 32
    lr: float = 1e-3
    num_points: int = 512
    chunk_len: int = 8
    noise_frac: float = 0.2
    noise_m: float = 0.02
    gap_scales: tuple[float, ...] = (0.5, 1.0, 2.0)
    seed: int = 0
    ckpt_every: int = 500
    max_minutes: float | None = None
    resume: bool = False
    progress: bool = True
    # A world-model checkpoint whose predictions from the episodes' frames serve as futures too
    # (None: true futures only); the share of each batch taken from those pairs; clips per episode;
    # sampler steps (None: the checkpoint's own).
    predicted_futures: str | None = None
    predicted_share: float = 0.5
    predicted_starts: int = 3
    predicted_sample_steps: int | None = None


@dataclass
class PairSet:
    """Training pairs held in memory. F frames, P pairs, N points."""

    points: np.ndarray  # (F, N, 6) float16
    qpos: np.ndarray  # (F, D) float32
    text: np.ndarray  # (F, text_dim) float32, the episode's instruction embedding per frame
    now: np.ndarray  # (P,) frame index of the current frame
    next: np.ndarray  # (P,) frame index of the future frame
    target: np.ndarray  # (P, output_dim) raw targets (encode_target)
    control_mode: str
    action_dim: int
    camera: str
    resolution: tuple[int, int]
    episodes: list[str]
    predicted: np.ndarray | None = None  # (P,) bool: the future frame is the world model's prediction

    def __post_init__(self) -> None:
        if self.predicted is None:
            self.predicted = np.zeros(len(self.now), bool)


def pair_frames(frame_steps: np.ndarray, num_steps: int, gap_scales: tuple[float, ...] = (1.0,)) -> list[tuple[int, int]]:
    """(i, j) frame pairs: j is the kept frame nearest to s * G steps after frame i, for each s in
    ``gap_scales`` (G = num_steps / 15). Scales other than 1 teach the IDM to catch up with a future
    further ahead (a robot lagging its plan) or nearer; duplicates are dropped."""
    steps = np.asarray(frame_steps, np.int64)
    pairs = []
    for scale in gap_scales:
        gap = clip_gap(num_steps, scale)
        for i in range(len(steps) - 1):
            j = i + 1 + int(np.argmin(np.abs(steps[i + 1:] - (steps[i] + gap))))
            pairs.append((i, j))
    return list(dict.fromkeys(pairs))


def load_pairs(data: str | Path, *, camera: str | None, num_points: int, chunk_len: int, tasks: list[str] | None,
               max_episodes_per_task: int, text_encoder, seed: int = 0, progress: bool = True,
               gap_scales: tuple[float, ...] = (1.0,), predicted=None) -> PairSet:
    """The training pairs of a dataset; ``predicted`` (a ``PredictedFutures``) adds the pairs whose
    future is the world model's prediction. Their clouds are stored after the true frames'."""
    from tqdm import tqdm

    files = df.list_episode_files(data)
    if not files:
        raise UserError(f"{data} holds no episodes; generate some with `tesseract4d datagen --out {data}`")
    by_task: dict[str, list[Path]] = {}
    for f in files:
        by_task.setdefault(f.parent.name, []).append(f)
    if tasks:
        missing = [t for t in tasks if t not in by_task]
        if missing:
            raise UserError(f"{data} has no episodes of {', '.join(missing)}; it has {', '.join(sorted(by_task))}")
        by_task = {t: by_task[t] for t in tasks}
    chosen = [f for t in sorted(by_task) for f in (by_task[t][:max_episodes_per_task] if max_episodes_per_task else by_task[t])]
    points, qpos, text, now, nxt, target, names = [], [], [], [], [], [], []
    pred_points, pred_now, pred_target = [], [], []
    meta: dict = {}
    offset = 0
    for path in tqdm(chosen, desc="load pairs", unit="ep", disable=not progress):
        ep = df.read_episode(path, cameras=[camera] if camera else None, check=True)
        cam_name = camera or next(iter(ep.cameras))
        cam = ep.cameras[cam_name]
        info = dict(control_mode=ep.control_mode, action_dim=int(ep.actions.shape[1]), camera=cam_name,
                    resolution=tuple(int(x) for x in cam.rgb.shape[1:3]))
        if meta and info != meta:
            raise UserError(f"{path} differs from the other episodes ({info} vs {meta}); train on one camera/"
                            f"resolution/control mode")
        meta = info
        if len(ep.actions) == 0 or ep.num_frames < 2:
            continue
        rng = np.random.default_rng([seed, ep.seed, len(names)])
        for t in range(ep.num_frames):
            points.append(frame_points(cam.rgb[t], cam.depth_m[t], cam.K[t], cam.T_world_cam[t], num_points, rng)
                          .astype(np.float16))
        qpos.append(ep.qpos.astype(np.float32))
        emb = sentence_embeddings(text_encoder, [ep.instruction])[0].numpy()
        text.append(np.repeat(emb[None], ep.num_frames, 0))
        for i, j in pair_frames(ep.frame_steps, len(ep.actions), gap_scales):
            s0, s1 = int(ep.frame_steps[i]), int(ep.frame_steps[j])
            now.append(offset + i)
            nxt.append(offset + j)
            target.append(encode_target(ep.actions[s0:s1], ep.qpos[i], chunk_len))
        if predicted is not None:
            for pair in predicted.pairs(ep, cam_name, num_points, chunk_len, rng):
                pred_now.append(offset + pair.now)
                pred_points.append(pair.points.astype(np.float16))
                pred_target.append(pair.target)
        offset += ep.num_frames
        names.append(ep.episode_id)
    if not now:
        raise UserError(f"{data}: no episode has actions and two frames")
    qpos_all, text_all = np.concatenate(qpos), np.concatenate(text).astype(np.float32)
    # Predicted clouds go after the true frames; their qpos/text rows (never read: a pair reads the
    # current frame's) keep the frame arrays aligned.
    frames = len(points)
    pred_now_arr = np.asarray(pred_now, np.int64)
    return PairSet(np.stack(points + pred_points), np.concatenate([qpos_all, qpos_all[pred_now_arr]]),
                   np.concatenate([text_all, text_all[pred_now_arr]]),
                   np.asarray(now + pred_now), np.asarray(nxt + list(range(frames, frames + len(pred_now)))),
                   np.stack(target + pred_target), meta["control_mode"], meta["action_dim"],
                   meta["camera"], meta["resolution"], names,
                   predicted=np.arange(len(now) + len(pred_now)) >= len(now))


def make_batch(pairs: PairSet, idx: np.ndarray, rng: np.random.Generator, noise_frac: float, noise_m: float) -> dict:
    """Tensors of the pairs ``idx``; noise on the future cloud when noise_frac > 0."""
    now = pairs.points[pairs.now[idx]].astype(np.float32)  # (B, N, 6)
    nxt = pairs.points[pairs.next[idx]].astype(np.float32)
    if noise_frac > 0:
        hit = rng.random(nxt.shape[:2]) < noise_frac  # (B, N)
        nxt[..., :3] += hit[..., None] * rng.normal(0.0, noise_m, nxt[..., :3].shape).astype(np.float32)
    return {
        "points_now": torch.from_numpy(now), "points_next": torch.from_numpy(nxt),
        "text": torch.from_numpy(pairs.text[pairs.now[idx]]), "qpos": torch.from_numpy(pairs.qpos[pairs.now[idx]]),
        "target": torch.from_numpy(pairs.target[idx]),
    }


def fit_report(model: InverseDynamics, pairs: PairSet, max_pairs: int = 2048, predicted: bool = False) -> dict:
    """Errors of the model on (a fixed random subset of up to max_pairs of) the pairs with true
    futures (``predicted``: with the world model's), without noise: arm joint targets (rad, mean and
    95th percentile of |error|), gripper command sign agreement, steps a chunk spans (relative error)."""
    candidates = np.flatnonzero(pairs.predicted == predicted)
    if len(candidates) == 0:
        raise ValueError(f"no pairs with {'predicted' if predicted else 'true'} futures")
    idx = np.sort(candidates[np.random.default_rng(0).permutation(len(candidates))[:max_pairs]])
    errs, grip, steps_rel = [], [], []
    model.eval()
    with torch.no_grad():
        for start in range(0, len(idx), 256):
            b = make_batch(pairs, idx[start:start + 256], np.random.default_rng(0), 0.0, 0.0)
            out = model(b["points_now"], b["points_next"] if model.config.use_future else None, b["text"], b["qpos"])
            chunk, steps = model.decode(out, b["qpos"])
            true = b["target"]
            true_chunk, true_steps = model.decode((true - model.target_mean) / model.target_std, b["qpos"])
            errs.append((chunk[..., :ARM_JOINTS] - true_chunk[..., :ARM_JOINTS]).abs().reshape(-1).numpy())
            grip.append((torch.sign(chunk[..., ARM_JOINTS:]) == torch.sign(true_chunk[..., ARM_JOINTS:])).float().reshape(-1).numpy())
            steps_rel.append(((steps - true_steps).abs() / true_steps).numpy())
    e = np.concatenate(errs)
    return {"pairs": int(len(idx)), "arm_abs_err_rad_mean": float(e.mean()), "arm_abs_err_rad_p95": float(np.percentile(e, 95)),
            "gripper_sign_agreement": float(np.concatenate(grip).mean()),
            "steps_rel_err_mean": float(np.concatenate(steps_rel).mean())}


class IDMTrainer:
    def __init__(self, config: IDMTrainConfig, text_encoder=None):
        from tesseract4d.outputs import claim_folder, release_new_folder

        self.config = cfg = config
        if not cfg.data or not cfg.out:
            raise UserError("pass --data DATASET and --out RUN")
        self.out = Path(cfg.out)
        ckpt = self.out / "checkpoint"
        if ckpt.exists() and not cfg.resume:
            raise UserError(f"{self.out} already holds a checkpoint; pass --resume to continue, or choose a new --out")
        if cfg.resume and not ckpt.exists():
            raise UserError(f"--resume: {self.out} has no checkpoint to continue from")
        # A folder holding other files is refused (a run of its own is continued with --resume).
        fresh = claim_folder(self.out, "train-idm", inputs=[cfg.data], legacy_marker="train_idm_config.json")
        try:
            self._setup(cfg, ckpt, text_encoder)
        except BaseException:
            if fresh is not None:  # a mistake found while setting up leaves nothing behind
                release_new_folder(self.out, remove_folder=fresh)
            raise

    def _setup(self, cfg: IDMTrainConfig, ckpt: Path, text_encoder) -> None:
        from safetensors.torch import load_file

        from tesseract4d.model.text_encoder import TextEncoder

        self.text_encoder = text_encoder or TextEncoder("minilm", max_tokens=32)
        predicted = None
        if cfg.predicted_futures:
            from tesseract4d.policy.predicted_pairs import PredictedFutures

            if not cfg.use_future:
                raise UserError("--predicted-futures gives the IDM predicted future frames; behaviour cloning "
                                "(--no-future) reads no future: drop one of them")
            if not 0.0 < cfg.predicted_share <= 1.0:
                raise UserError(f"--predicted-share must be in (0, 1], got {cfg.predicted_share}")
            predicted = PredictedFutures(cfg.predicted_futures, starts=cfg.predicted_starts,
                                         sample_steps=cfg.predicted_sample_steps, sample_seed=cfg.seed)
        self.pairs = load_pairs(cfg.data, camera=cfg.camera, num_points=cfg.num_points, chunk_len=cfg.chunk_len,
                                tasks=cfg.tasks, max_episodes_per_task=cfg.max_episodes_per_task,
                                text_encoder=self.text_encoder, seed=cfg.seed, progress=cfg.progress,
                                gap_scales=tuple(cfg.gap_scales), predicted=predicted)
        p = self.pairs
        self.true_idx, self.pred_idx = np.flatnonzero(~p.predicted), np.flatnonzero(p.predicted)
        self.idm_config = IDMConfig(
            use_future=cfg.use_future, num_points=cfg.num_points, chunk_len=cfg.chunk_len, action_dim=p.action_dim,
            qpos_dim=int(p.qpos.shape[1]), text_dim=int(p.text.shape[1]), control_mode=p.control_mode, camera=p.camera,
            resolution=list(p.resolution),
            training={"data": str(cfg.data), "episodes": len(p.episodes), "pairs": int(len(p.now)), "steps": cfg.steps,
                      "batch_size": cfg.batch_size, "lr": cfg.lr, "noise_frac": cfg.noise_frac, "noise_m": cfg.noise_m, "gap_scales": list(cfg.gap_scales),
                      "tasks": sorted({e.split("/")[0] for e in p.episodes}), "seed": cfg.seed},
        )
        if predicted is not None:
            self.idm_config.training.update({"predicted_futures": predicted.describe(),
                                             "predicted_pairs": int(len(self.pred_idx)),
                                             "predicted_share": cfg.predicted_share})
        torch.manual_seed(cfg.seed)
        self.model = InverseDynamics(self.idm_config)
        std = p.target.std(0)
        self.model.target_mean.copy_(torch.from_numpy(p.target.mean(0)))
        self.model.target_std.copy_(torch.from_numpy(np.maximum(std, 1e-3)))
        self.model.qpos_mean.copy_(torch.from_numpy(p.qpos.mean(0)))
        self.model.qpos_std.copy_(torch.from_numpy(np.maximum(p.qpos.std(0), 1e-3)))
        self.optimizer = torch.optim.AdamW(self.model.parameters(), lr=cfg.lr, weight_decay=1e-4)
        self.step = 0
        self.stopped_by: int | None = None  # the signal that stopped train(), if one did
        self.last_loss = float("nan")
        if cfg.resume:
            from tesseract4d.model.trainer import load_optimizer, load_rng

            saved = json.loads((ckpt / "trainer_state.json").read_text())
            if saved["use_future"] != cfg.use_future:
                raise UserError(f"{self.out} trains use_future={saved['use_future']}; resume it the same way")
            self.model.load_state_dict(load_file(str(ckpt / "model.safetensors")))
            load_optimizer(self.optimizer, ckpt)
            load_rng(ckpt)
            self.step = int(saved["step"])
        df.atomic_write_text(self.out / "train_idm_config.json", json.dumps(dataclasses.asdict(cfg), indent=2))

    def lr_at(self, step: int) -> float:
        warm = 100
        if step < warm:
            return self.config.lr * (step + 1) / warm
        frac = (step - warm) / max(1, self.config.steps - warm)
        return self.config.lr * 0.5 * (1 + np.cos(np.pi * min(1.0, frac)))

    def train_step(self) -> float:
        cfg, p = self.config, self.pairs
        rng = np.random.default_rng([cfg.seed, self.step])  # per-step draws: resume is exact
        if len(self.pred_idx):  # predicted_share of the batch from the predicted pairs, the rest true
            n_pred = int(round(cfg.predicted_share * cfg.batch_size))
            idx = np.concatenate([rng.choice(self.pred_idx, n_pred), rng.choice(self.true_idx, cfg.batch_size - n_pred)])
        else:
            idx = rng.integers(0, len(p.now), cfg.batch_size)
        b = make_batch(p, idx, rng, cfg.noise_frac, cfg.noise_m)
        for g in self.optimizer.param_groups:
            g["lr"] = self.lr_at(self.step)
        self.model.train()
        out = self.model(b["points_now"], b["points_next"] if cfg.use_future else None, b["text"], b["qpos"])
        loss = torch.nn.functional.mse_loss(out, (b["target"] - self.model.target_mean) / self.model.target_std)
        self.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(self.model.parameters(), 1.0)
        self.optimizer.step()
        self.step += 1
        self.last_loss = float(loss.detach())
        return self.last_loss

    def save_checkpoint(self) -> Path:
        """RUN/checkpoint, written whole beside it and swapped in: a stop mid-write keeps the previous one."""
        import shutil

        from tesseract4d.model.trainer import save_optimizer, save_rng
        from tesseract4d.outputs import signals_held

        ckpt = self.out / "checkpoint"
        tmp = self.out / ".checkpoint.tmp"  # this run's own name; one a killed run left is replaced
        shutil.rmtree(tmp, ignore_errors=True)
        save_idm(self.model, tmp)
        save_optimizer(self.optimizer, tmp)
        save_rng(tmp)
        df.atomic_write_text(tmp / "trainer_state.json", json.dumps(
            {"step": self.step, "use_future": self.config.use_future, "last_loss": self.last_loss}))
        with signals_held():
            shutil.rmtree(ckpt, ignore_errors=True)
            os.replace(tmp, ckpt)
        return ckpt

    def train(self) -> Path:
        from tqdm import tqdm

        cfg = self.config
        t0 = time.monotonic()
        bar = tqdm(total=cfg.steps, initial=self.step, desc="train idm" if cfg.use_future else "train bc", unit="step",
                   disable=not cfg.progress)
        # Ctrl-C or SIGTERM stop after the step: the checkpoint and final/ are written, then the command
        # line exits 130 / 143 (stopped_by).
        with StopSignals() as stop:
            while self.step < cfg.steps and not stop.requested:
                loss = self.train_step()
                bar.update(1)
                bar.set_postfix_str(f"loss {loss:.4f}")
                if cfg.ckpt_every and self.step % cfg.ckpt_every == 0:
                    self.save_checkpoint()
                if cfg.max_minutes is not None and time.monotonic() - t0 > 60 * cfg.max_minutes:
                    break
            bar.close()
            if stop.requested:
                print(f"stopped at step {self.step}; saving a checkpoint and final/", flush=True)
            self.save_checkpoint()
            self.model.config.training.update({"trained_steps": self.step, "last_loss": self.last_loss,
                                               "minutes": round((time.monotonic() - t0) / 60, 2)})
            self.model.config.training["fit"] = fit_report(self.model, self.pairs)
            if len(self.pred_idx):
                self.model.config.training["fit_predicted"] = fit_report(self.model, self.pairs, predicted=True)
            final = save_idm(self.model, self.out / "final")
        self.stopped_by = stop.signum
        return final


