"""Train the RGB-D-N autoencoder of the latent world model (per frame, continuous latents).

Reads every frame of a dataset folder (RGB, metric depth, normals, segmentation) into memory and
trains a diffusers AutoencoderKL behind a pixel-unshuffle stem. Every --ckpt-every steps it writes a
resumable checkpoint (RUN/checkpoint-XXXXXX/) and exports RUN/autoencoder/ (EMA weights, latent
statistics), measures the fidelity gate on the --heldout frames (RGB PSNR, depth mm/AbsRel, normal
angle; all pixels and robot/object pixels), prints it and stores it as RUN/autoencoder/fidelity.json.
The autoencoder needs hours on a CPU: run it in the background and stop/resume at will. Where torch
sees a CUDA GPU it trains there (about 15 times the steps/s of a 2-core CPU at batch 8);
CUDA_VISIBLE_DEVICES= keeps it on the CPU. Every option of the run is a field of AutoencoderTrainConfig
(`--set list`); the loss weights and the schedule are set with `--set NAME=VALUE`.

Example:
  tesseract4d datagen --tasks PickCube-v1,PushCube-v1 --episodes 40 --resolution 128 --out data/ae128
  tesseract4d datagen --tasks PickCube-v1,PushCube-v1 --episodes 3 --resolution 128 \\
      --seed-start 100000 --instruction-split heldout --out data/ae128_heldout
  tesseract4d train-autoencoder --recipe ae-f8c32 --data data/ae128 --heldout data/ae128_heldout --out runs/ae
                                                        # the shipped autoencoder's recipe
  tesseract4d train-autoencoder --recipe ae-f8c32 --data data/ae128 --heldout data/ae128_heldout --out runs/ae --resume
  tesseract4d train-autoencoder --init runs/ae/autoencoder --data data/ae128 data/skills128 --set frame_stride=4 \\
      --set lr=1.5e-4 --set warmup_steps=50 --max-steps 1500 --heldout data/skills128_heldout --out runs/ae_ft
                                                        # fine-tune
  tesseract4d train-autoencoder --recipe ae-f8c32-decoder --init tesseract4d/checkpoints/v2/autoencoder \\
      --data data/skills128 --heldout data/skills128_heldout --out runs/dec_ft
                                                        # a better decoder for v2's latents (then
                                                        # `tesseract4d checkpoint swap-decoder`)
  tesseract4d train-autoencoder --data data/ae128 --heldout data/ae128_heldout --max-steps auto --max-minutes 8 \\
      --out runs/ae_gpu     # the cosine decay fitted to an 8-minute budget (e.g. a lent GPU)
"""

from __future__ import annotations

import argparse

from tesseract4d.cli.argument_types import number, seed, whole
from tesseract4d.cli.config_args import PRECISION_MOVED, add_moved_to_set, add_trainer_options, config_from_args
from tesseract4d.model.autoencoder import AUTOENCODER_PRESETS
from tesseract4d.model.autoencoder_trainer import AutoencoderTrainConfig
from tesseract4d.recipes import AUTOENCODER as RECIPES

FLAGS = ("data", "heldout", "out", "init")
# Flags of earlier releases whose options are --set fields now, with their old types (one more release).
MOVED = {"frame_stride": whole(1), "camera": str, "batch_size": whole(1), "lr": number(0, above=True),
         "warmup_steps": whole(0), "object_weight": number(0), "rgb_weight": number(0), "depth_weight": number(0),
         "normal_weight": number(0), "kl_weight": number(0), "heldout_frames": whole(1), "seed": seed()}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    names = add_trainer_options(parser, AutoencoderTrainConfig, FLAGS, RECIPES, required=("data", "out"),
                                types={"max_minutes": number(0), "ckpt_every": whole(0, hint=" (0 = only at the end)")})
    parser.set_defaults(flag_fields=names)
    add_moved_to_set(parser, AutoencoderTrainConfig,
                     [(f"--{name.replace('_', '-')}", name, kind) for name, kind in MOVED.items()]
                     + [("--decoder-only", "decoder_only", None, True), PRECISION_MOVED,
                        ("--preset", "preset", {"choices": list(AUTOENCODER_PRESETS)})])


def read_recipe(folder) -> dict:
    """The options an autoencoder folder (RUN/autoencoder or a checkpoint's autoencoder/) records: its
    architecture preset, and, beside a run's export, the run's own options (RUN/ae_train_config.json)."""
    import json
    from pathlib import Path

    from tesseract4d.errors import UserError
    from tesseract4d.model.autoencoder_trainer import CONFIG_FILE

    folder = Path(folder)
    try:
        saved = json.loads((folder / "config.json").read_text())
    except (OSError, ValueError) as e:
        raise UserError(f"--recipe-from {folder}: cannot read its config.json ({e}); pass an autoencoder folder "
                        f"(RUN/autoencoder, or a checkpoint's autoencoder/)") from None
    values = {"preset": saved["name"]} if saved.get("name") in AUTOENCODER_PRESETS else {}
    run_config = folder.parent / CONFIG_FILE
    if run_config.is_file():
        import dataclasses

        recorded = json.loads(run_config.read_text())
        keep = {f.name for f in dataclasses.fields(AutoencoderTrainConfig)} - {"data", "heldout", "out", "init", "resume",
                                                                              "max_steps_fit", "quiet"}
        values.update({k: v for k, v in recorded.items() if k in keep})
    return values


def run(args: argparse.Namespace) -> int:
    from tesseract4d.stopping import raise_for_stop

    import functools

    import numpy as np

    from tesseract4d.evaluation.autoencoder_fidelity import fidelity_metrics, format_fidelity
    from tesseract4d.model.autoencoder_trainer import AutoencoderTrainer, load_heldout_frames

    from tesseract4d.cli.config_args import recipe_from_args

    cfg = config_from_args(AutoencoderTrainConfig, args, args.flag_fields,
                           recipe=recipe_from_args(args, RECIPES, read_recipe))
    trainer = AutoencoderTrainer(cfg, format_fn=format_fidelity)
    if cfg.heldout is not None:
        heldout = load_heldout_frames(cfg.heldout, trainer.model, cfg.heldout_frames, camera=cfg.camera)
        trainer.fidelity_fn = functools.partial(lambda model, frames: fidelity_metrics(model, frames), frames=heldout)
    trainer.train()  # its last checkpoint prints the final gate
    if cfg.heldout is not None:
        import imageio.v3 as iio

        from tesseract4d.evaluation.autoencoder_fidelity import reconstruction_sheet

        picks = [int(i) for i in np.linspace(0, len(heldout) - 1, 4).round()]
        sheet = reconstruction_sheet(trainer.ema.model, heldout, picks)
        iio.imwrite(cfg.out / "reconstructions.png", sheet)
        print(f"held-out frames (truth above, reconstruction below; RGB | depth | normals): {cfg.out / 'reconstructions.png'}")
    print(f"autoencoder: {cfg.out / 'autoencoder'}  (resume with the same command plus --resume)")
    raise_for_stop(trainer.stopped_by)  # a stopped run ends 130 / 143, its checkpoint and export kept
    return 0
