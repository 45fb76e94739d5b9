"""Benchmark the browser viewer in headless Chromium with software WebGL (SwiftShader).

Scene: the analytic table + sliding box, ray-cast at RESxRES and back-projected, decimated to
the per-frame point budget (default 16 frames x 50k points). For each configuration (a row of
the table) it measures

* build: ViewerApp.start() (scene nodes for every frame, GUI);
* first frame: page.goto -> the canvas shows the cloud (polled screenshots, 0.1 s apart);
* static: frames drawn per second when the page is made to redraw an unchanging scene
  (the cost of drawing one frame of points);
* playing: while playing at the FPS slider's maximum, frames drawn per second and time steps
  shown per second (frames at which a different time step was visible than at the frame
  before). Measured after a warm-up, so viser's adaptive resolution has settled, and over
  --seconds.

Rows: the default window (1100x700), a full-HD window, and two diagnostics that show where the
time goes: a smaller point budget (--max-points) and the browser's WebGL antialiasing switched
off with a Chromium flag (viser always asks for a multisampled canvas; the flag is a browser
setting, not something the viewer can choose).

  .venv/bin/python benchmarks/bench_viewer.py [--frames 16] [--points 50000] [--seconds 8] [--rows default,hd,budget,no-msaa]
"""

from __future__ import annotations

import argparse
import time

from measure import machine_line

TARGET_FPS = 15

# Counts animation frames and the time steps visible at each (the page renders at most once per
# animation frame); resolves to [frames/s, time steps shown/s].
PLAYBACK_COUNTER_JS = """([seconds, prefix]) => new Promise((resolve) => {
  const tree = window.__viserSceneTree;
  const visible = () => { const st = tree.getState();
    for (const k in st) { if (k.startsWith(prefix) && st[k].effectiveVisibility) return k; } return null; };
  let n = 0, shown = 0, last = visible(); const t0 = performance.now();
  function tick(now) {
    n += 1; const v = visible(); if (v !== last) { shown += 1; last = v; }
    if (now - t0 < seconds * 1000) requestAnimationFrame(tick);
    else { const s = (now - t0) / 1000; resolve([n / s, shown / s]); }
  }
  requestAnimationFrame(tick);
})"""
# Frames per second while every animation frame asks viser for a redraw of the unchanged scene.
FORCED_REDRAW_JS = """(seconds) => new Promise((resolve) => {
  const m = window.__viserMutable; let n = 0; const t0 = performance.now();
  function tick(now) { n += 1; m.requestRender(); if (now - t0 < seconds * 1000) requestAnimationFrame(tick); else resolve(n / ((now - t0) / 1000)); }
  requestAnimationFrame(tick);
})"""

ROWS = {
    # name: (label, window, point budget factor, extra chromium flags)
    "default": ("default window", (1100, 700), 1.0, []),
    "hd": ("full-HD window", (1920, 1080), 1.0, []),
    "budget": ("half point budget", (1100, 700), 0.5, []),
    "no-msaa": ("browser antialiasing off", (1100, 700), 1.0, ["--webgl-antialiasing-mode=none"]),
}


def measure(recon, label: str, window: tuple[int, int], max_points: int, flags: list[str], seconds: float,
            warmup_s: float, play_fps: int) -> dict:
    from tesseract4d.testing import browser
    from tesseract4d.testing.browser import chromium, wait_until_drawn
    from viewer.app import ViewerApp

    t_start = time.perf_counter()
    app = ViewerApp(recon, port=0, max_points=max_points)
    url = app.start()
    row = {"config": label, "window": f"{window[0]}x{window[1]}", "points": int(min(len(f.points_local) for f in app.layer.frames)),
           "build_s": time.perf_counter() - t_start}
    default_args = browser.CHROMIUM_ARGS
    browser.CHROMIUM_ARGS = default_args + flags
    try:
        with chromium(*window) as page:
            t_goto = time.perf_counter()
            page.goto(url)
            wait_until_drawn(page, min_fraction=0.05, poll_s=0.1)
            row["first_frame_s"] = time.perf_counter() - t_start
            row["goto_s"] = time.perf_counter() - t_goto
            time.sleep(0.5)
            row["static_fps"] = page.evaluate(FORCED_REDRAW_JS, 3.0)

            app.fps_slider.value = play_fps
            app.play_checkbox.value = True
            time.sleep(warmup_s)
            row["drawn_fps"], row["steps_fps"] = page.evaluate(PLAYBACK_COUNTER_JS, [seconds, f"/{app.layer.name}/frames/"])
            app.play_checkbox.value = False
            row["canvas"] = page.evaluate("() => { const c = [...document.querySelectorAll('canvas')].find(c => c.width > 0); return c ? c.width + 'x' + c.height : '?'; }")
    finally:
        browser.CHROMIUM_ARGS = default_args
        app.stop()
    return row


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--frames", type=int, default=16)
    parser.add_argument("--points", type=int, default=50_000, help="per-frame point budget")
    parser.add_argument("--resolution", type=int, default=320, help="ray-cast image size (enough pixels for --points)")
    parser.add_argument("--seconds", type=float, default=8.0, help="measurement window while playing")
    parser.add_argument("--warmup", type=float, default=6.0, help="seconds of playback before measuring (adaptive resolution settles)")
    parser.add_argument("--rows", default=",".join(ROWS), help=f"comma-separated configurations out of {', '.join(ROWS)}")
    args = parser.parse_args()
    names = [r.strip() for r in args.rows.split(",") if r.strip()]
    unknown = [r for r in names if r not in ROWS]
    if unknown:
        parser.error(f"unknown rows {unknown}; choose from {', '.join(ROWS)}")

    from tesseract4d.testing.synthetic_scene import analytic_episode

    from reconstruction.backproject import recon_from_episode
    from viewer.app import MAX_FPS

    recon = recon_from_episode(analytic_episode(num_frames=args.frames, height=args.resolution, width=args.resolution))
    rows = []
    for name in names:
        label, window, factor, flags = ROWS[name]
        rows.append(measure(recon, label, window, max(1, int(args.points * factor)), flags, args.seconds, args.warmup, MAX_FPS))
        print(f"measured {label}", flush=True)

    print(f"\n{args.frames} frames, played at the FPS slider's maximum ({MAX_FPS}); target >= {TARGET_FPS} time steps shown per second")
    header = f"{'configuration':<26} {'window':>9} {'canvas':>9} {'points':>7} {'first frame s':>13} {'static fps':>10} {'drawn fps':>9} {'steps/s':>7} {'target':>6}"
    print(machine_line())
    print(header)
    print("-" * len(header))
    for r in rows:
        ok = "met" if r["steps_fps"] >= TARGET_FPS else "missed"
        print(f"{r['config']:<26} {r['window']:>9} {r['canvas']:>9} {r['points']:>7} {r['first_frame_s']:>13.2f} "
              f"{r['static_fps']:>10.1f} {r['drawn_fps']:>9.1f} {r['steps_fps']:>7.1f} {ok:>6}")


if __name__ == "__main__":
    main()
