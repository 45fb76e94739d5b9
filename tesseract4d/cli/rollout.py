"""Closed-loop rollouts in ManiSkill on held-out seeds: motion planner, IDM + true future (oracle),
IDM + world-model predictions, and behaviour cloning, with success rates and 95 % Wilson intervals.

  tesseract4d rollout --idm runs/idm/final --bc runs/bc/final --checkpoint tesseract4d/checkpoints/v2 \\
      --tasks PushCube-v1,PullCube-v1,PickCube-v1,StackCube-v1 --episodes 50 --out out/rollouts

The env is rendered at the world model's resolution (by default) and every frame reaches the IDM
at the resolution it was trained on, resized by a whole factor: the shipped 128² models steer an IDM
trained on 64² renders.

Loop per episode: observe (RGB-D-N) -> predict the clip from the current frame and the instruction
-> back-project -> IDM -> execute the chunk -> observe; a new clip every --replan-every frames.
Writes OUT/report.json, OUT/report.md, OUT/rollout_config.json, OUT/videos/<arm>/<task>/seed_*.mp4
and OUT/viewer/<arm>/<task>/seed_*/replan_XX/{observed,predicted,predicted_clip}; look at a replan with
  tesseract4d view OUT/viewer/world_model/PushCube-v1/seed_100000/replan_00/predicted \\
      --compare OUT/viewer/world_model/PushCube-v1/seed_100000/replan_00/observed
"""

from __future__ import annotations

import argparse

from tesseract4d.cli.argument_types import seed, whole


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from tesseract4d.precision import add_precision_argument

    from datagen.generate import MAX_IMAGE_SIDE
    from tesseract4d.model.checkpoint import SHIPPED_CHECKPOINT
    from tesseract4d.policy.loop import LoopConfig
    from tesseract4d.policy.rollout_eval import ARMS, RolloutConfig

    d, lc = RolloutConfig(), LoopConfig()
    parser.add_argument("--out", required=True, help="output folder (report, videos, viewer folders)")
    parser.add_argument("--tasks", default=",".join(d.tasks), help="comma-separated task ids (default %(default)s)")
    parser.add_argument("--episodes", type=whole(1), default=d.episodes, help="held-out seeds per task and arm (default %(default)s)")
    parser.add_argument("--seed-start", type=seed(), default=d.seed_start,
                        help="first held-out seed (default %(default)s; never a training seed)")
    parser.add_argument("--arms", default=",".join(d.arms),
                        help=f"comma-separated arms from {', '.join(ARMS)} (default: %(default)s; static_world feeds "
                             f"the IDM the current frame repeated, the control for what the predicted frames add)")
    parser.add_argument("--idm", help="inverse dynamics model folder (train-idm RUN/final)")
    parser.add_argument("--bc", help="behaviour-cloning model folder (train-idm --no-future RUN/final)")
    parser.add_argument("--checkpoint", default=str(SHIPPED_CHECKPOINT),
                        help="world-model inference checkpoint (default: the shipped v2-2step, 2 steps; "
                             "tesseract4d/checkpoints/v2 takes 10 guided steps)")
    parser.add_argument("--replan-every", type=whole(1, lc.num_frames - 1, hint=f" (a clip has {lc.num_frames} frames)"),
                        default=lc.replan_every,
                        help="predicted frames executed per prediction, k (default %(default)s)")
    parser.add_argument("--max-steps", type=whole(1), default=lc.max_steps, help="env steps per episode (default %(default)s)")
    parser.add_argument("--sample-steps", type=whole(1),
                        help="diffusion steps per prediction (default: the checkpoint's, 2 for v2-2step, 10 for v2)")
    parser.add_argument("--draws", type=whole(1, hint=" (1: a single draw)"), metavar="N",
                        help="noise draws per prediction; each keeps the one whose objects (found by colour in the "
                             "observation) keep their colours best, at N times the prediction's cost (default: the "
                             "checkpoint's, 2 for the shipped models; 1 = a single draw)")
    parser.add_argument("--camera", default=lc.camera, help="camera preset (default %(default)s)")
    parser.add_argument("--resolution", type=whole(1, MAX_IMAGE_SIDE),
                        help="rendered square image size (default: the world model's with the world_model arm, else "
                             "the IDM's); the world model and the IDM each get frames at their own resolution when it "
                             "differs by a whole factor")
    parser.add_argument("--instruction-split", default=lc.instruction_split, choices=["train", "heldout"],
                        help="instruction paraphrases (default %(default)s)")
    parser.add_argument("--videos", type=whole(0), default=d.videos, help="MP4s per arm and task (default %(default)s)")
    parser.add_argument("--viewer-episodes", type=whole(0), default=d.viewer_episodes,
                        help="episodes per future arm and task written for the viewer (default %(default)s)")
    add_precision_argument(parser)
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")


def run(args: argparse.Namespace) -> int:
    from tesseract4d.policy.loop import LoopConfig
    from tesseract4d.policy.rollout_eval import RolloutConfig, run_rollouts

    loop = LoopConfig(replan_every=args.replan_every, max_steps=args.max_steps, sample_steps=args.sample_steps,
                      draws=args.draws, camera=args.camera,
                      resolution=None if args.resolution is None else (args.resolution, args.resolution),
                      instruction_split=args.instruction_split)
    cfg = RolloutConfig(tasks=[t.strip() for t in args.tasks.split(",") if t.strip()], seed_start=args.seed_start,
                        episodes=args.episodes, arms=[a.strip() for a in args.arms.split(",") if a.strip()],
                        idm=args.idm, bc=args.bc, checkpoint=args.checkpoint, out=args.out, videos=args.videos,
                        viewer_episodes=args.viewer_episodes, loop=loop, precision=args.precision)
    report = run_rollouts(cfg, progress=not args.no_progress)
    print(open(f"{args.out}/report.md").read())
    return 0 if report else 1
