"""Distil a checkpoint into a few-step student (rectified-flow reflow): one network pass per step.

  tesseract4d distill --teacher tesseract4d/checkpoints/v2 --data data/train --pairs runs/pairs --out runs/student
  tesseract4d distill --pairs-only --teacher tesseract4d/checkpoints/v2 --data data/train --pairs runs/pairs
  tesseract4d distill --teacher tesseract4d/checkpoints/v2 --pairs runs/pairs --out runs/student --resume
  tesseract4d train --export runs/student --to checkpoints/v2-2step --half   # the student in float16
  tesseract4d distill --teacher tesseract4d/checkpoints/v2 --data data/groups --pairs runs/gpairs --group-pairs \\
      --counterfactual-swap 0.5 --out runs/student   # keeps reading the future from the words (as v2-2step)

Two stages, each resumable:
1. pairs: the teacher samples --num-pairs clips (on the GPU where torch sees one) with its full
   sampler (its preset's steps and guidance, or --teacher-steps and --teacher-guidance) from stored
   noise, first frames and instructions of --data, into --pairs (shards written whole; a rerun continues at the first
   missing shard, and refuses a folder made with other settings). Skipped when --data is not given and --pairs is complete.
2. student: initialised with the teacher's weights, trained on the straight path between each
   pair's noise and the teacher's clip (with --counterfactual-swap P, on --group-pairs pairs: in
   batches of whole groups, and at noise >= 0.3 shown, with probability P, a sibling's noisy
   sample while its target stays its own teacher clip, as `train --counterfactual-swap`). RUN/final
   is an inference checkpoint whose preset samples in --student-steps steps without guidance, and
   which records the teacher it was distilled from.
"""

from __future__ import annotations

import argparse
from pathlib import Path


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from tesseract4d.cli.argument_types import number, probability, seed, whole
    from tesseract4d.training.schedule import add_max_steps_argument
    from tesseract4d.model.reflow import PairsConfig, ReflowConfig
    from tesseract4d.precision import add_precision_argument

    p, d = PairsConfig(Path(), Path(), Path()), ReflowConfig()
    parser.add_argument("--teacher", type=Path, required=True, help="the inference checkpoint to distil (e.g. RUN/final)")
    parser.add_argument("--data", type=Path, nargs="+",
                        help="dataset folder(s) the pairs' first frames and instructions come from (drawn as one set)")
    parser.add_argument("--pairs", type=Path, required=True, help="pairs folder (written, or resumed, from --data)")
    parser.add_argument("--out", type=Path, help="the student's run folder (checkpoints, logs, final/)")
    parser.add_argument("--pairs-only", action="store_true", help="make the pairs and stop")
    parser.add_argument("--num-pairs", type=whole(1), default=p.num_pairs, help="teacher clips to sample (default %(default)s)")
    parser.add_argument("--teacher-steps", type=whole(1), help="the teacher's sampler steps (default: its preset's)")
    parser.add_argument("--teacher-guidance", type=number(0, above=True, hint=" (1: no guidance)"), metavar="SCALE",
                        help="the teacher's text guidance scale (default: its preset's); the student learns the "
                             "guided clips, so this becomes the student's guidance at no cost")
    parser.add_argument("--group-pairs", action="store_true",
                        help="draw the pairs as whole counterfactual groups of --data (one scene under several "
                             "instructions, `datagen --instructions-per-scene`), a group's pairs sharing one noise")
    parser.add_argument("--pair-batch-size", type=whole(1), default=p.batch_size,
                        help="teacher clips per sampler call (default %(default)s)")
    parser.add_argument("--student-steps", type=whole(1), default=d.student_steps,
                        help="the student's sampler steps, one network pass each (default %(default)s)")
    parser.add_argument("--counterfactual-swap", type=probability(), default=d.counterfactual_swap, metavar="P",
                        help="train the student in batches of whole groups (needs --group-pairs pairs) and show a "
                             "pair at noise >= 0.3, with probability P, a sibling's noisy sample (default %(default)s)")
    parser.add_argument("--rephrase", type=probability(), default=d.rephrase, metavar="P",
                        help="probability of training a pair under another training wording of its instruction, the "
                             "teacher's clip staying the target (as `train --rephrase`) (default %(default)s)")
    add_max_steps_argument(parser, d.max_steps, "the student's training steps")
    parser.add_argument("--max-minutes", type=number(0), help="stop with a checkpoint after this many minutes of this invocation")
    parser.add_argument("--batch-size", type=whole(1), help="pairs per step (default: the teacher preset's)")
    parser.add_argument("--lr", type=number(0, above=True), help="peak learning rate (default: the teacher preset's)")
    add_precision_argument(parser)
    parser.add_argument("--resume", action="store_true", help="continue the student's run from the latest checkpoint in --out")
    parser.add_argument("--val-every", type=whole(0, hint=" (0 = never)"), default=d.val_every,
                        help="PSNR of the student against the teacher every K steps, 0 = never (default %(default)s)")
    parser.add_argument("--ckpt-every", type=whole(0, hint=" (0 = only at the end)"), default=d.ckpt_every,
                        help="checkpoint every K steps (default %(default)s)")
    parser.add_argument("--seed", type=seed(), default=0,
                        help="seed of the pairs' noise and of the training (default %(default)s)")
    parser.add_argument("--camera", help="camera of --data (default: the teacher's)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bars")


