"""Benchmark the browser viewer in headless Chromium with software WebGL (SwiftShader).

Scene: the analytic table + sliding box, ray-cast at RESxRES and back-projected, decimated to
the per-frame point budget (default 16 frames x 50k points). Measures

* build: ViewerApp.start() (scene nodes for every frame, GUI);
* first frame: page.goto -> the canvas shows the cloud (polled screenshots, 0.1 s apart);
* playback fps: requestAnimationFrame callbacks per second in the page while playing at the
  FPS slider's maximum (the page renders once per animation frame), plus how many frame
  switches per second the server sent meanwhile.

  .venv/bin/python benchmarks/bench_viewer.py [--frames 16] [--points 50000] [--play-fps 30] [--no-frustums]
"""

from __future__ import annotations

import argparse
import json
import time

RAF_COUNTER_JS = """(seconds) => new Promise((resolve) => {
  let n = 0; const t0 = performance.now();
  function tick(now) { n += 1; if (now - t0 < seconds * 1000) requestAnimationFrame(tick); else resolve(n / ((now - t0) / 1000)); }
  requestAnimationFrame(tick);
})"""


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--frames", type=int, default=16)
    parser.add_argument("--points", type=int, default=50_000, help="per-frame point budget")
    parser.add_argument("--resolution", type=int, default=320, help="ray-cast image size (enough pixels for --points)")
    parser.add_argument("--seconds", type=float, default=6.0, help="measurement window for fps")
    parser.add_argument("--play-fps", type=int, default=30, help="FPS slider value while playing (default: its maximum)")
    parser.add_argument("--no-frustums", action="store_true", help="hide the camera frustums")
    args = parser.parse_args()

    from viewer.app import MAX_FPS, ViewerApp
    from viewer.browser import chromium, wait_until_drawn
    from viewer.sources import analytic_episode, recon_from_episode

    recon = recon_from_episode(analytic_episode(num_frames=args.frames, height=args.resolution, width=args.resolution))
    t_start = time.perf_counter()
    app = ViewerApp(recon, port=0, max_points=args.points)
    url = app.start()
    build_s = time.perf_counter() - t_start
    points = [len(f.points_local) for f in app.layer.frames]
    result = {"play_fps": min(args.play_fps, MAX_FPS), "frustums": not args.no_frustums, "frames": args.frames, "points_per_frame": int(min(points)), "precision": app.layer.precision,
              "build_s": round(build_s, 2)}
    try:
        with chromium() as page:
            t_goto = time.perf_counter()
            page.goto(url)
            _, _ = wait_until_drawn(page, min_fraction=0.05, poll_s=0.1)
            t_drawn = time.perf_counter()
            result["goto_to_first_frame_s"] = round(t_drawn - t_goto, 2)
            result["start_to_first_frame_s"] = round(t_drawn - t_start, 2)
            result["idle_raf_fps"] = round(page.evaluate(RAF_COUNTER_JS, 2.0), 1)

            app.fps_slider.value = min(args.play_fps, MAX_FPS)
            app.frustum_checkbox.value = not args.no_frustums
            app.play_checkbox.value = True
            time.sleep(1.0)  # let playback settle
            t0, n0 = time.perf_counter(), app.frame_switches
            raf_fps = page.evaluate(RAF_COUNTER_JS, args.seconds)
            t1 = time.perf_counter()
            app.play_checkbox.value = False
            result["playing_raf_fps"] = round(raf_fps, 1)
            result["server_frame_switches_per_s"] = round((app.frame_switches - n0) / (t1 - t0), 1)
            result["target_fps"] = 15
            result["meets_target"] = bool(raf_fps >= 15)
    finally:
        app.stop()
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
