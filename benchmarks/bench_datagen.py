"""Benchmark RGB-D-N(-seg) capture of datagen: frames/s per worker and scaling over local worker
processes (what `datagen --workers K` starts: no server, nothing listens).

What one "frame" is: for one camera at HxW, set the recorded simulator state, render RGB, depth,
normals and segmentation, and convert them to the dataset's conventions (depth_m, normal_cam,
K, T_world_cam) — exactly what datagen does per kept frame. Steady state: each worker first
plans one PickCube episode and renders it once (Vulkan pipeline warm-up, ~4 s per process).

  .venv/bin/python benchmarks/bench_datagen.py [--resolution 128] [--frames 150] [--workers 1,2]
"""

from __future__ import annotations

import argparse
import os
import time

from measure import machine_line


class BenchWorker:
    """Plans one episode, then renders its recorded states over and over."""

    def __init__(self, env_id: str, resolution: int, camera: str, render_threads: int | None = None):
        from tesseract4d import runtime

        runtime.configure()
        if render_threads:
            os.environ.setdefault("LP_NUM_THREADS", str(render_threads))
        import logging

        import torch

        logging.getLogger("mani_skill").setLevel(logging.ERROR)
        torch.set_num_threads(1)
        from datagen.simulate import EpisodeSimulator, SimConfig

        self.sim = EpisodeSimulator(env_id, SimConfig(height=resolution, width=resolution, cameras=[camera], frames=0))
        seed = 0
        while True:
            res = self.sim.run(seed)
            if res.success:
                break
            seed += 1
        self.plan_s, self.steps = res.plan_s, res.num_steps
        self.states = list(self.sim.env.states)

    def info(self) -> dict:
        return {"plan_s": self.plan_s, "steps": self.steps}

    def render(self, n: int) -> float:
        """Render n frames (cycling over the episode's states); returns seconds taken."""
        base = self.sim.env.unwrapped
        renderer = self.sim._renderer
        t0 = time.perf_counter()
        for i in range(n):
            base.set_state_dict(self.states[i % len(self.states)])
            renderer.capture(base)
        return time.perf_counter() - t0


def _measure(env_id: str, resolution: int, camera: str, render_threads: int, frames: int, start, results) -> None:
    """One worker process: plan and warm up, wait for the others, render ``frames`` frames."""
    worker = BenchWorker(env_id, resolution, camera, render_threads)
    worker.render(10)
    start.wait()
    results.put(worker.render(frames))
    worker.sim.close()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--task", default="PickCube-v1")
    parser.add_argument("--resolution", type=int, default=128)
    parser.add_argument("--camera", default="close")
    parser.add_argument("--frames", type=int, default=150, help="frames rendered per worker per measurement")
    parser.add_argument("--workers", default="1,2", help="worker-process counts to measure")
    args = parser.parse_args()

    from tesseract4d import runtime

    runtime.configure()
    rows = []
    # In-process: the per-worker number without any Ray overhead.
    w = BenchWorker(args.task, args.resolution, args.camera)
    w.render(10)
    dt = w.render(args.frames)
    rows.append(("in-process", 1, args.frames, dt, args.frames / dt))
    plan = w.info()
    w.sim.close()
    del w

    import multiprocessing as mp

    cpus = os.cpu_count() or 1
    ctx = mp.get_context("spawn")  # a fresh interpreter per worker, as datagen's worker processes
    for k in [int(x) for x in args.workers.split(",")]:
        start, results = ctx.Barrier(k + 1), ctx.Queue()
        procs = [ctx.Process(target=_measure, args=(args.task, args.resolution, args.camera, max(1, cpus // k),
                                                    args.frames, start, results), daemon=True) for _ in range(k)]
        for p in procs:
            p.start()
        try:
            start.wait(timeout=600)  # every worker planned and warm
            t0 = time.perf_counter()
            for _ in range(k):
                results.get(timeout=600)
            wall = time.perf_counter() - t0
        finally:
            for p in procs:
                p.join(timeout=30)
                if p.is_alive():
                    p.terminate()
        rows.append((f"procs x{k}", k, k * args.frames, wall, k * args.frames / wall))

    print(f"\nRGB-D-N + segmentation capture, {args.task}, camera '{args.camera}', "
          f"{args.resolution}x{args.resolution}, {cpus} CPU cores (load when measured: {os.getloadavg()[0]:.2f})")
    print(f"planning without rendering: {plan['steps']} steps in {plan['plan_s']:.2f} s "
          f"({plan['steps'] / plan['plan_s']:.0f} steps/s)")
    print(machine_line())
    print(f"{'mode':<12} {'workers':>7} {'frames':>7} {'wall s':>8} {'frames/s':>9} {'per worker':>11} {'scaling':>8}")
    base = rows[1][4] if len(rows) > 1 else rows[0][4]
    for mode, k, n, wall, fps in rows:
        print(f"{mode:<12} {k:>7} {n:>7} {wall:>8.2f} {fps:>9.1f} {fps / k:>11.1f} {fps / base:>7.2f}x")


if __name__ == "__main__":
    main()