def run(args: argparse.Namespace) -> int:
    from tesseract4d.stopping import raise_for_stop

    from tesseract4d.errors import UserError
    from tesseract4d.training.schedule import check_max_steps
    from tesseract4d.model.reflow import (MANIFEST, PairsConfig, ReflowConfig, ReflowTrainer, check_pairs_of_teacher,
                                          generate_pairs)
    from tesseract4d.outputs import check_not_input

    if not args.pairs_only and args.out is None:
        raise UserError("pass --out RUN (the student's run folder), or --pairs-only to make the pairs only")
    # Every refusal before the teacher samples a single pair: the pairs take the longest.
    inputs = [*(args.data or []), args.teacher]
    check_not_input(args.pairs, inputs, "--pairs")
    if args.pairs.exists() and not args.pairs.is_dir():
        raise UserError(f"--pairs {args.pairs} is a file, not a folder; pass a folder path")
    if not args.pairs_only:
        check_not_input(args.out, [*inputs, args.pairs], "--out")
        check_max_steps(args.max_steps, args.max_minutes, resume=args.resume)
    if args.data is not None:
        generate_pairs(PairsConfig(
            teacher=args.teacher, data=args.data[0] if len(args.data) == 1 else args.data, out=args.pairs, num_pairs=args.num_pairs,
            batch_size=args.pair_batch_size, teacher_steps=args.teacher_steps,
            text_guidance=args.teacher_guidance, seed=args.seed, camera=args.camera,
            precision=args.precision, groups=args.group_pairs),
            progress=not args.no_progress)
        print(f"pairs: {args.pairs}")
    elif args.pairs_only or not (args.pairs / MANIFEST).is_file():
        raise UserError(f"pass --data DIR: the pairs in {args.pairs} are made from a dataset folder")
    else:
        check_pairs_of_teacher(args.pairs, args.teacher, args.teacher_steps, args.teacher_guidance)
    if args.pairs_only:
        return 0
    cfg = ReflowConfig(
        data=args.pairs, out=args.out, teacher=args.teacher, student_steps=args.student_steps,
        max_steps=args.max_steps, max_minutes=args.max_minutes, batch_size=args.batch_size, lr=args.lr,
        precision=args.precision, resume=args.resume, val_every=args.val_every, ckpt_every=args.ckpt_every,
        seed=args.seed, quiet=args.no_progress, group_batches=args.counterfactual_swap > 0,
        counterfactual_swap=args.counterfactual_swap, rephrase=args.rephrase)
    from datagen.paraphrases import train_paraphrases

    trainer = ReflowTrainer(cfg, train_paraphrases)
    final = trainer.train()
    print(f"student checkpoint: {final} ({args.student_steps} steps, one network pass each)")
    raise_for_stop(trainer.stopped_by)  # a stopped run ends 130 / 143, its checkpoint and export kept
    return 0
