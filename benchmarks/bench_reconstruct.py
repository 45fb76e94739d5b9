"""Benchmark 4D reconstruction: seconds per 16-frame clip for each stage, at 64^2 and 128^2.

Scene: the analytic table + sliding box (tests/synthetic_scene.py: analytic_episode) with depth corrupted
by 1 % noise and a per-frame scale/shift wobble (flickering_depth, same module). Stages
(reconstruction.reconstruct.STAGES): flow (DIS flow + dynamic masks), normal_terms (normal
integration rows), temporal_terms (consistency rows), solve (joint sparse least squares),
points (world points, colours, normals), tsdf (Open3D VoxelBlockGrid fusion + mesh).
The first call pays the imports (OpenCV, SciPy, Open3D); it is reported apart and not in the
median. Also prints the Chamfer distance of plain back-projection and of the refined cloud.

  .venv/bin/python benchmarks/bench_reconstruct.py [--sizes 64,128] [--frames 16] [--repeats 3] [--json out.json]
"""

from __future__ import annotations

import argparse
import json
import statistics
import time

from measure import machine_line


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sizes", default="64,128", help="comma-separated square image sizes")
    parser.add_argument("--frames", type=int, default=16)
    parser.add_argument("--repeats", type=int, default=3, help="timed runs per size after the warm-up")
    parser.add_argument("--json", help="also write the results here")
    args = parser.parse_args()

    from tesseract4d import runtime

    runtime.configure()
    start = time.perf_counter()
    from tesseract4d.evaluation.episode import evaluate_episode
    from reconstruction.reconstruct import STAGES, ReconConfig, reconstruct_episode

    from tesseract4d.testing.synthetic_scene import analytic_episode, flickering_depth

    results = {"frames": args.frames, "sizes": {}}
    first = True
    for size in [int(s) for s in args.sizes.split(",")]:
        gt = analytic_episode(num_frames=args.frames, height=size, width=size)
        noisy = flickering_depth(gt)
        if first:
            reconstruct_episode(noisy)
            results["first_call_s_incl_imports"] = round(time.perf_counter() - start, 3)
            first = False
        runs = []
        for _ in range(args.repeats):
            t0 = time.perf_counter()
            recon = reconstruct_episode(noisy)
            total = time.perf_counter() - t0
            runs.append({**recon.metadata["timings_s"], "total": total})
        median = {k: statistics.median(r[k] for r in runs) for k in (*STAGES, "total")}
        raw = reconstruct_episode(noisy, config=ReconConfig(refine=False, fuse_background=False))
        chamfer_raw = evaluate_episode(raw, gt)["mean"]["chamfer_l1_m"]
        chamfer_refined = evaluate_episode(recon, gt)["mean"]["chamfer_l1_m"]
        results["sizes"][size] = {
            "seconds": {k: round(v, 4) for k, v in median.items()},
            "solver_iterations": recon.metadata["solver"]["iterations"],
            "points_per_frame": int(sum(len(p) for p in recon.points_world) / recon.num_frames),
            "background_points": int(len(recon.background_points)), "mesh_faces": int(len(recon.mesh_faces)),
            "chamfer_raw_m": chamfer_raw, "chamfer_refined_m": chamfer_refined,
        }

    print(f"first call (imports + {args.sizes.split(',')[0]}^2 clip): {results['first_call_s_incl_imports']:.2f} s")
    header = f"{'size':>6}" + "".join(f"{s:>15}" for s in (*STAGES, "total")) + f"{'CG iters':>10}{'Chamfer mm raw->refined':>26}"
    print(machine_line())
    print(f"median seconds per {args.frames}-frame clip over {args.repeats} runs")
    print(header)
    for size, r in results["sizes"].items():
        s = r["seconds"]
        print(f"{str(size) + '^2':>6}" + "".join(f"{s[k]:>15.3f}" for k in (*STAGES, "total"))
              + f"{r['solver_iterations']:>10}" + f"{1000 * r['chamfer_raw_m']:>14.2f} -> {1000 * r['chamfer_refined_m']:.2f}")
    if args.json:
        with open(args.json, "w") as f:
            json.dump(results, f, indent=2)


if __name__ == "__main__":
    main()
