"""Closed-loop rollouts in ManiSkill on held-out seeds: motion planner, IDM + true future (oracle),
IDM + world-model predictions, and behaviour cloning, with success rates and 95 % Wilson intervals.

  tesseract4d rollout --idm runs/idm/final --bc runs/bc/final --checkpoint tesseract4d/checkpoints/v2 \\
      --tasks PushCube-v1,PullCube-v1,PickCube-v1,StackCube-v1 --episodes 50 --out out/rollouts

The env is rendered at the world model's resolution (by default) and every frame reaches the IDM
at the resolution it was trained on, resized by a whole factor: the shipped 128² models steer an IDM
trained on 64² renders.

Loop per episode: observe (RGB-D-N) -> predict the clip from the current frame and the instruction
-> back-project -> IDM -> execute the chunk -> observe; a new clip every `--set replan_every=K` frames.
The plan arms (world_model_plan, oracle_plan, words_plan) instead read where the future's object layer
puts the moved object and run a motion-planned primitive toward it from the perceived poses, up to
`--set plan_replans=N` times.
Writes OUT/report.json, OUT/report.md, OUT/rollout_config.json, OUT/videos/<arm>/<task>/seed_*.mp4
and OUT/viewer/<arm>/<task>/seed_*/replan_XX/{observed,predicted,predicted_clip}; look at a replan with
  tesseract4d view OUT/viewer/world_model/PushCube-v1/seed_100000/replan_00/predicted \\
      --compare OUT/viewer/world_model/PushCube-v1/seed_100000/replan_00/observed
"""

from __future__ import annotations

import argparse

from tesseract4d.cli.argument_types import seed, whole
from tesseract4d.cli.config_args import PRECISION_MOVED, add_deprecated, add_moved_to_set, add_set_option


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from datagen.generate import MAX_IMAGE_SIDE
    from tesseract4d.model.checkpoint import SHIPPED_CHECKPOINT
    from tesseract4d.policy.loop import LoopConfig
    from tesseract4d.policy.rollout_eval import ARMS, RolloutConfig

    d, lc = RolloutConfig(), LoopConfig()
    parser.add_argument("--out", required=True, help="output folder (report, videos, viewer folders)")
    parser.add_argument("--tasks", default=",".join(d.tasks), help="comma-separated task ids (default %(default)s)")
    parser.add_argument("--episodes", type=whole(1), default=d.episodes, help="held-out seeds per task and arm (default %(default)s)")
    parser.add_argument("--arms", default=",".join(d.arms),
                        help=f"comma-separated arms from {', '.join(ARMS)} (default: %(default)s; static_world feeds "
                             f"the IDM the current frame repeated, the control for what the predicted frames add; the "
                             f"*_plan arms need no IDM: they read the goal from a future's objects, or the words, and "
                             f"run motion-planned primitives; every arm also runs the tabletop's skills, task "
                             f"Tesseract4dTabletop-v1, the IDM arms with an IDM trained on tabletop episodes)")
    parser.add_argument("--idm", help="inverse dynamics model folder (train-idm RUN/final)")
    parser.add_argument("--bc", help="behaviour-cloning model folder (RUN/final of `train-idm --recipe bc`)")
    parser.add_argument("--checkpoint", default=str(SHIPPED_CHECKPOINT),
                        help="world-model inference checkpoint (default: the shipped v2-2step, 2 steps; "
                             "tesseract4d/checkpoints/v2 takes 10 guided steps)")
    parser.add_argument("--max-sim-steps", type=whole(1), default=lc.max_steps, dest="max_sim_steps",
                        help="simulator steps per episode before it counts as failed (default %(default)s)")
    parser.add_argument("--steps", type=whole(1),
                        help="sampler steps per prediction (default: the checkpoint's, 2 for v2-2step, 10 for v2)")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    add_set_option(parser, RolloutConfig)
    # Old spellings, kept for one release.
    add_deprecated(parser, "--max-steps", use="--max-sim-steps", dest="max_sim_steps", type=whole(1))
    add_deprecated(parser, "--sample-steps", use="--steps", dest="steps", type=whole(1))
    add_deprecated(parser, "--no-progress", use="--quiet", dest="quiet", switch=True)
    add_deprecated(parser, "--replan-every", use="--set replan_every=K", set_field="replan_every",
                   config_class=RolloutConfig,
                   type=whole(1, lc.num_frames - 1, hint=f" (a clip has {lc.num_frames} frames)"))
    add_deprecated(parser, "--draws", use="--set draws=N", set_field="draws", config_class=RolloutConfig,
                   type=whole(1, hint=" (1: a single draw)"))
    add_deprecated(parser, "--camera", use="--set camera=NAME", set_field="camera", config_class=RolloutConfig)
    add_deprecated(parser, "--resolution", use="--set resolution=H,W", set_field="resolution",
                   config_class=RolloutConfig, type=_square(MAX_IMAGE_SIDE))
    add_deprecated(parser, "--instruction-split", use="--set instruction_split=NAME", set_field="instruction_split",
                   config_class=RolloutConfig, choices=["train", "heldout"])
    add_moved_to_set(parser, RolloutConfig, [("--videos", "videos", whole(0)), PRECISION_MOVED,
                                             ("--seed-start", "seed_start", seed())])
    add_deprecated(parser, "--viewer-episodes", use="--set viewer_episodes=N", set_field="viewer_episodes",
                   config_class=RolloutConfig, type=whole(0))


def _square(high: int):
    side = whole(1, high)

    def parse(text: str) -> tuple[int, int]:
        n = side(text)
        return (n, n)

    parse.__name__ = "whole number"
    return parse


def run(args: argparse.Namespace) -> int:
    from tesseract4d.policy.loop import LoopConfig
    from tesseract4d.policy.rollout_eval import RolloutConfig, run_rollouts

    from tesseract4d.configs import with_overrides

    # resolution None: the world model's with the world_model arm, else the IDM's (unless --set resolution=H,W)
    loop = LoopConfig(max_steps=args.max_sim_steps, sample_steps=args.steps, resolution=None)
    cfg = RolloutConfig(tasks=[t.strip() for t in args.tasks.split(",") if t.strip()],
                        episodes=args.episodes, arms=[a.strip() for a in args.arms.split(",") if a.strip()],
                        idm=args.idm, bc=args.bc, checkpoint=args.checkpoint, out=args.out, loop=loop)
    cfg = with_overrides(cfg, args.set_overrides)
    report = run_rollouts(cfg, progress=not args.quiet)
    print(open(f"{args.out}/report.md").read())
    return 0 if report else 1
