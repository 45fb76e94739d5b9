"""Train the RGB-D-N autoencoder of the latent world model (per frame, continuous latents).

Reads every frame of a dataset folder (RGB, metric depth, normals, segmentation) into memory and
trains a diffusers AutoencoderKL behind a pixel-unshuffle stem. Every --ckpt-every steps it writes a
resumable checkpoint (RUN/checkpoint-XXXXXX/) and exports RUN/autoencoder/ (EMA weights, latent
statistics), measures the fidelity gate on the --heldout frames (RGB PSNR, depth mm/AbsRel, normal
angle; all pixels and robot/object pixels), prints it and stores it as RUN/autoencoder/fidelity.json.
The autoencoder needs hours on a CPU: run it in the background and stop/resume at will. Where torch
sees a CUDA GPU it trains there (about 15 times the steps/s of a 2-core CPU at batch 8);
CUDA_VISIBLE_DEVICES= keeps it on the CPU.

Example:
  tesseract4d datagen --tasks PickCube-v1,PushCube-v1 --episodes 40 --resolution 128 --out data/ae128
  tesseract4d datagen --tasks PickCube-v1,PushCube-v1 --episodes 3 --resolution 128 \\
      --seed-start 100000 --instruction-split heldout --out data/ae128_heldout
  tesseract4d train-autoencoder --data data/ae128 --heldout data/ae128_heldout --out runs/ae
  tesseract4d train-autoencoder --data data/ae128 --heldout data/ae128_heldout --out runs/ae --resume
  tesseract4d train-autoencoder --init runs/ae/autoencoder --data data/ae128 data/skills128 --frame-stride 4 \\
      --lr 1.5e-4 --warmup-steps 50 --max-steps 1500 --heldout data/skills128_heldout --out runs/ae_ft   # fine-tune
  tesseract4d train-autoencoder --init tesseract4d/checkpoints/v2/autoencoder --decoder-only --data data/skills128 \\
      --heldout data/skills128_heldout --out runs/dec_ft     # a better decoder for v2's latents (see swap-decoder)
  tesseract4d train-autoencoder --data data/ae128 --heldout data/ae128_heldout --max-steps auto --max-minutes 8 \\
      --out runs/ae_gpu     # the cosine decay fitted to an 8-minute budget (e.g. a lent GPU)
"""

from __future__ import annotations

import argparse
from pathlib import Path

from tesseract4d.cli.argument_types import number, seed, whole
from tesseract4d.model.autoencoder import AUTOENCODER_PRESETS
from tesseract4d.model.autoencoder_trainer import AutoencoderTrainConfig
from tesseract4d.training.schedule import add_max_steps_argument
from tesseract4d.precision import add_precision_argument


def add_arguments(parser: argparse.ArgumentParser) -> None:
    d = AutoencoderTrainConfig()
    parser.add_argument("--data", type=Path, nargs="+", required=True,
                        help="training dataset folder(s) (tesseract4d datagen), trained as one set")
    parser.add_argument("--init", type=Path, default=None,
                        help="start from this exported autoencoder (RUN/autoencoder) instead of random weights: "
                             "fine-tune it on new scenes; the latent model must then be trained on the new one")
    parser.add_argument("--decoder-only", action="store_true",
                        help="with --init: train only the decoder; the encoder and latent statistics stay exactly as they "
                             "are, so a latent model trained on them keeps working: put the new decoder into its "
                             "checkpoint with `tesseract4d swap-decoder`")
    parser.add_argument("--frame-stride", type=whole(1), default=d.frame_stride,
                        help="train on every k-th frame of each episode (less memory; default %(default)s)")
    parser.add_argument("--heldout", type=Path, default=None,
                        help="held-out dataset folder for the fidelity gate (recommended; e.g. seeds >= 100000)")
    parser.add_argument("--out", type=Path, required=True, help="run folder (new, or an existing one with --resume)")
    parser.add_argument("--preset", default=d.preset, choices=list(AUTOENCODER_PRESETS),
                        help="autoencoder architecture (default %(default)s)")
    parser.add_argument("--camera", default=None, help="camera of the dataset to train on (default: its first)")
    add_max_steps_argument(parser, d.max_steps)
    parser.add_argument("--max-minutes", type=number(0), default=None,
                        help="stop with a checkpoint after this many minutes")
    parser.add_argument("--batch-size", type=whole(1), default=d.batch_size, help="frames per step (default %(default)s)")
    parser.add_argument("--lr", type=number(0, above=True), default=d.lr, help="peak learning rate (default %(default)s)")
    parser.add_argument("--warmup-steps", type=whole(0), default=d.warmup_steps, help="linear warm-up steps (default %(default)s)")
    parser.add_argument("--object-weight", type=number(0), default=d.object_weight,
                        help="loss weight of robot/object pixels relative to scenery (default %(default)s)")
    parser.add_argument("--rgb-weight", type=number(0), default=d.rgb_weight, help="default %(default)s")
    parser.add_argument("--depth-weight", type=number(0), default=d.depth_weight, help="default %(default)s")
    parser.add_argument("--normal-weight", type=number(0), default=d.normal_weight, help="default %(default)s")
    parser.add_argument("--kl-weight", type=number(0), default=d.kl_weight, help="default %(default)s")
    add_precision_argument(parser)
    parser.add_argument("--ckpt-every", type=whole(0, hint=" (0 = only at the end)"), default=d.ckpt_every,
                        help="steps between checkpoints + fidelity gate (default %(default)s)")
    parser.add_argument("--heldout-frames", type=whole(1), default=d.heldout_frames,
                        help="held-out frames in the fidelity gate (default %(default)s)")
    parser.add_argument("--seed", type=seed(), default=d.seed)
    parser.add_argument("--resume", action="store_true", help="continue the latest checkpoint in --out exactly")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")


def run(args: argparse.Namespace) -> int:
    from tesseract4d.stopping import raise_for_stop

    import functools

    import numpy as np

    from tesseract4d.evaluation.autoencoder_fidelity import fidelity_metrics, format_fidelity
    from tesseract4d.model.autoencoder_trainer import AutoencoderTrainer, load_heldout_frames

    cfg = AutoencoderTrainConfig(
        data=args.data, heldout=args.heldout, out=args.out, preset=args.preset, camera=args.camera,
        init=args.init, decoder_only=args.decoder_only,
        frame_stride=args.frame_stride, warmup_steps=args.warmup_steps,
        max_steps=args.max_steps, max_minutes=args.max_minutes, batch_size=args.batch_size, lr=args.lr,
        object_weight=args.object_weight, rgb_weight=args.rgb_weight, depth_weight=args.depth_weight, normal_weight=args.normal_weight,
        kl_weight=args.kl_weight, precision=args.precision, ckpt_every=args.ckpt_every,
        heldout_frames=args.heldout_frames, seed=args.seed, resume=args.resume, quiet=args.quiet,
    )
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
