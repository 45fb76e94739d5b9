"""How often can a policy that sees only PickCube's first frame and its instruction reach the goal?

ManiSkill's PickCube-v1 asks for the cube within ``goal_thresh`` (2.5 cm) of a goal point drawn anew
per seed, and hides that point from every sensor camera: it shows in no frame the world model sees or
predicts. The instruction datagen writes for it gives the goal only in words: a direction in the
table plane ("forward and to the left", or none) and one of three heights ("slightly", "up", "high";
datagen/instructions.py). So whatever a world model predicts from the first frame and the words, the
goal it can act on is at best the one displacement per wording that most often lands within reach.

This draws the scenes of ``--seeds`` seeds (resets only, nothing rendered), puts each in the class of
its wording, picks on the first half the displacement per class that is within ``goal_thresh`` of the
most others, and counts on the second half how often it is within ``goal_thresh`` of the true goal:
the ceiling of any policy without the goal's position, the plan arms' world model included. A policy
told the goal (the oracle future, the motion planner) is not bound by it.

  .venv/bin/python benchmarks/measure_pickcube_goal.py --seeds 2000
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from measure import print_table  # noqa: E402

FIRST_SEED = 300000  # outside the validation and test seed ranges: scenes only, no model is scored


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     epilog=__doc__.split("\n\n", 1)[1], formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seeds", type=int, default=2000, help="scenes drawn, half to choose, half to score (default %(default)s)")
    args = parser.parse_args(argv)
    if args.seeds < 4:
        parser.error("--seeds needs at least 4 (half to choose, half to score)")

    import numpy as np

    from tesseract4d import runtime

    runtime.configure()
    import gymnasium as gym
    import mani_skill.envs  # noqa: F401  (registers the ManiSkill tasks)
    from tqdm import tqdm

    from datagen.instructions import direction_words, height_words
    from datagen.simulate import ENV_KWARGS

    env = gym.make("PickCube-v1", **ENV_KWARGS)
    displacement, wording = [], []
    for s in tqdm(range(args.seeds), desc="PickCube scenes", unit="scene"):
        env.reset(seed=FIRST_SEED + s)
        u = env.unwrapped
        d = (u.goal_site.pose.p[0] - u.cube.pose.p[0]).cpu().numpy().astype(np.float64)
        displacement.append(d)
        wording.append(f"{direction_words(d[:2])} | {height_words(float(d[2]))}")
    thresh = float(u.goal_thresh)
    env.close()
    displacement, wording = np.array(displacement), np.array(wording)
    half = args.seeds // 2
    choose, score = np.arange(half), np.arange(half, args.seeds)
    rows, hits = [], 0
    for w in sorted(set(wording)):
        c, s = choose[wording[choose] == w], score[wording[score] == w]
        if len(s) == 0:
            continue
        if len(c) == 0:
            rows.append((w, 0, len(s), 0))
            continue
        cand = displacement[c]
        near = (np.linalg.norm(cand[:, None] - cand[None], axis=2) < thresh).sum(axis=1)
        best = cand[near.argmax()]
        h = int((np.linalg.norm(displacement[s] - best, axis=1) < thresh).sum())
        hits += h
        rows.append((w, len(c), len(s), h))
    print(f"PickCube-v1, goal within {100 * thresh:.1f} cm, seeds {FIRST_SEED}-{FIRST_SEED + args.seeds - 1}")
    print_table(("wording (direction | height)", "scenes to choose", "scenes scored", "reached"), rows)
    print(f"best goal from the first frame and the words: {hits} of {len(score)} = {hits / len(score):.3f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
