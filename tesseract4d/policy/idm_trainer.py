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
    RUN/checkpoint-XXXXXX/        model.safetensors + idm_config.json + optimizer + rng + trainer_state.json
    RUN/logs/                     TensorBoard (loss, lr, steps/s)
    RUN/final/                    the trained IDM (load_idm), with its fit on the training pairs

The loop (stop signals, schedule, checkpoints, logs) is the project's one training loop
(``tesseract4d/training/loop.py``).
"""

from __future__ import annotations

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
from tesseract4d.training.checkpoints import (list_checkpoints, load_optimizer, load_rng, resume_newest, save_optimizer,
                                              save_rng, write_checkpoint)
from tesseract4d.training.config import TrainingLoopConfig, option
from tesseract4d.training.loop import (check_finite, learning_rate, loop_state, restore_loop_state, run_loop,
                                       set_learning_rate, write_config_file)
from tesseract4d.outputs import claim_folder, release_new_folder
from tesseract4d.model.text_encoder import TextEncoder
from tesseract4d.policy.predicted_pairs import PredictedFutures

CONFIG_FILE = "train_idm_config.json"


@dataclass
class IDMTrainConfig(TrainingLoopConfig):
    """Options of `tesseract4d train-idm`: the loop's (``TrainingLoopConfig``) and the IDM's."""

    data: str = option("", "dataset folder of datagen episodes (with actions)")
    out: str = option("", "the run folder (checkpoints, logs, final/)")
    use_future: bool = option(True, "read the future frame (an inverse dynamics model); False: behaviour cloning")
    tasks: list[str] | None = option(None, "train on these tasks only (default: every task of the data)")
    max_episodes_per_task: int = option(0, "at most this many episodes per task (0: all)")
    camera: str | None = option(None, "camera of the dataset (default: its first)")
    max_steps: int | str = option(2000, "optimiser steps; the cosine learning-rate decay ends here; 'auto' (with "
                                        "max_minutes) fits it to the time budget")
    lr: float = option(1e-3, "peak learning rate")
    warmup_steps: int = option(100, "linear learning-rate warm-up steps")
    min_lr_ratio: float = option(0.0, "the learning rate at max_steps, as a share of the peak")
    batch_size: int = option(32, "pairs per step")
    num_points: int = option(512, "points per cloud")
    chunk_len: int = option(8, "actions per predicted chunk")
    noise_frac: float = option(0.2, "share of the future cloud's points given Gaussian noise (as on generated frames)")
    noise_m: float = option(0.02, "std of that noise (metres)")
    gap_scales: tuple[float, ...] = option((0.5, 1.0, 2.0), "future frames at these multiples of episode_steps/15 ahead")
    # A world-model checkpoint whose predictions from the episodes' frames serve as futures too
    # (None: true futures only); the share of each batch taken from those pairs; clips per episode;
    # sampler steps (None: the checkpoint's own).
    predicted_futures: str | None = option(None, "a world-model checkpoint whose predicted futures are trained on too")
    predicted_share: float = option(0.5, "share of each batch from the predicted futures' pairs")
    predicted_starts: int = option(3, "predicted clips per episode")
    predicted_sample_steps: int | None = option(None, "sampler steps per predicted clip (default: the checkpoint's)")


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
        self.config = self.cfg = cfg = config
        if not cfg.data or not cfg.out:
            raise UserError("pass --data DATASET and --out RUN")
        cfg.check_loop()
        self.out = Path(cfg.out)
        existing = list_checkpoints(self.out)
        if existing and not cfg.resume:
            raise UserError(f"{self.out} already holds a checkpoint; pass --resume to continue, or choose a new --out")
        if cfg.resume and not existing:
            raise UserError(f"--resume: {self.out} has no checkpoint to continue from")
        # A folder holding other files is refused (a run of its own is continued with --resume).
        fresh = claim_folder(self.out, "train-idm", inputs=[cfg.data], legacy_marker=CONFIG_FILE)
        try:
            self._setup(cfg, text_encoder)
        except BaseException:
            if fresh is not None:  # a mistake found while setting up leaves nothing behind
                release_new_folder(self.out, remove_folder=fresh)
            raise

    def _setup(self, cfg: IDMTrainConfig, text_encoder) -> None:
        from safetensors.torch import load_file

        self.text_encoder = text_encoder or TextEncoder("minilm", max_tokens=32)
        predicted = None
        if cfg.predicted_futures:
            if not cfg.use_future:
                raise UserError("--predicted-futures gives the IDM predicted future frames; behaviour cloning "
                                "(use_future=false) reads no future: drop one of them")
            if not 0.0 < cfg.predicted_share <= 1.0:
                raise UserError(f"--predicted-share must be in (0, 1], got {cfg.predicted_share}")
            predicted = PredictedFutures(cfg.predicted_futures, starts=cfg.predicted_starts,
                                         sample_steps=cfg.predicted_sample_steps, sample_seed=cfg.seed)
        self.pairs = load_pairs(cfg.data, camera=cfg.camera, num_points=cfg.num_points, chunk_len=cfg.chunk_len,
                                tasks=cfg.tasks, max_episodes_per_task=cfg.max_episodes_per_task,
                                text_encoder=self.text_encoder, seed=cfg.seed, progress=not cfg.quiet,
                                gap_scales=tuple(cfg.gap_scales), predicted=predicted)
        p = self.pairs
        self.true_idx, self.pred_idx = np.flatnonzero(~p.predicted), np.flatnonzero(p.predicted)
        self.idm_config = IDMConfig(
            use_future=cfg.use_future, num_points=cfg.num_points, chunk_len=cfg.chunk_len, action_dim=p.action_dim,
            qpos_dim=int(p.qpos.shape[1]), text_dim=int(p.text.shape[1]), control_mode=p.control_mode, camera=p.camera,
            resolution=list(p.resolution),
            training={"data": str(cfg.data), "episodes": len(p.episodes), "pairs": int(len(p.now)), "steps": cfg.max_steps,
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
        self.elapsed_s = 0.0
        self.stopped_by: int | None = None  # the signal that stopped train(), if one did
        self.last_loss = float("nan")
        if cfg.resume:
            def load(ckpt: Path, state: dict) -> None:
                if state["use_future"] != cfg.use_future:
                    raise UserError(f"{self.out} trains use_future={state['use_future']}; resume it the same way")
                self.model.load_state_dict(load_file(str(ckpt / "model.safetensors")))
                load_optimizer(self.optimizer, ckpt)
                load_rng(ckpt)
                restore_loop_state(self, state)

            resume_newest(self.out, load)
        self.write_config()

    def write_config(self) -> None:
        write_config_file(self.out / CONFIG_FILE, self.cfg)

    def train_step(self) -> float:
        cfg, p = self.config, self.pairs
        rng = np.random.default_rng([cfg.seed, self.step])  # per-step draws: resume is exact
        if len(self.pred_idx):  # predicted_share of the batch from the predicted pairs, the rest true
            n_pred = int(round(cfg.predicted_share * cfg.batch_size))
            idx = np.concatenate([rng.choice(self.pred_idx, n_pred), rng.choice(self.true_idx, cfg.batch_size - n_pred)])
        else:
            idx = rng.integers(0, len(p.now), cfg.batch_size)
        b = make_batch(p, idx, rng, cfg.noise_frac, cfg.noise_m)
        lr = learning_rate(self)
        set_learning_rate(self.optimizer, lr)
        self.model.train()
        out = self.model(b["points_now"], b["points_next"] if cfg.use_future else None, b["text"], b["qpos"])
        loss = torch.nn.functional.mse_loss(out, (b["target"] - self.model.target_mean) / self.model.target_std)
        self.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        grad_norm = torch.nn.utils.clip_grad_norm_(self.model.parameters(), 1.0)
        check_finite(float(loss.detach()), float(grad_norm), step=self.step + 1, run=self.out)
        self.optimizer.step()
        self.step += 1
        self.last_loss = float(loss.detach())
        return {"loss": self.last_loss, "lr": lr, "grad_norm": float(grad_norm)}

    def save_checkpoint(self) -> Path:
        """RUN/checkpoint-XXXXXX of the current step (training/checkpoints.py)."""
        def write(tmp: Path) -> None:
            save_idm(self.model, tmp)
            save_optimizer(self.optimizer, tmp)
            save_rng(tmp)

        return write_checkpoint(self.out, self.step, {**loop_state(self), "use_future": self.cfg.use_future}, write,
                                keep=self.cfg.keep_checkpoints)

    def export(self) -> Path:
        """RUN/final: the trained IDM with its fit on the training pairs."""
        self.model.config.training.update({"trained_steps": self.step, "last_loss": self.last_loss,
                                           "minutes": round(self.elapsed_s / 60, 2)})
        self.model.config.training["fit"] = fit_report(self.model, self.pairs)
        if len(self.pred_idx):
            self.model.config.training["fit_predicted"] = fit_report(self.model, self.pairs, predicted=True)
        return save_idm(self.model, self.out / "final")

    def train(self) -> Path:
        """Train until max_steps or max_minutes, or a stop signal (training/loop.py); always ends with a
        checkpoint and RUN/final. Returns that folder."""
        return run_loop(self, "train idm" if self.cfg.use_future else "train bc")
