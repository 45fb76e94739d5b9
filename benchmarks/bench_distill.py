"""Benchmark a distilled student against its teacher on held-out first frames: quality and speed.

For every held-out episode (first frame + instruction, same initial noise per scene for every
model), the teacher samples its reference clip with its preset's steps and guidance; the student
(`tesseract4d distill`) and, for comparison, the teacher itself then sample with 1/2/4 steps (the
student without guidance, one network pass per step; the teacher with its guidance). Reported: RGB
PSNR (dB, frames 1..T-1) against the teacher's reference over all pixels and over the pixels that
move in the reference (tesseract4d.evaluation.metrics.moving_region_mask), the same against the
ground truth, and seconds per clip (predict_scenes, all scenes in one call). A PNG strip of the
first scene (rows: ground truth, teacher reference, student and teacher at each step count) goes
to --strip.

  .venv/bin/python benchmarks/bench_distill.py --teacher tesseract4d/checkpoints/v2 \
      --student tesseract4d/checkpoints/v2-2step --data data/heldout [--steps 1,2,4] [--strip strip.png]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from measure import add_isa_cap_argument, apply_isa_cap, machine_line, print_table


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--teacher", type=Path, required=True)
    parser.add_argument("--student", type=Path, required=True)
    parser.add_argument("--data", type=Path, required=True, help="held-out dataset folder (ground truth)")
    parser.add_argument("--steps", default="1,2,4")
    parser.add_argument("--max-episodes", type=int, default=8)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--strip", type=Path, help="PNG of the first scene's frames")
    add_isa_cap_argument(parser)
    args = parser.parse_args(argv)
    apply_isa_cap(args.cap_isa)

    from tesseract4d import runtime

    runtime.configure()
    import numpy as np

    from tesseract4d import dataset_format as df
    from tesseract4d.evaluation.metrics import moving_region_mask, rgb_psnr
    from tesseract4d.model.predict import load_pipeline, predict_scenes

    teacher, student = load_pipeline(args.teacher), load_pipeline(args.student)
    camera = teacher.camera_name
    paths = df.list_episode_files(args.data)[: args.max_episodes]
    gts = [df.read_episode(p, cameras=[camera]) for p in paths]
    T = teacher.num_frames
    firsts = [df.Episode(env_id=g.env_id, seed=g.seed, instruction=g.instruction,
                         cameras={camera: g.cameras[camera]}, frame_steps=g.frame_steps[:1]) for g in gts]
    texts = [g.instruction for g in gts]

    def run(pipe, steps):
        t0 = time.perf_counter()
        # One noise draw each: the student's clip against the teacher's from the same noise.
        eps = predict_scenes(pipe, firsts, texts, batch_size=len(firsts), seed=args.seed, num_steps=steps, num_frames=T,
                             draws=1)
        return [e.cameras[camera] for e in eps], (time.perf_counter() - t0) / len(firsts)

    def scores(pred, refs):
        out = []
        for p, r in zip(pred, refs):
            moving = moving_region_mask(r)[1:]
            out.append((rgb_psnr(p.rgb[1:], r.rgb[1:]), rgb_psnr(p.rgb[1:], r.rgb[1:], mask=moving) if moving.any() else np.nan))
        return np.nanmean(np.array(out), axis=0)

    gt_cams = []
    for g in gts:
        c = g.cameras[camera]
        gt_cams.append(df.CameraFrames(rgb=c.rgb[:T], depth_m=c.depth_m[:T], normal_cam=c.normal_cam[:T],
                                       K=c.K[:T], T_world_cam=c.T_world_cam[:T]))
    for pipe in (teacher, student):  # warm-up (allocations, text encoding)
        predict_scenes(pipe, firsts[:1], texts[:1], num_steps=1, draws=1)
    ref, ref_s = run(teacher, teacher.preset.num_steps)
    p = teacher.preset
    rows = [(f"teacher {p.num_steps} steps, guidance {p.text_guidance}/{p.image_guidance}", "-", "-",
             *(f"{v:.2f}" for v in scores(ref, gt_cams)), f"{ref_s:.2f}")]
    strip_rows = [gt_cams[0].rgb, ref[0].rgb]
    for k in [int(s) for s in args.steps.split(",")]:
        for name, pipe in (("student", student), ("teacher", teacher)):
            pred, s = run(pipe, k)
            q = pipe.preset
            g = "no guidance" if q.text_guidance == q.image_guidance == 1.0 else f"guidance {q.text_guidance}/{q.image_guidance}"
            rows.append((f"{name} {k} steps, {g}", *(f"{v:.2f}" for v in scores(pred, ref)),
                         *(f"{v:.2f}" for v in scores(pred, gt_cams)), f"{s:.2f}"))
            strip_rows.append(pred[0].rgb)
            print(*rows[-1], sep=" | ", flush=True)
    header = ("sampler", "PSNR vs teacher", "moving", "PSNR vs GT", "moving", "s/clip")
    print()
    print(machine_line(f"{len(firsts)} held-out scenes from {args.data}", f"student {args.student}"))
    print_table(header, rows)
    if args.strip is not None:
        import imageio.v3 as iio

        cols = list(range(0, T, max(1, T // 6)))
        img = np.concatenate([np.concatenate([r[c] for c in cols], axis=1) for r in strip_rows], axis=0)
        iio.imwrite(args.strip, img)
        print(f"strip: {args.strip} (rows: ground truth, teacher reference, then "
              f"{', '.join(f'student {k}, teacher {k}' for k in args.steps.split(','))}; columns: frames {cols})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
