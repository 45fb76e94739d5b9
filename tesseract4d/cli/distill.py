"""Distil a checkpoint into a few-step student (rectified-flow reflow): one network pass per step.

  tesseract4d distill --recipe v2-2step --teacher tesseract4d/checkpoints/v2 --data data/v2_tabletop_160 \\
      data/v2_tasks_160 --pairs runs/pairs720 --out runs/student720     # the shipped v2-2step's recipe
  tesseract4d distill --teacher tesseract4d/checkpoints/v2 --data data/train --pairs runs/pairs --out runs/student
  tesseract4d distill --pairs-only --teacher tesseract4d/checkpoints/v2 --data data/train --pairs runs/pairs
  tesseract4d distill --teacher tesseract4d/checkpoints/v2 --pairs runs/pairs --out runs/student --resume
  tesseract4d checkpoint export runs/student --to checkpoints/v2-2step --half   # the student in float16
  tesseract4d distill --teacher tesseract4d/checkpoints/v2 --data data/groups --pairs runs/gpairs \\
      --set groups=true --set counterfactual_swap=0.5 --out runs/student   # keeps reading the future from the words

Two stages, each resumable:
1. pairs: the teacher samples `num_pairs` clips (on the GPU where torch sees one) with its full
   sampler (its preset's steps and guidance, or `--set teacher_steps=N --set text_guidance=S`) from
   stored noise, first frames and instructions of --data, into --pairs (shards written whole; a rerun
   continues at the first missing shard, and refuses a folder made with other settings). Skipped when
   --data is not given and --pairs is complete.
2. student: initialised with the teacher's weights, trained on the straight path between each
   pair's noise and the teacher's clip (with `counterfactual_swap` P on `groups` pairs: in batches of
   whole groups, and at noise >= 0.3 shown, with probability P, a sibling's noisy sample while its
   target stays its own teacher clip, as in `train`). RUN/final is an inference checkpoint whose
   preset samples in `student_steps` steps without guidance, and which records the teacher it was
   distilled from.

Every option is a field of the pairs' config (PairsConfig) or of the student's (ReflowConfig), set
with `--set NAME=VALUE` (`--set list` prints them; a name both have is the student's, the pairs' is
`pairs.NAME`); the teacher, seed, camera and precision are shared by both stages.
"""

from __future__ import annotations

import argparse
import dataclasses
from dataclasses import dataclass, field
from pathlib import Path

from tesseract4d.cli.argument_types import number, probability, seed, whole
from tesseract4d.cli.config_args import PRECISION_MOVED, add_moved_to_set, add_trainer_options, config_from_args
from tesseract4d.configs import knob
from tesseract4d.model.reflow import PairsConfig, ReflowConfig
from tesseract4d.recipes import DISTILL as RECIPES


def _pairs_config() -> PairsConfig:
    return PairsConfig(teacher=None, data=None, out=None)


@dataclass
class DistillConfig:
    """`tesseract4d distill`: the student's training, then the teacher's pairs it trains on."""

    student: ReflowConfig = knob(help="the student's training", default_factory=ReflowConfig)
    pairs: PairsConfig = knob(help="the teacher's pairs", default_factory=_pairs_config)

    def shared(self) -> "DistillConfig":
        """The pairs with the student's teacher, seed, camera and precision (one of each for both stages)."""
        s = self.student
        return dataclasses.replace(self, pairs=dataclasses.replace(
            self.pairs, teacher=s.teacher, seed=s.seed, camera=s.camera, precision=s.precision))


FLAGS = ("teacher", "pairs.data", "pairs.out", "student.out")
# Flags of earlier releases whose options are --set fields now, with their old types (one more release).
MOVED = [("--num-pairs", "num_pairs", whole(1)), ("--teacher-steps", "teacher_steps", whole(1)),
         ("--teacher-guidance", "text_guidance", number(0, above=True, hint=" (1: no guidance)")),
         ("--group-pairs", "groups", None, True), ("--pair-batch-size", "pairs.batch_size", whole(1)),
         ("--student-steps", "student_steps", whole(1)), ("--counterfactual-swap", "counterfactual_swap", probability()),
         ("--rephrase", "rephrase", probability()), ("--batch-size", "batch_size", whole(1)),
         ("--lr", "lr", number(0, above=True)), ("--val-every", "val_every", whole(0, hint=" (0 = never)")),
         ("--seed", "seed", seed()), ("--camera", "camera"), PRECISION_MOVED]


