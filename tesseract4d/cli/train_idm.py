"""Train the inverse dynamics model (current + future point clouds + instruction -> action chunk),
or with --no-future its behaviour-cloning twin (current point cloud + instruction -> action chunk).

  tesseract4d train-idm --data data/idm_train --out runs/idm --steps 1500
  tesseract4d train-idm --data data/idm_train --out runs/bc --steps 1500 --no-future
  tesseract4d train-idm --data data/idm_train --out runs/idm --steps 3000 --resume   # continue
  tesseract4d train-idm --data data/idm_train128 --out runs/idm_pred --steps 3000 \\
      --predicted-futures tesseract4d/checkpoints/v2-2step          # also learn from predicted frames

Training pairs are ground-truth frames of datagen episodes (best written with --frames 0, every
step) about episode_steps/15 steps apart and the actions between them. Writes
RUN/train_idm_config.json, RUN/checkpoint/ (resumable) and RUN/final/ (idm_config.json +
model.safetensors, with the fit on the training pairs in its config).

With --predicted-futures CHECKPOINT the world model predicts clips from frames of the training
episodes (--predicted-starts per episode, from steps 0, L/n, 2L/n, ... as the policy loop does),
and --predicted-share of every batch pairs a true frame with the predicted future and the true
actions, so the IDM learns to act on generated frames as the world-model arm gives them. The
dataset must be rendered at every step, at the checkpoint's camera and resolution (or a whole
factor of it).
"""

from __future__ import annotations

import argparse
import json

from tesseract4d.cli.argument_types import number, probability, seed, whole


def gap_scales(text: str) -> tuple[float, ...]:
    """argparse type of ``--gap-scales``: comma-separated multiples of episode_steps/15, each > 0."""
    scale = number(0, above=True)
    parts = [t.strip() for t in text.split(",") if t.strip()]
    if not parts:
        raise argparse.ArgumentTypeError(f"must be comma-separated numbers > 0 such as 0.5,1,2, got {text!r}")
    try:
        return tuple(scale(t) for t in parts)
    except argparse.ArgumentTypeError as e:
        raise argparse.ArgumentTypeError(f"{e} (each of the comma-separated scales, e.g. 0.5,1,2)") from None


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from tesseract4d.policy.idm_trainer import IDMTrainConfig

    d = IDMTrainConfig()
    parser.add_argument("--data", required=True, help="dataset folder written by `tesseract4d datagen`")
    parser.add_argument("--out", required=True, help="run folder")
    parser.add_argument("--no-future", action="store_true", help="behaviour cloning: the same network without the future cloud")
    parser.add_argument("--tasks", help="comma-separated task ids to train on (default: every task of the dataset)")
    parser.add_argument("--max-episodes-per-task", type=whole(0, hint=" (0 = all)"), default=d.max_episodes_per_task,
                        help="0 = all (default)")
    parser.add_argument("--camera", help="camera of the dataset (default: its first)")
    parser.add_argument("--steps", type=whole(1), default=d.max_steps, help="training steps (default %(default)s)")
    parser.add_argument("--batch-size", type=whole(1), default=d.batch_size, help="pairs per step (default %(default)s)")
    parser.add_argument("--lr", type=number(0, above=True), default=d.lr, help="peak learning rate (default %(default)s)")
    parser.add_argument("--num-points", type=whole(1), default=d.num_points, help="points per cloud (default %(default)s)")
    parser.add_argument("--chunk-len", type=whole(1), default=d.chunk_len, help="actions per predicted chunk (default %(default)s)")
    parser.add_argument("--noise-frac", type=probability(), default=d.noise_frac,
                        help="share of future points given Gaussian noise, for generated frames (default %(default)s)")
    parser.add_argument("--noise-m", type=number(0), default=d.noise_m, help="that noise's std in metres (default %(default)s)")
    parser.add_argument("--gap-scales", type=gap_scales, default=",".join(str(g) for g in d.gap_scales),
                        help="future frames at these multiples of episode_steps/15 ahead (default %(default)s)")
    parser.add_argument("--predicted-futures", metavar="CHECKPOINT",
                        help="a world-model checkpoint: also train on its predicted futures (default: true futures only)")
    parser.add_argument("--predicted-share", type=number(0, above=True), default=d.predicted_share,
                        help="share of each batch with predicted futures (default %(default)s)")
    parser.add_argument("--predicted-starts", type=whole(1), default=d.predicted_starts,
                        help="clips predicted per episode (default %(default)s)")
    parser.add_argument("--predicted-steps", type=whole(1),
                        help="sampler steps per predicted clip (default: the checkpoint's own)")
    parser.add_argument("--ckpt-every", type=whole(0, hint=" (0 = only at the end)"), default=d.ckpt_every,
                        help="checkpoint every K steps (default %(default)s)")
    parser.add_argument("--max-minutes", type=number(0), help="stop with a checkpoint after this many minutes")
    parser.add_argument("--seed", type=seed(), default=d.seed)
    parser.add_argument("--resume", action="store_true", help="continue from RUN/checkpoint")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")


def run(args: argparse.Namespace) -> int:
    from tesseract4d.policy.idm_trainer import IDMTrainConfig, IDMTrainer
    from tesseract4d.stopping import raise_for_stop

    cfg = IDMTrainConfig(
        data=args.data, out=args.out, use_future=not args.no_future,
        tasks=[t.strip() for t in args.tasks.split(",") if t.strip()] if args.tasks else None,
        max_episodes_per_task=args.max_episodes_per_task, camera=args.camera, max_steps=args.steps,
        batch_size=args.batch_size, lr=args.lr, num_points=args.num_points, chunk_len=args.chunk_len,
        noise_frac=args.noise_frac, noise_m=args.noise_m,
        gap_scales=args.gap_scales, seed=args.seed, ckpt_every=args.ckpt_every,
        max_minutes=args.max_minutes, resume=args.resume, quiet=args.no_progress,
        predicted_futures=args.predicted_futures, predicted_share=args.predicted_share,
        predicted_starts=args.predicted_starts, predicted_sample_steps=args.predicted_steps,
    )
    trainer = IDMTrainer(cfg)
    n_pred = int(trainer.pairs.predicted.sum())
    print(f"{len(trainer.pairs.episodes)} episodes, {len(trainer.pairs.now) - n_pred} training pairs"
          + (f" and {n_pred} with predicted futures" if n_pred else ""))
    final = trainer.train()
    training = trainer.model.config.training
    print(f"wrote {final}; fit on the training pairs: {json.dumps(training['fit'])}")
    if "fit_predicted" in training:
        print(f"fit on the pairs with predicted futures: {json.dumps(training['fit_predicted'])}")
    raise_for_stop(trainer.stopped_by)  # a stopped run ends 130 / 143, its checkpoint and final/ kept
    return 0
