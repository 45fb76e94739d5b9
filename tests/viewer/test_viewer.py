"""Viewer: colour maps, episode back-projection, decimation/precision, metrics reports, CLI errors."""

from __future__ import annotations

import json
import socket
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from reconstruction.recon4d import Recon4D
from tesseract4d.errors import UserError
from tesseract4d.colors import colorize_depth, colorize_normals, point_colors, turbo
from tesseract4d.psnr import PSNR_MAX_DB
from viewer.compare import image_metrics, load_report_per_frame
from viewer.scene import SceneLayer, decimate
from reconstruction.backproject import recon_from_episode
from tesseract4d.testing.synthetic_scene import analytic_episode
from viewer.sources import load_source

CLI = str(Path(sys.executable).with_name("tesseract4d"))


def test_turbo_and_image_colour_maps():
    rgb = turbo(np.linspace(0, 1, 5))
    assert rgb.shape == (5, 3) and rgb.dtype == np.uint8
    assert rgb[0, 2] > rgb[0, 0] and rgb[-1, 0] > rgb[-1, 2]  # near blue, far red
    depth = colorize_depth(np.array([[0.0, 1.0], [2.0, np.nan]]), 1.0, 2.0)
    assert (depth[0, 0] == 0).all() and (depth[1, 1] == 0).all() and depth[0, 1].any()
    normals = colorize_normals(np.array([[0.0, 0.0, -1.0], [0.0, 0.0, 0.0]]))
    assert normals[0].tolist() == [127, 127, 0] and normals[1].tolist() == [0, 0, 0]
    with pytest.raises(ValueError):
        point_colors("nope", rgb, rgb, np.zeros(5), np.zeros(5, bool), (0, 1))


def test_episode_back_projection_finds_the_moving_box():
    episode = analytic_episode(num_frames=5, height=48, width=48)
    recon = recon_from_episode(episode)
    recon.validate()
    assert recon.num_frames == 5 and len(recon.background_points) > 0
    for t in range(5):
        pts, dyn, col = recon.points_world[t], recon.dynamic[t], recon.colors[t]
        assert np.allclose(np.linalg.norm(recon.normals_world[t], axis=1), 1.0, atol=1e-3)
        # The table is the plane z = 0 (static); moving points are the red box, above it.
        table = pts[:, 2] < 1e-4
        assert not dyn[table].any()
        assert dyn.sum() > 0 and (pts[dyn, 2] > 1e-4).all() and (col[dyn, 0] > 150).all()
    # The box slides along the x = y diagonal.
    y = [recon.points_world[t][recon.dynamic[t], 1].mean() for t in range(5)]
    assert np.all(np.diff(y) > 0)


def test_decimation_budget_and_float16_choice():
    assert len(decimate(10, 20)) == 10 and len(np.unique(decimate(1000, 100))) == 100
    recon = recon_from_episode(analytic_episode(num_frames=2, height=64, width=64))
    layer = SceneLayer(recon, max_points=500)
    assert all(len(f.points_local) == 500 for f in layer.frames)
    assert layer.precision == "float16"  # a 2 m scene around its centre: float16 spacing < 1 mm
    far = Recon4D(**{**recon.__dict__, "points_world": [p * 100 for p in recon.points_world]})
    assert SceneLayer(far, max_points=500).precision == "float32"


