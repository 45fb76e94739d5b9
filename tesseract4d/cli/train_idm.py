"""Train the inverse dynamics model (current + future point clouds + instruction -> action chunk),
or its behaviour-cloning twin (`--recipe bc`, or `--set use_future=false`: current point cloud +
instruction -> action chunk).

  tesseract4d train-idm --recipe idm --data data/idm_train128 --out runs/idm   # the closed loop's IDM
  tesseract4d train-idm --recipe bc --data data/idm_train128 --out runs/bc     # its behaviour-cloning twin
  tesseract4d train-idm --data data/idm_train --out runs/idm --max-steps 1500
  tesseract4d train-idm --data data/idm_train --out runs/idm --max-steps 3000 --resume   # continue
  tesseract4d train-idm --data data/idm_train128 --out runs/idm_pred --max-steps 3000 \\
      --predicted-futures tesseract4d/checkpoints/v2-2step          # also learn from predicted frames

Training pairs are ground-truth frames of datagen episodes (best written with --frames 0, every
step) about episode_steps/15 steps apart and the actions between them. Writes
RUN/train_idm_config.json, RUN/checkpoint/ (resumable) and RUN/final/ (idm_config.json +
model.safetensors, with the fit on the training pairs in its config). Every option is a field of
IDMTrainConfig (`--set list`).

With --predicted-futures CHECKPOINT the world model predicts clips from frames of the training
episodes (`predicted_starts` per episode, from steps 0, L/n, 2L/n, ... as the policy loop does),
and `predicted_share` of every batch pairs a true frame with the predicted future and the true
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


FLAGS = ("data", "out", "predicted_futures")
# Flags of earlier releases whose options are --set fields now, with their old types (one more release).
MOVED = [("--tasks", "tasks"), ("--max-episodes-per-task", "max_episodes_per_task", whole(0, hint=" (0 = all)")),
         ("--camera", "camera"), ("--batch-size", "batch_size", whole(1)), ("--lr", "lr", number(0, above=True)),
         ("--num-points", "num_points", whole(1)), ("--chunk-len", "chunk_len", whole(1)),
         ("--noise-frac", "noise_frac", probability()), ("--noise-m", "noise_m", number(0)),
         ("--gap-scales", "gap_scales", gap_scales), ("--predicted-share", "predicted_share", number(0, above=True)),
         ("--predicted-starts", "predicted_starts", whole(1)),
         ("--predicted-steps", "predicted_sample_steps", whole(1)), ("--seed", "seed", seed()),
         ("--no-future", "use_future", None, False)]


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from tesseract4d.cli.config_args import add_deprecated, add_moved_to_set, add_trainer_options
    from tesseract4d.policy.idm_trainer import IDMTrainConfig
    from tesseract4d.recipes import IDM

    names = add_trainer_options(
        parser, IDMTrainConfig, FLAGS, IDM, required=("data", "out"),
        types={"max_minutes": number(0), "ckpt_every": whole(0, hint=" (0 = only at the end)")})
    parser.set_defaults(flag_fields=names)
    add_deprecated(parser, "--steps", use="--max-steps", dest="max_steps", type=whole(1))
    add_moved_to_set(parser, IDMTrainConfig, MOVED)


def run(args: argparse.Namespace) -> int:
    from tesseract4d.cli.config_args import config_from_args, recipe_from_args
    from tesseract4d.policy.idm_trainer import IDMTrainConfig, IDMTrainer
    from tesseract4d.recipes import IDM
    from tesseract4d.stopping import raise_for_stop

    cfg = config_from_args(IDMTrainConfig, args, args.flag_fields, recipe=recipe_from_args(args, IDM, read_recipe))
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


def read_recipe(folder) -> dict:
    """The IDMTrainConfig values an IDM folder (RUN/final) records: the options of the run that wrote it
    (RUN/train_idm_config.json beside it) or, without that, its training record."""
    import dataclasses
    from pathlib import Path

    from tesseract4d.errors import UserError
    from tesseract4d.policy.idm_trainer import IDMTrainConfig

    folder = Path(folder)
    keep = {f.name for f in dataclasses.fields(IDMTrainConfig)} - {"data", "out", "resume", "quiet"}
    for path in (folder.parent / "train_idm_config.json", folder / "train_idm_config.json"):
        if path.is_file():
            return {k: (tuple(v) if k == "gap_scales" else v) for k, v in json.loads(path.read_text()).items()
                    if k in keep}
    try:
        training = json.loads((folder / "idm_config.json").read_text()).get("training") or {}
    except (OSError, ValueError) as e:
        raise UserError(f"--recipe-from {folder}: cannot read its idm_config.json ({e}); pass an IDM folder "
                        f"(RUN/final of `tesseract4d train-idm`)") from None
    return {k: v for k, v in training.items() if k in keep}
