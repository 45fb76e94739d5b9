"""Benchmark the skill library: planner success per skill over seeds, and render throughput.

Per skill variant (datagen/skills.py) in the tabletop scene (datagen/tabletop.py), for seeds
0..N-1: reset, pick a feasible target as datagen's groups do (drawn from the seed), plan and
execute on ManiSkill's Panda planner, judge success from object poses. "no target" counts a
seed where the scene offers no feasible target (e.g. a push path blocked by another object)
as a failure too. Then frames/s: RGB + depth + normals + segmentation of one camera at HxW,
rendered from the recorded states of the skill's last successful episode, converted to the
dataset's conventions (what datagen does per kept frame), with one rasteriser thread
(LP_NUM_THREADS=1) so the number is per core.

  .venv/bin/python benchmarks/bench_skills.py [--seeds 20] [--resolution 128] [--frames 32]
"""

from __future__ import annotations

import argparse
import os
import time

from measure import machine_line


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seeds", type=int, default=20)
    parser.add_argument("--resolution", type=int, default=128)
    parser.add_argument("--camera", default="close")
    parser.add_argument("--frames", type=int, default=32, help="frames rendered per skill for frames/s")
    parser.add_argument("--skills", default="all", help="comma-separated variants (default all)")
    args = parser.parse_args()

    os.environ.setdefault("LP_NUM_THREADS", "1")
    from tesseract4d import runtime

    runtime.configure()
    import logging
    import warnings

    import numpy as np
    import torch

    from datagen import skills as sk
    from datagen.simulate import EpisodeSimulator, SimConfig
    from datagen.tabletop import ENV_ID

    warnings.simplefilter("ignore")
    logging.getLogger("mani_skill").setLevel(logging.ERROR)
    torch.set_num_threads(1)
    names = list(sk.VARIANTS) if args.skills == "all" else args.skills.split(",")
    sim = EpisodeSimulator(ENV_ID, SimConfig(height=args.resolution, width=args.resolution, cameras=[args.camera]))
    env = sim.env
    base = env.unwrapped
    env.reset(seed=0)
    sim._renderer.set_views(base, __import__("datagen.cameras", fromlist=["episode_views"]).episode_views(
        [args.camera], ENV_ID, 0, 0.0, base_env=base))
    sim._renderer.capture(base)  # Vulkan pipeline warm-up

    rows = []
    for name in names:
        v = sk.VARIANTS[name]
        ok = no_target = 0
        plan_s, steps, states = 0.0, 0, None
        for seed in range(args.seeds):
            env.reset(seed=seed)
            cands = sk.candidates(ENV_ID, base, v)
            if not cands:
                no_target += 1
                continue
            rng = np.random.default_rng([seed, 271828])
            target, other = cands[int(rng.integers(len(cands)))]
            env.reset(seed=seed)
            intent = sk.commanded_intent(ENV_ID, base, v, target, other)
            present = intent["objects_present"]
            start = {n: sk.object_positions(ENV_ID, base)[n] for n in present}
            tcp0 = sk.tcp_position(base)
            t0 = time.perf_counter()
            try:
                sk.execute(env, ENV_ID, v, target, other)
            except Exception:  # no motion plan: a failure, counted
                plan_s += time.perf_counter() - t0
                continue
            plan_s += time.perf_counter() - t0
            end = {n: sk.object_positions(ENV_ID, base)[n] for n in present}
            out = sk.check_intent(intent, start, end, tcp0, sk.tcp_position(base), sk.is_grasping(ENV_ID, base, target))
            if out["success"]:
                ok += 1
                steps += len(env.actions)
                states = list(env.states)
        fps = float("nan")
        if states:
            t0 = time.perf_counter()
            for i in range(args.frames):
                base.set_state_dict(states[int(i * (len(states) - 1) / max(args.frames - 1, 1))])
                sim._renderer.capture(base)
            fps = args.frames / (time.perf_counter() - t0)
        rows.append((name, ok, args.seeds, no_target, plan_s / args.seeds, steps / max(ok, 1), fps))
        print(f"  {name}: {ok}/{args.seeds}", flush=True)
    sim.close()

    print(f"\nSkills in {ENV_ID}, {args.seeds} seeds each; frames/s = RGB-D-N + segmentation, camera "
          f"'{args.camera}', {args.resolution}x{args.resolution}, 1 rasteriser thread")
    print(machine_line())
    print(f"| {'skill':<14} | {'planner success':>15} | {'no target':>9} | {'plan s/seed':>11} | {'sim steps':>9} | {'frames/s':>8} |")
    print(f"|{'-' * 16}|{'-' * 17}|{'-' * 11}|{'-' * 13}|{'-' * 11}|{'-' * 10}|")
    for name, ok, n, nt, ps, st, fps in rows:
        print(f"| {name:<14} | {f'{ok}/{n} ({100 * ok / n:.0f} %)':>15} | {nt:>9} | {ps:>11.2f} | {st:>9.0f} | {fps:>8.1f} |")


if __name__ == "__main__":
    main()
