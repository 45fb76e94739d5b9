"""Train the RGB-D-N video diffusion model on a dataset folder, or export a run's EMA weights.

  tesseract4d train --data data/ae128 --autoencoder runs/ae/autoencoder --out runs/latent   # latent-128 (default)
  tesseract4d train --data data/skills data/tasks --autoencoder runs/ae/autoencoder --out runs/v2   # two datasets
  tesseract4d train --preset tiny --data data/train --out runs/tiny --max-minutes 60
  tesseract4d train --data data/ae128 --autoencoder runs/ae/autoencoder --out runs/gpu --max-steps auto --max-minutes 8
                                                                     # the cosine decay fitted to an 8-minute budget
  tesseract4d train --out runs/tiny --resume --data data/train      # continue exactly where it stopped
  tesseract4d train --init tesseract4d/checkpoints/v2 --data data/skills --out runs/v2-more --lr 1.5e-4
                                                                     # fine-tune a checkpoint (new schedule)
  tesseract4d train --export runs/tiny --to checkpoints/mine        # inference folder (EMA weights)
  tesseract4d train --export runs/v2 --to checkpoints/v2 --half     # the same in float16 (half the size)

Every run ends (max steps, --max-minutes, Ctrl-C or SIGTERM) with a checkpoint and an export of
the EMA weights to RUN/final; a run stopped by Ctrl-C or SIGTERM then exits 130 or 143, so a
scheduler tells it from a finished one (0). Scale out with `accelerate launch -m tesseract4d.cli train ...`.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from tesseract4d.model.presets import PRESETS


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from tesseract4d.model.recipe import SWAP_MIN_T
    from tesseract4d.training.schedule import add_max_steps_argument
    from tesseract4d.model.trainer import TrainConfig
    from tesseract4d.precision import add_precision_argument

    d = TrainConfig()
    parser.add_argument("--preset", default=d.preset, choices=list(PRESETS), help="model preset (default %(default)s)")
    parser.add_argument("--data", type=Path, nargs="+",
                        help="dataset folder(s) written by `tesseract4d datagen`; several folders (same resolution "
                             "and camera) train as one set")
    parser.add_argument("--out", type=Path, help="run folder (checkpoints, logs, validation videos, final/)")
    parser.add_argument("--pretrained", type=Path, help="local CogVideoX-5B-I2V folder (cogvideox-5b preset)")
    parser.add_argument("--autoencoder", type=Path,
                        help="RGB-D-N autoencoder folder for latent presets (RUN/autoencoder of `tesseract4d train-autoencoder`); "
                             "the dataset is encoded once into DATA/latent_cache/")
    parser.add_argument("--init", type=Path, metavar="CKPT",
                        help="start from this inference checkpoint's transformer weights (e.g. tesseract4d/checkpoints/v2 "
                             "or RUN/final) with a fresh optimiser and learning-rate schedule; a latent preset then uses "
                             "the checkpoint's autoencoder unless --autoencoder names one with the same encoder")
    parser.add_argument("--condition-noise", type=float, default=d.condition_noise,
                        help="max std of noise on the conditioning first frame in training (default %(default)s)")
    parser.add_argument("--moving-weight", type=float, default=d.moving_weight,
                        help="loss weight of moving cells (default %(default)s)")
    parser.add_argument("--object-weight", type=float, default=d.object_weight,
                        help="loss weight of robot/object cells, latent presets (default %(default)s)")
    parser.add_argument("--scene-object-weight", type=float, default=d.scene_object_weight, metavar="W",
                        help="added loss weight of the cells of the scene's objects alone (cubes, cylinders; not the "
                             "robot), latent presets: they hold about 2 %% of the loss weight of v2's recipe, "
                             "the robot 25 %% (default %(default)s = off)")
    parser.add_argument("--time-logit-normal", type=float, default=d.time_logit_normal, metavar="STD",
                        help="draw the diffusion time logit-normal, sigmoid(STD * n) with n ~ N(0, 1), instead of uniform: trains "
                             "most at middle noise, as SD3 does (1 is SD3's; default %(default)s = uniform)")
    parser.add_argument("--group-batches", action="store_true",
                        help="make every batch of whole counterfactual groups (one scene under several instructions, "
                             "from `datagen --instructions-per-scene`) sharing one noise and diffusion time")
    parser.add_argument("--counterfactual-swap", type=float, default=d.counterfactual_swap,
                        help=f"with --group-batches: probability that a clip at noise >= {SWAP_MIN_T} is shown another "
                             f"future of its group as its noisy sample and must still predict its own (default %(default)s)")
    parser.add_argument("--rephrase", type=float, default=d.rephrase, metavar="P",
                        help="probability of training a clip under another training wording of its instruction (same "
                             "object, direction and distance, from the datagen's train templates) (default %(default)s)")
    parser.add_argument("--text-noise", type=float, default=d.text_noise, metavar="S",
                        help="max std of noise on the instruction's token embeddings in training, relative to each "
                             "token's size, drawn per clip from U(0, S): nearby wordings then read the same "
                             "(default %(default)s = off)")
    parser.add_argument("--text-dropout", type=float, help="share of steps without text, for guidance (default: the preset's)")
    add_max_steps_argument(parser, d.max_steps)
    parser.add_argument("--max-minutes", type=float, help="stop with a checkpoint after this many minutes of this invocation")
    parser.add_argument("--stop-at-step", type=int,
                        help="stop with a checkpoint at this step; the learning-rate schedule still ends at --max-steps "
                             "(a run cut short of its schedule, as the shipped v2's last stage; --resume goes on)")
    parser.add_argument("--batch-size", type=int, help="clips per step (default: the preset's)")
    parser.add_argument("--lr", type=float, help="peak learning rate (default: the preset's)")
    parser.add_argument("--warmup-steps", type=int, help="linear warm-up steps (default: the preset's)")
    add_precision_argument(parser)
    parser.add_argument("--resume", action="store_true", help="continue from the latest checkpoint in --out")
    parser.add_argument("--val-every", type=int, default=d.val_every, help="validation videos every K steps, 0 = never (default %(default)s)")
    parser.add_argument("--ckpt-every", type=int, default=d.ckpt_every, help="checkpoint every K steps (default %(default)s)")
    parser.add_argument("--loss-weights", default="rgb=1,depth=1,normal=1",
                        help="per-modality loss weights (default %(default)s)")
    parser.add_argument("--seed", type=int, default=d.seed, help="training seed (default %(default)s)")
    parser.add_argument("--camera", help="camera of the dataset to train on (default: its first)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    parser.add_argument("--export", type=Path, metavar="RUN", help="export RUN's latest EMA weights instead of training")
    parser.add_argument("--to", type=Path, help="with --export: the inference folder to write (default RUN/final)")
    parser.add_argument("--overwrite", action="store_true",
                        help="with --export: write into a folder holding other files (only the export's files are replaced)")
    parser.add_argument("--half", action="store_true",
                        help="with --export: store the weights (and a latent model's autoencoder) in float16, half the size")


def run(args: argparse.Namespace) -> int:
    from tesseract4d.stopping import raise_for_stop

    from tesseract4d.errors import UserError
    from tesseract4d.model.trainer import TrainConfig, Trainer, export_checkpoint

    if args.export is not None:
        folder = export_checkpoint(args.export, args.to, overwrite=args.overwrite, half=args.half)
        print(f"exported {folder}")
        return 0
    if args.to is not None or args.overwrite or args.half:
        raise UserError("--to, --overwrite and --half go with --export RUN")
    if args.out is None:
        raise UserError("pass --out RUN (the run folder)")
    try:
        weights = {k.strip(): float(v) for k, v in (item.split("=") for item in args.loss_weights.split(","))}
    except ValueError as e:
        raise UserError(f"--loss-weights must look like rgb=1,depth=1,normal=1, got {args.loss_weights!r}") from e
    cfg = TrainConfig(
        data=args.data, out=args.out, preset=args.preset, pretrained=args.pretrained, max_steps=args.max_steps,
        max_minutes=args.max_minutes, stop_at_step=args.stop_at_step, batch_size=args.batch_size, lr=args.lr,
        warmup_steps=args.warmup_steps,
        precision=args.precision, resume=args.resume, val_every=args.val_every, ckpt_every=args.ckpt_every, seed=args.seed,
        camera=args.camera, quiet=args.no_progress, loss_weights=weights, autoencoder=args.autoencoder,
        condition_noise=args.condition_noise, moving_weight=args.moving_weight, object_weight=args.object_weight,
        scene_object_weight=args.scene_object_weight,
        text_dropout=args.text_dropout, init=args.init, time_logit_normal=args.time_logit_normal,
        group_batches=args.group_batches,
        counterfactual_swap=args.counterfactual_swap, rephrase=args.rephrase, text_noise=args.text_noise,
    )
    from datagen.paraphrases import train_paraphrases

    trainer = Trainer(cfg, train_paraphrases)
    final = trainer.train()
    print(f"inference checkpoint: {final}")
    raise_for_stop(trainer.stopped_by)  # a stopped run ends 130 / 143, its checkpoint and export kept
    return 0
