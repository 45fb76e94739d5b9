"""Benchmark the object layer: seconds per 16-frame clip to track the first frame's objects, and the
whole reconstruction with it, on recorded episodes (datagen's, e.g. a held-out set at 128²).

Per episode (its first camera), the median of ``--repeats`` timed runs after one warm-up run:

* objects: ``reconstruction.objects.episode_objects`` alone, tracking through the episode's frames
  (not reading its recorded poses), objects from its first-frame segmentation; "no hand" the same
  without the hand's steps (``TrackConfig(follow_hand=False, keep_unreached=False)``: no hand track), so
  the difference is what the hand's track and its rules cost;
* plain + objects: ``recon_from_episode`` (back-projection without refinement) with tracked objects,
  what the viewer does for a prediction;
* refined + objects: ``reconstruct_episode`` with the default ``ReconConfig`` (normal and temporal
  refinement, TSDF background and mesh, object layer), what ``tesseract4d reconstruct`` does.

Also prints the tracker's accuracy on these frames against the recorded poses (share of objects whose
final position error is at most 5 mm). Prints a table per task (medians over its episodes); state the
CPU and threads beside any number taken from it.

  .venv/bin/python benchmarks/bench_objects.py --data data/heldout_cubes128 data/heldout_groups128 [--max 8] [--repeats 3]
"""

from __future__ import annotations

import argparse
import copy
import json
import os
import platform
import statistics
import time
from pathlib import Path


def cpu_name() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.machine()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", nargs="+", required=True, help="dataset folders (datagen output)")
    parser.add_argument("--max", type=int, default=8, help="episodes per dataset at most (default 8)")
    parser.add_argument("--repeats", type=int, default=3, help="timed runs per episode after the warm-up")
    parser.add_argument("--json", help="also write the results here")
    args = parser.parse_args()

    from tesseract4d import runtime

    runtime.configure()
    from reconstruction.backproject import recon_from_episode
    from reconstruction.objects import TrackConfig, episode_objects
    from reconstruction.reconstruct import ReconConfig, reconstruct_episode
    from tesseract4d.dataset_format import list_episode_files, read_episode
    from tesseract4d.evaluation.object_tracks import object_track_metrics

    def timed(fn) -> float:
        fn()  # warm-up: imports, caches
        runs = []
        for _ in range(args.repeats):
            start = time.perf_counter()
            fn()
            runs.append(time.perf_counter() - start)
        return statistics.median(runs)

    rows = []
    for data in args.data:
        for path in list_episode_files(data)[: args.max]:
            ep = read_episode(path)
            cam = next(iter(ep.cameras))
            as_prediction = copy.deepcopy(ep)
            as_prediction.source = "prediction"  # tracked, not read from the recorded poses
            frames = ep.cameras[cam]
            row = {"episode": f"{ep.env_id}/{path.stem}", "task": ep.env_id, "frames": int(len(frames.rgb)),
                   "size": f"{frames.rgb.shape[2]}x{frames.rgb.shape[1]}"}
            row["objects_s"] = timed(lambda: episode_objects(ep, cam))
            row["objects_no_hand_s"] = timed(lambda: episode_objects(ep, cam, config=TrackConfig(follow_hand=False,
                                                                                                keep_unreached=False)))
            row["plain_objects_s"] = timed(lambda: recon_from_episode(as_prediction))
            row["refined_objects_s"] = timed(lambda: reconstruct_episode(ep, config=ReconConfig()))
            m = object_track_metrics(episode_objects(ep, cam), ep, cam)
            row["objects"], row["within_5mm"] = m["summary"]["objects"], m["summary"]["within_5mm"]
            rows.append(row)
            print(f"{row['episode']:<42} {row['objects_s']:.3f} {row['objects_no_hand_s']:.3f} {row['plain_objects_s']:.3f} "
                  f"{row['refined_objects_s']:.3f}", flush=True)

    print()
    print(f"CPU: {cpu_name()}, {os.cpu_count()} logical cores, load average {os.getloadavg()[0]:.1f}, "
          f"OMP_NUM_THREADS={os.environ.get('OMP_NUM_THREADS', 'unset')}; medians of {args.repeats} runs per episode")
    print(f"{'task':<26}{'episodes':>9}{'clip':>15}{'objects s':>11}{'no hand s':>11}{'plain+obj s':>13}{'refined+obj s':>15}"
          f"{'objects ≤5 mm':>15}")
    for task in sorted({r["task"] for r in rows}):
        rs = [r for r in rows if r["task"] == task]
        objs = sum(r["objects"] for r in rs)
        hits = sum(r["within_5mm"] * r["objects"] for r in rs)
        print(f"{task:<26}{len(rs):>9}{str(rs[0]['frames']) + ' @ ' + rs[0]['size']:>15}"
              f"{statistics.median(r['objects_s'] for r in rs):>11.3f}{statistics.median(r['objects_no_hand_s'] for r in rs):>11.3f}"
              f"{statistics.median(r['plain_objects_s'] for r in rs):>13.3f}"
              f"{statistics.median(r['refined_objects_s'] for r in rs):>15.3f}{f'{hits:.0f} / {objs}':>15}")
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=2))


if __name__ == "__main__":
    main()
