"""Benchmark a long rollout as it streams: seconds until the first clip's frames are decoded, seconds
per clip after it, and frames per second over the whole rollout (default 64 frames at the checkpoint's
resolution: five 16-frame clips, each continuing from the last frame of the one before).

The first frame is a synthetic scene at the checkpoint's resolution (speed does not depend on the
content) or frame 0 of --episode (a chained episode is predicted with its instruction schedule). Rows:
one noise draw per rollout, and the checkpoint preset's draws (the shipped default keeps the better
of 2, so `predict` pays twice the sampling). The first line names the CPU, its ISA and the precision.

  .venv/bin/python benchmarks/bench_horizon.py [--checkpoint tesseract4d/checkpoints/v2] [--frames 64] [--steps 1] [--repeats 2]
  .venv/bin/python benchmarks/bench_horizon.py --episode data/heldout_chained/Tesseract4dTabletop-v1/100001
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from measure import add_pipeline_arguments, load_benchmark_pipeline, machine_line, print_table


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_pipeline_arguments(parser)
    parser.add_argument("--frames", type=int, default=64, help="frames per rollout (default %(default)s)")
    parser.add_argument("--repeats", type=int, default=2, help="timed rollouts per row (median)")
    parser.add_argument("--episode", help="first frame (and schedule) from this dataset episode instead of a synthetic one")
    args = parser.parse_args(argv)
    pipe = load_benchmark_pipeline(args)
    from tesseract4d import dataset_format as df
    from tesseract4d.instruction_schedule import clip_new_frames, schedule_of
    from tesseract4d.model.predict import predict_scenes
    from tesseract4d.testing.synthetic_scene import _segment, synthetic_episode

    p = pipe.preset
    clips = len(clip_new_frames(args.frames, p.num_frames, p.history_frames))
    steps = args.steps or p.num_steps
    print(f"checkpoint {args.checkpoint}: {p.name} {p.height}x{p.width}, clips of {p.num_frames} frames, {steps} "
          f"steps; a {args.frames}-frame rollout is {clips} clips")
    if args.episode:
        path = df.resolve_episode(args.episode)
        first = df.read_episode(path, frames=slice(0, 1))
        schedule = schedule_of(first.metadata)
    else:
        first, schedule = _segment(synthetic_episode(0, frames=1, size=p.height)), None
    predict_scenes(pipe, [first], [first.instruction], num_frames=p.num_frames, draws=1)  # warm-up

    def rollout(draws: int, seed: int) -> list[float]:
        """Seconds from the call to each clip's decoded frames; the last is the whole rollout."""
        marks: list[float] = []
        original = pipe.decode

        def timed_decode(*a, **kw):
            out = original(*a, **kw)
            marks.append(time.perf_counter() - t0)
            return out

        pipe.decode = timed_decode
        try:
            t0 = time.perf_counter()
            predict_scenes(pipe, [first], [first.instruction], num_frames=args.frames, seed=seed, draws=draws,
                           num_steps=steps, schedules=[schedule])
            marks.append(time.perf_counter() - t0)
        finally:
            pipe.decode = original
        return marks

    rows = []
    for draws in sorted({1, p.draws}):
        runs = [rollout(draws, r) for r in range(args.repeats)]
        first_clip = statistics.median(r[0] for r in runs)  # the first draw's first clip
        total = statistics.median(r[-1] for r in runs)
        per_clip = (total - first_clip) / max(clips * draws - 1, 1)
        rows.append((str(draws), f"{first_clip:.2f}", f"{per_clip:.2f}", f"{total:.2f}",
                     f"{args.frames / total:.1f}"))
        print(*rows[-1], sep=" | ", flush=True)
    print()
    print(machine_line())
    print_table(("draws", "s to first clip", "s per later clip", f"s for {args.frames} frames", "frames/s"), rows)
    return 0


if __name__ == "__main__":
    sys.exit(main())
