"""Benchmark batched prediction: clips per second for N scenes sampled per pipeline call.

`predict_scenes(pipeline, first_frames, instructions, batch_size=N)` samples N scenes (first frame +
instruction) in one call of the pipeline; this measures clips/s and seconds per call for N = 1, 2,
4, 8 on a checkpoint (default: the shipped default, v2-2step) at its preset's steps and guidance, or with
--steps/--no-guidance (e.g. a distilled student). First frames are synthetic scenes at the
checkpoint's resolution: speed does not depend on the content. The first line names the CPU model
and ISA and the precision used.

One noise draw per clip (the network's cost) unless --draws N: then each scene's first frame has a
segmentation (its square is a scene object) and every future is the best of N draws
(draw_choice.py), N times the sampling plus the choice, as `predict` and `demo` sample a
checkpoint whose preset has N draws.

  .venv/bin/python benchmarks/bench_throughput.py [--checkpoint tesseract4d/checkpoints/v2] [--batches 1,2,4,8] [--cap-isa avx2]
  .venv/bin/python benchmarks/bench_throughput.py --batches 1 --draws 2
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path
from measure import add_pipeline_arguments, load_benchmark_pipeline, machine_line, print_table

ROOT = Path(__file__).resolve().parent.parent


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_pipeline_arguments(parser)
    parser.add_argument("--batches", default="1,2,4,8", help="scenes per pipeline call (default %(default)s)")
    parser.add_argument("--repeats", type=int, default=2, help="timed calls per batch size (median)")
    parser.add_argument("--draws", type=int, default=1, help="noise draws per future, the best kept (default %(default)s)")
    args = parser.parse_args(argv)
    pipe = load_benchmark_pipeline(args)
    from tesseract4d.testing.synthetic_scene import _segment, synthetic_episode

    from tesseract4d.model.pipeline import guidance_passes
    from tesseract4d.model.predict import predict_scenes

    p = pipe.preset
    steps = args.steps or p.num_steps
    passes = len(guidance_passes(p.text_guidance, p.image_guidance))
    print(f"checkpoint {args.checkpoint}: {p.name} {p.height}x{p.width}, {p.num_frames} frames, {steps} steps x "
          f"{passes} network pass(es), {args.draws} noise draw(s) per future")
    batches = [int(b) for b in args.batches.split(",")]
    scenes = [synthetic_episode(i, frames=1, size=p.height) for i in range(max(batches))]
    if args.draws > 1:  # a segmentation, so that the draws are scored and one kept
        scenes = [_segment(s) for s in scenes]
    texts = [s.instruction for s in scenes]
    predict_scenes(pipe, scenes[:1], texts[:1], num_steps=1, draws=1)  # warm-up
    rows = []
    for n in batches:
        times = []
        for r in range(args.repeats):
            t0 = time.perf_counter()
            predict_scenes(pipe, scenes[:n], texts[:n], batch_size=n, num_steps=steps, seed=r, draws=args.draws)
            times.append(time.perf_counter() - t0)
        s = statistics.median(times)
        rows.append((str(n), f"{s:.2f}", f"{s / n:.2f}", f"{n / s:.3f}"))
        print(*rows[-1], sep=" | ", flush=True)
    header = ("scenes per call", "s per call", "s per clip", "clips/s")  # a clip: one predicted future
    print()
    print(machine_line())
    print_table(header, rows)
    return 0


if __name__ == "__main__":
    sys.exit(main())