def add_arguments(parser: argparse.ArgumentParser) -> None:
    names = add_trainer_options(
        parser, DistillConfig, FLAGS, RECIPES, required=("teacher", "pairs.out"),
        flags={"pairs.data": "--data", "pairs.out": "--pairs", "student.out": "--out"},
        types={"max_minutes": number(0), "ckpt_every": whole(0, hint=" (0 = only at the end)")})
    parser.set_defaults(flag_fields=names)
    parser.add_argument("--pairs-only", action="store_true", help="make the pairs and stop")
    add_moved_to_set(parser, DistillConfig, MOVED)


def run(args: argparse.Namespace) -> int:
    from tesseract4d.cli.config_args import recipe_from_args
    from tesseract4d.errors import UserError
    from tesseract4d.training.schedule import check_max_steps
    from tesseract4d.model.reflow import MANIFEST, ReflowTrainer, check_pairs_of_teacher, generate_pairs
    from tesseract4d.outputs import check_not_input
    from tesseract4d.stopping import raise_for_stop

    cfg = config_from_args(DistillConfig, args, args.flag_fields,
                           recipe=recipe_from_args(args, RECIPES, read_recipe)).shared()
    student, pairs = cfg.student, cfg.pairs
    if student.counterfactual_swap > 0 and not student.group_batches:  # the swap needs whole groups
        student = dataclasses.replace(student, group_batches=True)
    if not args.pairs_only and student.out is None:
        raise UserError("pass --out RUN (the student's run folder), or --pairs-only to make the pairs only")
    data = pairs.data
    # Every refusal before the teacher samples a single pair: the pairs take the longest.
    inputs = [*(data or []), student.teacher]
    check_not_input(pairs.out, inputs, "--pairs")
    if pairs.out.exists() and not pairs.out.is_dir():
        raise UserError(f"--pairs {pairs.out} is a file, not a folder; pass a folder path")
    if not args.pairs_only:
        check_not_input(student.out, [*inputs, pairs.out], "--out")
        check_max_steps(student.max_steps, student.max_minutes, resume=student.resume)
    if data is not None:
        generate_pairs(dataclasses.replace(pairs, data=data[0] if len(data) == 1 else data), progress=not student.quiet)
        print(f"pairs: {pairs.out}")
    elif args.pairs_only or not (pairs.out / MANIFEST).is_file():
        raise UserError(f"pass --data DIR: the pairs in {pairs.out} are made from a dataset folder")
    else:
        check_pairs_of_teacher(pairs.out, student.teacher, pairs.teacher_steps, pairs.text_guidance)
    if args.pairs_only:
        return 0
    from datagen.paraphrases import train_paraphrases

    trainer = ReflowTrainer(dataclasses.replace(student, data=pairs.out), train_paraphrases)
    final = trainer.train()
    print(f"student checkpoint: {final} ({student.student_steps} steps, one network pass each)")
    raise_for_stop(trainer.stopped_by)  # a stopped run ends 130 / 143, its checkpoint and export kept
    return 0


def read_recipe(checkpoint: Path) -> dict:
    """The DistillConfig values a student checkpoint records: its training options (as `train
    --recipe-from`) and how its pairs were made (``distilled_from``)."""
    from tesseract4d.cli.train import read_recipe as read_train_recipe
    from tesseract4d.model.checkpoint import read_inference_config

    student_fields = {f.name for f in dataclasses.fields(ReflowConfig)}
    values = {k: v for k, v in read_train_recipe(checkpoint).items() if k in student_fields and k != "preset"}
    made = read_inference_config(checkpoint).get("distilled_from") or {}
    for key, name in (("student_steps", "student_steps"), ("num_pairs", "num_pairs"), ("pair_groups", "groups"),
                      ("teacher_steps", "teacher_steps"), ("text_guidance", "text_guidance")):
        if made.get(key) is not None:
            values[name] = made[key]
    return values
