"""Generate RGB-D-N episodes with ManiSkill's motion planners (CPU physics, CPU rendering).

Keeps successful episodes only: --episodes is the number of successes wanted per task, seeds
are tried in order from --seed-start, at most `--set max_attempts=N` per task (default 4*N+4). Every
attempt is logged in DIR/datagen_attempts.jsonl, so rerunning the same command resumes:
finished episodes and failed seeds are not redone. At the end the per-task planner success
rates are printed and written to DIR/datagen_report.json; the resolved options go to
DIR/datagen_config.json.

Example (training data for the tiny model):
  tesseract4d datagen --tasks PickCube-v1,PushCube-v1 --episodes 200 --out data/train \\
      --resolution 64 --frames 16 --cameras close --workers 2

Counterfactual groups (one initial state, K futures chosen by the instruction): in the project's
multi-object scene Tesseract4dTabletop-v1, or in PickCube/PushCube/PullCube/StackCube with
--skills or --instructions-per-scene, every seed is rendered under K distinct skills
(--episodes then counts scenes; each scene gives K episodes seed_<S>_k<k>.h5):
  tesseract4d datagen --tasks Tesseract4dTabletop-v1 --instructions-per-scene 4 --episodes 100 \\
      --out data/skills --workers 2

Scene randomisation and the other options of the run are fields of DatagenConfig and SimConfig, set
with `--set NAME=VALUE` (`--set list` prints them): e.g. `--set randomize_colors=true`,
`--set randomize_lighting=true`, `--set camera_jitter_m=0.02`, `--set goal_marker=true`,
`--set max_attempts=N`, `--set previews=false`, and `--set ray_address=HOST:PORT` (a running Ray
cluster for --workers; default: a local Ray instance).
"""

from __future__ import annotations

import argparse
from pathlib import Path

from datagen.cameras import PRESETS, parse_camera_list
from datagen.generate import DatagenConfig, format_report, run_datagen
from datagen.instructions import SPLITS
from datagen.simulate import SimConfig
from datagen.tasks import parse_task_list, valid_task_ids
from tesseract4d.cli.config_args import add_deprecated, add_set_option
from tesseract4d.configs import with_overrides
from tesseract4d.errors import UserError


def add_arguments(parser: argparse.ArgumentParser) -> None:
    d = SimConfig()
    parser.add_argument("--tasks", required=True,
                        help=f"comma-separated task ids, or 'all' ({', '.join(valid_task_ids())})")
    parser.add_argument("--episodes", type=int, required=True, help="successful episodes wanted per task (with skills: scenes, each giving K episodes)")
    parser.add_argument("--out", type=Path, required=True, help="dataset folder (created, or resumed if it exists)")
    parser.add_argument("--resolution", type=int, default=None,
                        help=f"square image size in pixels, e.g. 64 or 128 (default {d.height})")
    parser.add_argument("--cameras", default=",".join(d.cameras),
                        help=f"comma-separated camera presets from {', '.join(PRESETS)} (default %(default)s)")
    parser.add_argument("--frames", type=int, default=d.frames,
                        help="evenly spaced frames kept per episode, first and last included; 0 = every step "
                             "(default %(default)s)")
    parser.add_argument("--seed-start", type=int, default=0, help="first seed tried per task (default %(default)s)")
    parser.add_argument("--workers", type=int, default=1,
                        help="parallel workers: local processes, or Ray workers with `--set ray_address=HEAD:PORT` "
                             "(a Ray cluster across machines, docs/ray_cluster.md) (default %(default)s)")
    parser.add_argument("--instruction-split", choices=SPLITS, default=d.instruction_split,
                        help="instruction paraphrases to draw from (default %(default)s; 'heldout' is kept for evaluation)")
    from datagen.skills import VARIANTS

    parser.add_argument("--instructions-per-scene", type=int, default=1, metavar="K",
                        help="render each initial state under K distinct skills (a counterfactual group; the K first "
                             "frames are identical). K > 1 needs a scene the skills run in (default %(default)s)")
    parser.add_argument("--skills", default=None,
                        help="comma-separated skill variants the groups draw from, each optionally pinned to an object "
                             f"as VARIANT@OBJECT (default: all that apply): {', '.join(VARIANTS)}")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    add_set_option(parser, DatagenConfig)
    # Options now set as `--set NAME=VALUE`; the old flags keep working for one release.
    for old, name, kind in (("--height", "height", int), ("--width", "width", int),
                            ("--max-attempts", "max_attempts", int), ("--camera-jitter", "camera_jitter_m", float),
                            ("--ray-address", "ray_address", str)):
        add_deprecated(parser, old, use=f"--set {name}=VALUE", set_field=name, config_class=DatagenConfig, type=kind)
    for old, name in (("--randomize-lighting", "randomize_lighting"), ("--randomize-colors", "randomize_colors"),
                      ("--goal-marker", "goal_marker"), ("--no-previews", "previews")):
        value = name != "previews"
        add_deprecated(parser, old, use=f"--set {name}={str(value).lower()}", set_field=name,
                       config_class=DatagenConfig, switch=value)


def config_from_args(args: argparse.Namespace) -> DatagenConfig:
    size = args.resolution if args.resolution is not None else SimConfig().height
    if args.resolution is not None and args.resolution <= 0:
        raise UserError(f"--resolution must be positive, got {args.resolution}")
    sim = SimConfig(
        height=size, width=size, cameras=parse_camera_list(args.cameras), frames=args.frames,
        instruction_split=args.instruction_split,
    )
    cfg = DatagenConfig(
        tasks=parse_task_list(args.tasks), episodes=args.episodes, out=args.out, sim=sim,
        seed_start=args.seed_start, workers=args.workers,
        instructions_per_scene=args.instructions_per_scene, skills=_skills(args.skills, args.tasks),
    )
    return with_overrides(cfg, args.set_overrides)


def _skills(text: str | None, tasks: str) -> list[str] | None:
    from datagen.skills import parse_skill_list

    if text is None:
        return None
    return parse_skill_list(text, parse_task_list(tasks))


def run(args: argparse.Namespace) -> int:
    cfg = config_from_args(args)
    report = run_datagen(cfg, progress=not args.quiet)
    print(format_report(report))
    incomplete = [t for t, r in report["tasks"].items() if not r["complete"]]
    if incomplete:
        print(f"warning: {', '.join(incomplete)} reached max_attempts before {cfg.episodes} successes; "
              f"raise --set max_attempts=N to try more seeds")
    print(f"dataset: {cfg.out}  (inspect with `tesseract4d dataset info {cfg.out}`)")
    return 0
