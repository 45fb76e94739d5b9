"""Train the RGB-D-N video diffusion model on a dataset folder.

  tesseract4d train --recipe v2 --data data/skills data/tasks --autoencoder tesseract4d/checkpoints/v2/autoencoder \\
      --out runs/v2                                                  # the shipped v2's recipe
  tesseract4d train --recipe v2 --init tesseract4d/checkpoints/v2 --data data/skills --out runs/v2-more
                                                                     # fine-tune v2 with its own recipe
  tesseract4d train --recipe-from tesseract4d/checkpoints/v2 --data data/skills --autoencoder AE --out runs/again
                                                                     # the recipe a checkpoint records
  tesseract4d train --data data/ae128 --autoencoder runs/ae/autoencoder --out runs/latent   # latent-128 (default)
  tesseract4d train --set preset=tiny --data data/train --out runs/tiny --max-minutes 60     # the first pixel model
  tesseract4d train --data data/ae128 --autoencoder runs/ae/autoencoder --out runs/gpu --max-steps auto --max-minutes 8
                                                                     # the cosine decay fitted to an 8-minute budget
  tesseract4d train --out runs/tiny --resume --data data/train      # continue exactly where it stopped
  tesseract4d train --recipe v2 --set lr=1.5e-4 --set batch_size=4 ...   # change any option of the recipe

Every option of the run (`--set list` prints them with their defaults) is a field of TrainConfig;
research levers (condition noise, cell weights, group batches, counterfactual swap, rephrasing,
text noise) are set with `--set NAME=VALUE`. Precedence: defaults < recipe < --set < flags.

Every run ends (max steps, --max-minutes, Ctrl-C or SIGTERM) with a checkpoint and an export of
the EMA weights to RUN/final (`tesseract4d checkpoint export RUN --to DIR [--half]` exports again);
a run stopped by Ctrl-C or SIGTERM then exits 130 or 143, so a scheduler tells it from a finished
one (0). Scale out with `accelerate launch -m tesseract4d.cli train ...`.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from tesseract4d.cli.config_args import (
    PRECISION_MOVED, add_deprecated, add_moved_to_set, add_trainer_options, config_from_args,
)
from tesseract4d.model.presets import PRESETS
from tesseract4d.recipes import TRAIN as RECIPES

# TrainConfig fields that are flags, beside the ones every trainer has (config_args.add_trainer_options).
FLAGS = ("data", "out", "autoencoder", "init")
# Flags of earlier releases whose options are --set fields now, with their old types (each keeps
# working for one release; the config's validate() refuses bad values as it did).
MOVED = {"pretrained": Path, "condition_noise": float, "moving_weight": float, "object_weight": float,
         "scene_object_weight": float, "time_logit_normal": float, "counterfactual_swap": float, "rephrase": float,
         "text_noise": float, "text_dropout": float, "stop_at_step": int, "batch_size": int, "lr": float,
         "warmup_steps": int, "val_every": int, "seed": int, "camera": str}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from tesseract4d.model.trainer import TrainConfig

    names = add_trainer_options(parser, TrainConfig, FLAGS, RECIPES)
    parser.set_defaults(flag_fields=names)
    add_moved_to_set(parser, TrainConfig, [(f"--{name.replace('_', '-')}", name, kind) for name, kind in MOVED.items()]
                     + [("--group-batches", "group_batches", None, True), ("--loss-weights", "loss_weights"),
                        ("--preset", "preset", {"choices": list(PRESETS)}), PRECISION_MOVED])
    # `train --export RUN` became `tesseract4d checkpoint export RUN`.
    from tesseract4d.cli.export import add_export_options

    add_deprecated(parser, "--export", use="`tesseract4d checkpoint export RUN`", dest="export", type=Path,
                   metavar="RUN")
    add_export_options(parser, hidden=True)
    parser.set_defaults(export=None)


def read_recipe(checkpoint: Path) -> dict:
    """The TrainConfig values an inference checkpoint records: its recipe levers, preset and the
    training options of its last run (``tesseract4d_config.json``)."""
    import dataclasses

    from tesseract4d.errors import UserError
    from tesseract4d.model.checkpoint import INFERENCE_CONFIG_FILE
    from tesseract4d.model.trainer import TrainConfig

    path = Path(checkpoint) / INFERENCE_CONFIG_FILE
    try:
        saved = json.loads(path.read_text())
    except (OSError, ValueError) as e:
        raise UserError(f"--recipe-from {checkpoint}: cannot read {path} ({e}); pass an inference checkpoint folder "
                        f"(RUN/final or `tesseract4d checkpoint export` output)") from None
    fields = {f.name for f in dataclasses.fields(TrainConfig)}
    training = saved.get("training") or {}
    values = {k: v for k, v in (saved.get("recipe") or {}).items() if k in fields}
    values.update({k: training[k] for k in ("batch_size", "lr", "ema_decay", "loss_weights", "seed") if k in training})
    if "steps" in training:
        values["max_steps"] = training["steps"]
    preset = saved.get("preset")
    if isinstance(preset, dict) and preset.get("name"):
        values["preset"] = preset["name"]
    return values


def run(args: argparse.Namespace) -> int:
    from tesseract4d.cli.config_args import recipe_from_args
    from tesseract4d.errors import UserError
    from tesseract4d.model.trainer import TrainConfig, Trainer
    from tesseract4d.stopping import raise_for_stop

    if args.export is not None:
        from tesseract4d.cli.export import export

        return export(args.export, args.to, args.overwrite, args.half)
    if args.to is not None or args.overwrite or args.half:
        raise UserError("--to, --overwrite and --half go with `tesseract4d checkpoint export RUN`")
    if args.out is None:
        raise UserError("pass --out RUN (the run folder)")
    cfg = config_from_args(TrainConfig, args, args.flag_fields, recipe=recipe_from_args(args, RECIPES, read_recipe))
    from datagen.paraphrases import train_paraphrases

    trainer = Trainer(cfg, train_paraphrases)
    final = trainer.train()
    print(f"inference checkpoint: {final}")
    raise_for_stop(trainer.stopped_by)  # a stopped run ends 130 / 143, its checkpoint and export kept
    return 0