def test_scene_size_and_initial_view_ignore_a_few_far_points():
    from viewer.scene import initial_view

    recon = recon_from_episode(analytic_episode(num_frames=2, height=64, width=64))
    near = SceneLayer(recon, max_points=2000)
    # 4% of the points far away (a floor seen up to the horizon) must not change the framing.
    rng = np.random.default_rng(0)
    far_points = [np.concatenate([p, p[rng.choice(len(p), len(p) // 25)] * 30.0]) for p in recon.points_world]
    grown = Recon4D(**{**recon.__dict__, "objects": None, "points_world": far_points,
                       "colors": [np.concatenate([c, c[: len(p) - len(c)]]) for c, p in zip(recon.colors, far_points)],
                       "normals_world": [np.concatenate([n, n[: len(p) - len(n)]]) for n, p in zip(recon.normals_world, far_points)],
                       "dynamic": [np.concatenate([d, np.zeros(len(p) - len(d), bool)]) for d, p in zip(recon.dynamic, far_points)]})
    layer = SceneLayer(grown, max_points=2000)
    assert layer.radius < 1.3 * near.radius
    view = initial_view(grown, layer.centre)
    eye = recon.T_world_cam[0, :3, 3]
    # Looking at the scene from about as far as the recording camera, from above the table.
    assert 1.0 < np.linalg.norm(view["position"] - layer.centre) / np.linalg.norm(eye - layer.centre) < 2.5
    assert view["up_axis"] == "+z" and view["position"][2] > layer.centre[2]


def test_point_budget_changes_live():
    from viewer.app import ViewerApp

    recon = recon_from_episode(analytic_episode(num_frames=3, height=128, width=128))
    with ViewerApp(recon, port=0, max_points=1500) as app:
        assert app.budget_dropdown.options == ("1,500",)  # no smaller step under 1,000 points
    with ViewerApp(recon, port=0, max_points=10**6) as app:  # the largest frame's points come first
        assert app.budget_dropdown.options[0] == f"{max(len(p) for p in recon.points_world):,}"
    with ViewerApp(recon, port=0, max_points=4000) as app:
        size_4k = app.point_size_slider.value
        assert app.budget_dropdown.options == ("4,000", "2,000")
        app.budget_dropdown.value = "2,000"
        assert all(len(f.points_local) == 2000 for f in app.layer.frames)
        assert all(len(c.points) == 2000 for c in app.layer._clouds)
        # Half the points: each covers twice the area, so the size that closes the gaps grows by sqrt(2).
        assert app.point_size_slider.value == pytest.approx(size_4k * np.sqrt(2), rel=0.01)
        assert app.point_size_slider.min < app.point_size_slider.value < app.point_size_slider.max


def test_image_metrics_and_report(tmp_path):
    a = recon_from_episode(analytic_episode(num_frames=3, height=32, width=32, seed=0))
    b = recon_from_episode(analytic_episode(num_frames=3, height=32, width=32, seed=1))
    same = image_metrics(a, a)
    assert len(same) == 3 and same[0]["psnr_rgb_db"] == PSNR_MAX_DB and same[0]["depth_absrel"] == 0.0
    diff = image_metrics(a, b)
    assert diff[0]["psnr_rgb_db"] < 40 and diff[0]["depth_absrel"] > 0
    (tmp_path / "r.json").write_text(json.dumps({"episodes": [{"per_frame": {"psnr": [1.0, 2.0], "absrel": [0.1, 0.2]}}]}))
    assert load_report_per_frame(tmp_path / "r.json") == [{"psnr": 1.0, "absrel": 0.1}, {"psnr": 2.0, "absrel": 0.2}]
    (tmp_path / "bad.json").write_text("{")
    with pytest.raises(UserError, match="not valid JSON"):
        load_report_per_frame(tmp_path / "bad.json")


def test_load_source_errors(tmp_path):
    with pytest.raises(UserError, match="does not exist"):
        load_source(tmp_path / "missing")
    (tmp_path / "notes.txt").write_text("hello")
    with pytest.raises(UserError, match="not something the viewer opens"):
        load_source(tmp_path / "notes.txt")
    with pytest.raises(UserError, match="neither a reconstruction folder"):
        load_source(tmp_path)
    recon_dir = recon_from_episode(analytic_episode(num_frames=2, height=32, width=32)).save(tmp_path / "r", write_ply=False)
    with pytest.raises(UserError, match="reconstruction of camera 'base_camera'; --camera chooses among an episode's"):
        load_source(recon_dir, camera="wrist")
    assert load_source(recon_dir, camera="base_camera").num_frames == 2  # the camera it was made from
    (recon_dir / "recon4d.npz").unlink()
    with pytest.raises(UserError, match="has a manifest.json but no recon4d.npz: the reconstruction is incomplete"):
        load_source(recon_dir)


def _run_cli(*args, timeout=60):
    return subprocess.run([CLI, "view", *map(str, args)], capture_output=True, text=True, timeout=timeout)


def test_cli_missing_and_malformed_paths(tmp_path):
    res = _run_cli(tmp_path / "nope")
    assert res.returncode == 2 and "does not exist" in res.stderr and "reconstruction folder" in res.stderr
    bad = tmp_path / "recon"
    bad.mkdir()
    (bad / "manifest.json").write_text("{not json")
    res = _run_cli(bad)
    assert res.returncode == 2 and "corrupt" in res.stderr and "tesseract4d reconstruct" in res.stderr
    (tmp_path / "episode.h5").write_bytes(b"not hdf5")
    res = _run_cli(tmp_path / "episode.h5")
    assert res.returncode == 2 and "is not an episode file (not HDF5)" in res.stderr
    assert "Traceback" not in res.stderr


def test_cli_port_in_use(tmp_path):
    recon_dir = recon_from_episode(analytic_episode(num_frames=2, height=32, width=32)).save(tmp_path / "recon", write_ply=False)
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        port = s.getsockname()[1]
        res = _run_cli(recon_dir, "--port", port)
    assert res.returncode == 2 and f"port {port}" in res.stderr and "in use" in res.stderr and "--port" in res.stderr


def test_port_of_a_just_stopped_server_is_free():
    from viewer.app import check_address

    # A server that closed its connections first leaves them in TIME_WAIT on its port for a
    # minute; restarting the viewer right away must still work.
    listener = socket.socket()
    listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    listener.bind(("127.0.0.1", 0))
    listener.listen()
    port = listener.getsockname()[1]
    client = socket.create_connection(("127.0.0.1", port))
    conn, _ = listener.accept()
    conn.close()  # the server side closes first -> TIME_WAIT on (127.0.0.1, port)
    client.close()
    listener.close()
    check_address("127.0.0.1", port)


def test_cli_export_of_a_dataset_episode(tmp_path):
    from tesseract4d.dataset_format import DatasetInfo, init_dataset, write_episode

    init_dataset(tmp_path / "data", DatasetInfo(height=32, width=32))
    write_episode(tmp_path / "data", analytic_episode(num_frames=3, height=32, width=32, seed=7))
    out = tmp_path / "scene.html"
    res = _run_cli(tmp_path / "data" / "Analytic-v0" / "7", "--export", out)
    assert res.returncode == 0, res.stderr
    html = out.read_text()
    assert "__VISER_EMBED_DATA__" in html and len(html) > 10_000


def test_cli_serves_and_prints_the_url(tmp_path):
    import signal
    import urllib.request

    recon_dir = recon_from_episode(analytic_episode(num_frames=2, height=32, width=32)).save(tmp_path / "recon", write_ply=False)
    # Ctrl-C as in a terminal: a test run started in the background by a shell inherits SIGINT as
    # ignored, and Python then never raises KeyboardInterrupt; give the viewer the default.
    proc = subprocess.Popen([CLI, "view", str(recon_dir), "--port", "0"], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    try:
        line = proc.stdout.readline()
        assert line.startswith("viewer: http://127.0.0.1:"), line + proc.stderr.read()
        url = line.split()[1]
        with urllib.request.urlopen(url, timeout=10) as page:
            assert b"<html" in page.read().lower()
    finally:
        proc.send_signal(signal.SIGINT)
        rc = proc.wait(timeout=60)
    assert rc == 130


def test_compare_mode_layout_and_metrics():
    from viewer.app import COMPARE_LAYOUTS, ViewerApp

    pred = recon_from_episode(analytic_episode(num_frames=3, height=32, width=32, seed=1))
    gt = recon_from_episode(analytic_episode(num_frames=3, height=32, width=32, seed=0))
    with ViewerApp(pred, compare=gt, port=0) as app:
        assert np.linalg.norm(app.right_layer.offset) > 1.0  # side by side
        assert (app.layer._label_node.text, app.right_layer._label_node.text) == ("prediction", "ground truth")
        assert "psnr_rgb_db" in app.metrics_md.content and "Frame 0" in app.metrics_md.content
        app.frame_slider.value = 2
        assert "Frame 2" in app.metrics_md.content
        app.layout_dropdown.value = COMPARE_LAYOUTS[2]
        assert not app.layer._root.visible and app.right_layer._root.visible
        assert np.allclose(app.right_layer.offset, 0.0)


def test_compare_mode_labels_a_counterfactual_pair():
    # Two futures of one scene, labelled with their instructions; one slider drives both.
    from viewer.app import COMPARE_LAYOUTS, ViewerApp

    push = recon_from_episode(analytic_episode(num_frames=4, height=32, width=32, seed=1))
    still = recon_from_episode(analytic_episode(num_frames=4, height=32, width=32, seed=1, instruction="keep still"))
    with ViewerApp(push, compare=still, labels=("push the box to the right", "keep still"), port=0) as app:
        assert (app.layer._label_node.text, app.right_layer._label_node.text) == ("push the box to the right", "keep still")
        assert np.linalg.norm(app.right_layer.offset) > 1.0
        app.frame_slider.value = 3
        assert app.frame == 3 and app.layer._current == app.right_layer._current == 3
        app.layout_dropdown.value = COMPARE_LAYOUTS[1]
        assert app.layer._root.visible and not app.right_layer._root.visible
    with pytest.raises(ValueError, match="two"):
        ViewerApp(push, compare=still, labels=("only one",), port=0)


def test_view_command_labels_the_two_clouds_of_compare_mode(tmp_path, monkeypatch):
    import viewer.app

    from tesseract4d.cli import main

    push = recon_from_episode(analytic_episode(num_frames=2, height=32, width=32, seed=1)).save(tmp_path / "push", write_ply=False)
    still = recon_from_episode(analytic_episode(num_frames=2, height=32, width=32, seed=1, instruction="keep still")).save(
        tmp_path / "still", write_ply=False)
    served = []

    def serve(app):  # instead of serving until Ctrl-C: start, read the labels, stop
        with app:
            served.append((app.layer._label_node.text, app.right_layer._label_node.text))

    monkeypatch.setattr(viewer.app, "serve_forever", serve)
    argv = ["view", str(push), "--compare", str(still), "--labels", "push it", "keep still", "--port", "0"]
    assert main(argv) == 0 and served[-1] == ("push it", "keep still")
    assert main(["view", str(push), "--labels", "a", "b", "--port", "0"]) == 2  # no --compare: one line, no server
    assert main(["view", str(push), "--metrics", str(tmp_path / "report.json"), "--port", "0"]) == 2  # likewise
    assert main(["view", str(push), "--compare", str(tmp_path / "nowhere"), "--port", "0"]) == 2
    assert served == [("push it", "keep still")]


def test_view_errors_name_the_flag_they_are_about(tmp_path, capsys):
    from tesseract4d.cli import main

    push = recon_from_episode(analytic_episode(num_frames=2, height=32, width=32, seed=1)).save(tmp_path / "push", write_ply=False)
    assert main(["view", str(push), "--metrics", str(tmp_path / "report.json"), "--port", "0"]) == 2
    assert "--metrics shows per-frame metrics in compare mode: pass --compare" in capsys.readouterr().err
    assert main(["view", str(push), "--compare", str(tmp_path / "nowhere"), "--port", "0"]) == 2
    assert f"error: --compare: {tmp_path / 'nowhere'} does not exist" in capsys.readouterr().err


@pytest.mark.parametrize("host, says", [("nosuchhost.invalid", "is not a name or address this machine can resolve"),
                                        ("192.0.2.1", "is not an address of this machine")])
def test_a_host_that_cannot_serve_is_named_before_any_warning(tmp_path, host, says):
    """192.0.2.1 is a documentation address (RFC 5737), never one of this machine's."""
    recon_dir = recon_from_episode(analytic_episode(num_frames=2, height=32, width=32)).save(tmp_path / "recon", write_ply=False)
    res = _run_cli(recon_dir, "--host", host, "--port", 0)
    assert res.returncode == 2 and f"--host {host} {says}" in res.stderr, res.stderr
    assert "reachable from the network" not in res.stderr and "--port" not in res.stderr


def test_model_generator_reports_a_missing_checkpoint(tmp_path):
    from viewer.generate import model_generator

    source = recon_from_episode(analytic_episode(num_frames=2, height=32, width=32))
    with pytest.raises(UserError, match="checkpoint"):
        model_generator(tmp_path / "no_ckpt", source)


def _slow_generator(calls: list):
    """A generator that reports progress every 20 ms for 500 steps (10 s unless stopped), like a
    sampler asked for many steps; back-projects the analytic scene when it gets to the end."""
    import time

    def generate(instruction, seed, steps, progress):
        for step in range(500):
            calls.append(step)
            progress(step / 500, f"step {step}")
            time.sleep(0.02)
        return recon_from_episode(analytic_episode(num_frames=2, height=32, width=32, instruction=instruction))

    return generate


def test_stopping_the_viewer_ends_a_running_generation_first(capsys):
    """The generation stops at its next step and its thread has ended when stop() returns (a model
    left running in a thread while Python exits aborts the process)."""
    import time

    from viewer.app import ViewerApp

    calls = []
    app = ViewerApp(recon_from_episode(analytic_episode(num_frames=2, height=32, width=32)), port=0,
                    generate=_slow_generator(calls))
    app.start()
    app.instruction_text.value = "push the box"
    app._start_generation()
    while len(calls) < 3:
        time.sleep(0.01)
    thread = app._generation_thread
    app.stop()
    assert not thread.is_alive() and len(calls) < 100
    assert app.generation_count == 0 and app.generation_error is None
    assert app.status_md.content == "Cancelled: the viewer is stopping."
    assert "stopping the generation at its next step" in capsys.readouterr().err


def test_a_generated_future_in_compare_mode_is_labelled_with_its_instruction():
    from viewer.app import ViewerApp

    def generate(instruction, seed, steps, progress):
        return recon_from_episode(analytic_episode(num_frames=3, height=32, width=32, instruction=instruction))

    push = recon_from_episode(analytic_episode(num_frames=3, height=32, width=32, seed=1))
    still = recon_from_episode(analytic_episode(num_frames=3, height=32, width=32, seed=1, instruction="keep still"))
    long = "lift the box " + "very " * 20 + "high"
    with ViewerApp(push, compare=still, labels=("push it", "keep still"), port=0, generate=generate) as app:
        app._run_generation(long, 0, 1)
        label = app.layer._label_node.text
        assert label.startswith("lift the box very") and label.endswith("…") and len(label) <= 48
        assert app.right_layer._label_node.text == "keep still"
        assert app.compare_md.content == f"Left: {label}. Right: keep still. Metrics: left against right."


def test_play_at_the_last_frame_without_loop_plays_again_from_the_start():
    from viewer.app import ViewerApp

    with ViewerApp(recon_from_episode(analytic_episode(num_frames=4, height=32, width=32)), port=0) as app:
        app.fps_slider.value = 1  # the playback thread then waits a second before the next frame
        app.loop_checkbox.value = False
        app.frame_slider.value = 3
        app.play_checkbox.value = True
        assert app.frame == 0 and app.frame_slider.value == 0 and app.play_checkbox.value


def test_denoising_progress_counts_the_steps_asked_for():
    from viewer.generate import denoising_message

    assert denoising_message(3, 10, 10) == "denoising step 3/10"
    # Two noise draws of two steps: the sampler runs twice.
    assert [denoising_message(k, 4, 2) for k in (1, 2, 3, 4)] == [
        "denoising step 1/2 of pass 1/2", "denoising step 2/2 of pass 1/2",
        "denoising step 1/2 of pass 2/2", "denoising step 2/2 of pass 2/2"]


def test_generate_from_a_first_frame_alone_predicts_the_models_clip(tmp_path):
    """The shipped checkpoint on a one-frame source (a first frame, as the demo writes it) predicts
    its own 16 frames, not one."""
    from tesseract4d.model.checkpoint import SHIPPED_CHECKPOINT, read_inference_config
    from viewer.generate import model_generator

    info = read_inference_config(SHIPPED_CHECKPOINT)
    h, w = info["resolution"]
    source = recon_from_episode(analytic_episode(num_frames=1, height=h, width=w))
    messages = []
    recon = model_generator(SHIPPED_CHECKPOINT, source)("push the box to the left", 0, 1,
                                                        lambda f, m: messages.append(m))
    assert recon.num_frames == info["num_frames"] == 16
    # One step asked for; the analytic scene's plain box stands out by no colour, so one draw is sampled.
    assert "denoising step 1/1" in messages and messages[-1] == "reconstructing the 4D point cloud"


def test_a_chained_scene_shows_its_instruction_timeline():
    from tesseract4d.instruction_schedule import SCHEDULE_KEY, Segment
    from viewer.app import ViewerApp

    recon = recon_from_episode(analytic_episode(num_frames=7, height=32, width=32, seed=1))
    recon.metadata[SCHEDULE_KEY] = [Segment("push the red cube left", 0, 3).to_dict(),
                                    Segment("lift the blue cylinder", 3, 6).to_dict()]
    with ViewerApp(recon, port=0) as app:
        lines = app.timeline_md.content.split("  \n")
        assert lines == ["▶ **1. push the red cube left (frames 0–3)**", "2. lift the blue cylinder (frames 3–6)"]
        app.frame_slider.value = 3  # the boundary frame ends the first segment
        assert app.timeline_md.content.startswith("▶ **1.")
        app.frame_slider.value = 4
        assert app.timeline_md.content.split("  \n")[1] == "▶ **2. lift the blue cylinder (frames 3–6)**"
    plain = recon_from_episode(analytic_episode(num_frames=3, height=32, width=32, seed=1))
    with ViewerApp(plain, port=0) as app:
        assert app.timeline_md.content == ""


def test_a_streaming_generator_shows_each_decoded_frame_at_once():
    from viewer.app import ViewerApp

    shown = []

    def generate(instruction, seed, steps, progress):
        for k, colour in enumerate(([200, 30, 30], [30, 30, 200])):
            progress(0.4 * (k + 1), f"clip {k + 1} decoded", np.full((32, 32, 3), colour, np.uint8))
            shown.append((np.asarray(app.rgb_image.image).reshape(-1, 3).mean(0), app.status_md.content))
        return recon_from_episode(analytic_episode(num_frames=3, height=32, width=32, instruction=instruction))

    with ViewerApp(recon_from_episode(analytic_episode(num_frames=3, height=32, width=32)), port=0,
                   generate=generate) as app:
        app._run_generation("push the box", 0, 1)
    assert [tuple(np.round(c).astype(int)) for c, _ in shown] == [(200, 30, 30), (30, 30, 200)]
    assert shown[1][1] == "Generating: clip 2 decoded"


def test_generate_streams_a_long_future_clip_by_clip():
    """The shipped checkpoint on a 17-frame source predicts two clips and hands each one's last frame
    to the progress callback as soon as it is decoded."""
    from tesseract4d.model.checkpoint import SHIPPED_CHECKPOINT, read_inference_config
    from viewer.generate import model_generator

    h, w = read_inference_config(SHIPPED_CHECKPOINT)["resolution"]
    source = recon_from_episode(analytic_episode(num_frames=17, height=h, width=w))
    streamed = []
    recon = model_generator(SHIPPED_CHECKPOINT, source)(
        "push the box to the left", 0, 1, lambda f, m, rgb=None: streamed.append((m, rgb)) if rgb is not None else None)
    assert recon.num_frames == 17
    assert [m for m, _ in streamed] == ["clip 1 decoded: frames 0–15", "clip 2 decoded: frames 0–16"]
    assert all(rgb.shape == (h, w, 3) and rgb.dtype == np.uint8 for _, rgb in streamed)
    np.testing.assert_array_equal(streamed[-1][1], recon.rgb[-1])  # the last streamed frame is the future's last
