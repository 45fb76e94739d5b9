"""The browser viewer: a viser server showing one 4D source, or two side by side (a prediction and
its ground truth, or two futures of one scene under two instructions).

Usage from Python (non-blocking)::

    app = ViewerApp(recon, port=0)        # or ViewerApp.from_path("out/reconstruction")
    url = app.start()                     # serves on 127.0.0.1, returns "http://127.0.0.1:PORT"
    ...
    app.stop()

GUI panels: Playback (frame slider, play, fps, loop), Display (colour mode, point size,
per-frame vs fused static points, frustums, the object layer drawn whole or the raw points), Frame images (RGB, depth, normal of the current
frame), Compare (layout and per-frame metrics, with a second source) and Generate (instruction,
seed, steps -> predict + reconstruct, shown when done).
"""

from __future__ import annotations

import os
import socket
import sys
import threading
import time
import traceback
from typing import Callable

import numpy as np

from reconstruction.recon4d import Recon4D
from tesseract4d.errors import Terminated, UserError
from tesseract4d.colors import COLOR_MODES, colorize_depth, colorize_normals
from viewer.origin import own_origin_only
from viewer.scene import (DEFAULT_MAX_POINTS, POINT_MODES, SCENE_MODES, SceneLayer, configure_rendering, initial_view,
                          make_server, stop_server)
from viewer.sources import load_source
from viewer.timeline import scene_schedule, timeline_markdown
from viewer.compare import format_metrics, image_metrics, load_report_per_frame
from viewer.generate import checkpoint_steps, model_generator

# generate(instruction, seed, steps, progress(fraction in [0, 1], message[, rgb])) -> a new source; a
# generator that streams passes each newly decoded RGB frame (H, W, 3) uint8 as ``rgb``, shown at once.
Generator = Callable[[str, int, int, Callable[[float, str], None]], Recon4D]
PANEL_IMAGE_MAX_SIDE = 256
MAX_FPS = 30
PANEL_REFRESH_WHILE_PLAYING_S = 0.5
COMPARE_LAYOUTS = ("Side by side", "Left only", "Right only")
# Compare mode's names of its two layers unless told otherwise.
COMPARE_LABELS = ("prediction", "ground truth")
# Range of the Generate panel's sampler steps.
MIN_STEPS, MAX_STEPS = 1, 1000
# How long stopping the viewer waits for a running generation to reach its next step and end.
GENERATION_STOP_WAIT_S = 60.0


class GenerationCancelled(Exception):
    """Raised inside a running generation (at its next progress report) when the viewer stops."""


def check_address(host: str, port: int) -> None:
    """Raise UserError if ``host`` is not an address of this machine or (host, port) cannot be bound
    (viser would silently take the next port)."""
    import errno

    try:
        infos = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)
    except socket.gaierror as e:
        raise UserError(f"--host {host} is not a name or address this machine can resolve ({e.strerror}); pass one "
                        f"of its addresses, e.g. --host 127.0.0.1 (this machine only) or --host 0.0.0.0 (all)") from e
    family, _, _, _, address = infos[0]  # port 0 binds to a free port: the address is checked all the same
    with socket.socket(family, socket.SOCK_STREAM) as s:
        # As the server binds: connections of a just-stopped viewer (TIME_WAIT) do not block the
        # port, a program listening on it does.
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            s.bind(address)
        except OSError as e:
            if e.errno == errno.EADDRNOTAVAIL:
                raise UserError(f"--host {host} is not an address of this machine ({e.strerror}); pass one of its "
                                f"addresses, e.g. --host 127.0.0.1 (this machine only) or --host 0.0.0.0 (all)") from e
            raise UserError(f"port {port} on {host} is in use or not available ({e.strerror}); "
                            f"pass another --port (or stop the program using it).") from e


def _panel_image(image: np.ndarray) -> np.ndarray:
    h, w = image.shape[:2]
    if max(h, w) <= PANEL_IMAGE_MAX_SIDE:
        return image
    import cv2

    s = PANEL_IMAGE_MAX_SIDE / max(h, w)
    return cv2.resize(image, (max(1, round(w * s)), max(1, round(h * s))), interpolation=cv2.INTER_AREA)


class ViewerApp:
    """A viser app for one source, or two side by side in compare mode. Thread-safe GUI + playback.

    compare: the second source, shown to the right of ``source`` (a ground truth, or another
    future of the same scene); one frame slider drives both. labels: the names drawn above the
    left and right layers (default :data:`COMPARE_LABELS`), e.g. the two instructions of a
    counterfactual pair. The Compare panel's metrics compare the left layer with the right one.
    """

    def __init__(self, source: Recon4D, *, host: str = "127.0.0.1", port: int = 8080,
                 max_points: int = DEFAULT_MAX_POINTS, compare: Recon4D | None = None,
                 labels: tuple[str, str] = COMPARE_LABELS,
                 metrics: list[dict] | None = None, generate: Generator | None = None,
                 generate_unavailable_reason: str = "Start the viewer with --checkpoint CKPT to generate.",
                 generate_steps: int | None = None, title: str = "tesseract4d"):
        self.host, self.port, self.max_points, self.title = host, int(port), int(max_points), title
        if len(labels) != 2:
            raise ValueError(f"labels names the left and right layers: give two, got {len(labels)}")
        self.labels = (str(labels[0]), str(labels[1]))
        self.layer = SceneLayer(source, "left" if compare is not None else "scene", max_points,
                                label=self.labels[0] if compare is not None else None)
        self.right_layer = SceneLayer(compare, "right", max_points, label=self.labels[1]) if compare is not None else None
        self._link_object_layers()
        self._metrics = metrics
        self._generate = generate
        self._generate_unavailable_reason = generate_unavailable_reason
        self._generate_steps = generate_steps  # the Steps box's first value (the checkpoint preset's)
        self.server = None
        self._lock = threading.RLock()
        self._stop = threading.Event()
        self._playback_thread: threading.Thread | None = None
        self._generation_thread: threading.Thread | None = None
        self._cancel = threading.Event()
        self._generating = False
        self._panels_updated_at = 0.0
        self._slider_synced_at = 0.0
        self._frame = 0
        self.frame_switches = 0  # how often the shown time step changed (for benchmarks)
        self.generation_error: str | None = None
        self.generation_count = 0

    def _link_object_layers(self) -> None:
        """Compare mode: the right source's (the truth's) object paths drawn thin over the left's objects."""
        if self.right_layer is not None and self.right_layer.has_objects:
            self.layer.reference = self.right_layer.recon.objects

    @classmethod
    def from_path(cls, path: str | os.PathLike, *, compare: str | os.PathLike | None = None,
                  metrics: str | os.PathLike | None = None, checkpoint: str | os.PathLike | None = None,
                  camera: str | None = None, precision: str = "auto", **kwargs) -> "ViewerApp":
        """Open PATH (reconstruction folder or dataset episode); see :func:`viewer.sources.load_source`."""
        source = load_source(path, camera=camera)
        gt = None
        if compare is not None:
            try:
                gt = load_source(compare, camera=camera)
            except UserError as e:
                raise UserError(f"--compare: {e}") from e
        rows = None
        if metrics is not None:
            rows = load_report_per_frame(metrics)
        generate = steps = None
        if checkpoint is not None:
            generate, steps = model_generator(checkpoint, source, precision=precision), checkpoint_steps(checkpoint)
        return cls(source, compare=gt, metrics=rows, generate=generate, generate_steps=steps, **kwargs)

    # ------------------------------------------------------------------ lifecycle

    @property
    def url(self) -> str:
        if self.server is None:
            raise RuntimeError("the viewer is not running; call start() first")
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"http://{host}:{self.server.get_port()}"

    def start(self) -> str:
        """Start serving in background threads; returns the URL."""
        _one_line_handshake_errors()
        check_address(self.host, self.port)
        with own_origin_only(self.host):  # a web page from elsewhere cannot connect (viewer/origin.py)
            self.server = make_server(self.host, self.port)
        if self.port and self.server.get_port() != self.port:  # lost a race for the port
            got = self.server.get_port()
            stop_server(self.server)
            self.server = None
            raise UserError(f"port {self.port} on {self.host} is in use (viser fell back to {got}); pass another --port.")
        self.server.gui.configure_theme(control_width="medium", show_share_button=False)
        self.server.gui.set_panel_label(self.title)
        self._build_scene()
        self._build_gui()
        self._stop.clear()
        self._cancel.clear()
        self._playback_thread = threading.Thread(target=self._playback_loop, name="viewer-playback", daemon=True)
        self._playback_thread.start()
        return self.url

    def stop(self) -> None:
        self._stop.set()
        if self._playback_thread is not None:
            self._playback_thread.join(timeout=5)
        self._cancel_generation()
        if self.server is not None:
            stop_server(self.server)
        self.server = None

    def __enter__(self) -> "ViewerApp":
        self.start()
        return self

    def __exit__(self, *exc) -> None:
        self.stop()

    # ------------------------------------------------------------------ scene

    @property
    def num_frames(self) -> int:
        return max(self.layer.recon.num_frames, self.right_layer.recon.num_frames if self.right_layer else 0)

    def _layers(self) -> list[SceneLayer]:
        return [self.layer] + ([self.right_layer] if self.right_layer is not None else [])

    def _build_scene(self) -> None:
        server = self.server
        configure_rendering(server)
        if self.right_layer is not None:
            # The second source to the right of the first (as seen from the first camera).
            right = self.layer.recon.T_world_cam[0, :3, 0]
            self.right_layer.set_offset(right * 2.2 * max(self.layer.radius, self.right_layer.radius))
        for layer in self._layers():
            layer.build(server)
        offset = self.right_layer.offset if self.right_layer is not None else np.zeros(3)
        view = initial_view(self.layer.recon, self.layer.centre + offset / 2, extra_distance=0.4 * float(np.linalg.norm(offset)))
        server.scene.set_up_direction(view["up_axis"])
        cam = server.initial_camera
        cam.position = tuple(view["position"])
        cam.look_at = tuple(view["look_at"])
        cam.up = tuple(view["up"])

    # ------------------------------------------------------------------ GUI

    def _build_gui(self) -> None:
        """The side panel, one folder per step, then the callbacks."""
        gui = self.server.gui
        self._build_playback(gui)
        self._build_display(gui)
        self._build_frame_images(gui)
        self._build_compare(gui)
        self._build_generate(gui)
        self._connect_callbacks()
        self._update_panels(0)

    def _build_playback(self, gui) -> None:
        T = self.num_frames
        with gui.add_folder("Playback"):
            self.frame_slider = gui.add_slider("Frame", min=0, max=max(T - 1, 1), step=1, initial_value=0, disabled=T < 2)
            self.play_checkbox = gui.add_checkbox("Play", initial_value=False, disabled=T < 2)
            self.fps_slider = gui.add_slider("FPS", min=1, max=MAX_FPS, step=1,
                                             initial_value=int(np.clip(round(self.layer.recon.fps), 1, MAX_FPS)))
            self.loop_checkbox = gui.add_checkbox("Loop", initial_value=True)
            # A chained scene's instructions by frame (viewer/timeline.py); empty for one instruction.
            self.timeline_md = gui.add_markdown("")

    def _build_display(self, gui) -> None:
        with gui.add_folder("Display"):
            self.color_dropdown = gui.add_dropdown("Colour", tuple(COLOR_MODES), initial_value="RGB")
            lo, hi, step, size = point_size_range(self.layer.default_point_size)
            self.point_size_slider = gui.add_slider("Point size (m)", min=lo, max=hi, step=step, initial_value=size)
            self.points_dropdown = gui.add_dropdown("Points", tuple(POINT_MODES), initial_value=next(iter(POINT_MODES)))
            # The object layer drawn whole, or the raw predicted points (only with a source that has one).
            self.scene_dropdown = gui.add_dropdown("Scene", tuple(SCENE_MODES), initial_value=next(iter(SCENE_MODES)),
                                                   disabled=not any(layer.has_objects for layer in self._layers()))
            self.frustum_checkbox = gui.add_checkbox("Camera frustums", initial_value=True)
            # Fewer points play faster where the browser draws WebGL in software.
            largest = max(len(p) for layer in self._layers() for p in layer.recon.points_world)
            budgets = point_budgets(min(self.max_points, max(largest, 1)))
            self.budget_dropdown = gui.add_dropdown("Points per frame", tuple(f"{n:,}" for n in budgets), initial_value=f"{budgets[0]:,}")

    def _build_frame_images(self, gui) -> None:
        with gui.add_folder("Frame images"):
            self.rgb_image = gui.add_image(np.zeros((8, 8, 3), np.uint8), label="RGB", format="jpeg")
            self.depth_image = gui.add_image(np.zeros((8, 8, 3), np.uint8), label="Depth (turbo, near=blue)", format="jpeg")
            self.normal_image = gui.add_image(np.zeros((8, 8, 3), np.uint8), label="Normal (camera frame)", format="jpeg")

    def _build_compare(self, gui) -> None:
        self.layout_dropdown = None
        self.metrics_md = self.compare_md = None
        if self.right_layer is None:
            return
        with gui.add_folder("Compare"):
            self.layout_dropdown = gui.add_dropdown("Layout", COMPARE_LAYOUTS, initial_value=COMPARE_LAYOUTS[0])
            self.compare_md = gui.add_markdown(self._compare_text())
            self.metrics_md = gui.add_markdown("")
        if self._metrics is None:
            self._metrics = image_metrics(self.layer.recon, self.right_layer.recon)
        self.layout_dropdown.on_update(lambda _: self._apply_layout())

    def _compare_text(self) -> str:
        return f"Left: {self.labels[0]}. Right: {self.labels[1]}. Metrics: left against right."

    def _build_generate(self, gui) -> None:
        with gui.add_folder("Generate"):
            instruction = str(self.layer.recon.metadata.get("instruction", ""))
            self.instruction_text = gui.add_text("Instruction", initial_value=instruction)
            self.seed_number = gui.add_number("Seed", initial_value=0, min=0, step=1)
            self.steps_number = gui.add_number("Steps", initial_value=self._generate_steps or MIN_STEPS, min=MIN_STEPS,
                                               max=MAX_STEPS, step=1)
            self.generate_button = gui.add_button("Generate", disabled=self._generate is None)
            self.progress_bar = gui.add_progress_bar(0.0, visible=False)
            self.status_md = gui.add_markdown("Ready." if self._generate is not None else self._generate_unavailable_reason)

    def _connect_callbacks(self) -> None:
        self.frame_slider.on_update(lambda _: self._show_frame(int(self.frame_slider.value)))
        self.color_dropdown.on_update(lambda _: self._recolor())
        self.point_size_slider.on_update(lambda _: self._resize_points())
        self.points_dropdown.on_update(lambda _: self._rebuild())
        self.scene_dropdown.on_update(lambda _: self._rebuild())
        self.frustum_checkbox.on_update(lambda _: self._toggle_frustums())
        self.budget_dropdown.on_update(lambda _: self._change_budget(int(self.budget_dropdown.value.replace(",", ""))))
        self.play_checkbox.on_update(lambda _: self._on_play_toggled())
        self.generate_button.on_click(lambda _: self._start_generation())

    def _color_mode(self) -> str:
        return COLOR_MODES[self.color_dropdown.value]

    @property
    def frame(self) -> int:
        """The time step shown now."""
        return self._frame

    def _show_frame(self, t: int) -> None:
        with self._lock:
            if t != self._frame:
                self.frame_switches += 1
            self._frame = t
            with self.server.atomic():
                for layer in self._layers():
                    layer.show(t)
            # While playing, refresh the side images a few times a second only: decoding three
            # images per frame in the page halves the software-WebGL frame rate.
            now = time.perf_counter()
            if not self.play_checkbox.value or now - self._panels_updated_at >= PANEL_REFRESH_WHILE_PLAYING_S:
                self._update_panels(t)
                self._panels_updated_at = now

    def _update_panels(self, t: int) -> None:
        r = self.layer.recon
        i = self.layer.frame_index(t)
        self.rgb_image.image = _panel_image(r.rgb[i])
        self.depth_image.image = _panel_image(colorize_depth(r.depth_m[i], *self.layer.depth_limits))
        self.normal_image.image = _panel_image(colorize_normals(r.normal_cam[i]))
        schedule = scene_schedule(r.metadata)
        self.timeline_md.content = "" if schedule is None else timeline_markdown(schedule, t, self.num_frames)
        if self.metrics_md is not None:
            rows = self._metrics or []
            self.metrics_md.content = format_metrics(rows[t] if t < len(rows) else None, t)

    def _on_play_toggled(self) -> None:
        with self._lock:
            if not self.play_checkbox.value:  # paused: the slider and images show the exact frame
                self.frame_slider.value = self._frame
                self._update_panels(self._frame)
            elif self._frame >= self.num_frames - 1 and not self.loop_checkbox.value:
                # Play at the end of a clip that does not loop plays it again from the start.
                self._show_frame(0)
                self.frame_slider.value = 0

    def _recolor(self) -> None:
        with self._lock:
            for layer in self._layers():
                layer.set_color_mode(self._color_mode())

    def _resize_points(self) -> None:
        with self._lock:
            for layer in self._layers():
                layer.set_point_size(float(self.point_size_slider.value))

    def _toggle_frustums(self) -> None:
        with self._lock:
            for layer in self._layers():
                layer.set_frustums_visible(bool(self.frustum_checkbox.value))

    def _change_budget(self, max_points: int) -> None:
        """Send every frame again with a different point budget, sized to close the gaps."""
        with self._lock:
            self.max_points = int(max_points)
            for layer in self._layers():
                layer.set_max_points(self.max_points)
            self._set_point_size_range(self.layer.default_point_size)
            self._rebuild()

    def _set_point_size_range(self, size: float) -> None:
        slider = self.point_size_slider
        slider.min, slider.max, slider.step, slider.value = point_size_range(size)

    def _rebuild(self) -> None:
        with self._lock:
            for layer in self._layers():
                layer.build(self.server, color_mode=self._color_mode(), point_size=float(self.point_size_slider.value),
                            point_mode=POINT_MODES[self.points_dropdown.value],
                            show_frustums=bool(self.frustum_checkbox.value), t=self._frame,
                            objects=SCENE_MODES[self.scene_dropdown.value])
            self._apply_layout()

    def _apply_layout(self) -> None:
        if self.right_layer is None or self.layout_dropdown is None:
            return
        layout = self.layout_dropdown.value
        with self._lock, self.server.atomic():
            side = layout == COMPARE_LAYOUTS[0]
            right = self.layer.recon.T_world_cam[0, :3, 0]
            self.right_layer.set_offset(right * 2.2 * max(self.layer.radius, self.right_layer.radius) if side else np.zeros(3))
            self.layer.set_visible(layout != COMPARE_LAYOUTS[2])
            self.right_layer.set_visible(layout != COMPARE_LAYOUTS[1])

    # ------------------------------------------------------------------ playback

    def _playback_loop(self) -> None:
        while not self._stop.is_set():
            if self.server is not None and self.play_checkbox.value and self.num_frames > 1:
                t = self._frame + 1
                if t >= self.num_frames:
                    if self.loop_checkbox.value:
                        t = 0
                    else:
                        self.play_checkbox.value = False
                        continue
                self._show_frame(t)
                # Move the slider a few times a second only: a GUI update per frame costs the
                # page ~20% of its software-WebGL frame rate. The slider's own callback then
                # finds the frame already shown.
                now = time.perf_counter()
                if now - self._slider_synced_at >= PANEL_REFRESH_WHILE_PLAYING_S / 2:
                    self._slider_synced_at = now
                    self.frame_slider.value = t
            self._stop.wait(1.0 / max(float(self.fps_slider.value), 1.0))

    # ------------------------------------------------------------------ generation

    def set_source(self, recon: Recon4D) -> None:
        """Replace the shown (predicted) source, e.g. with a freshly generated one."""
        with self._lock:
            self.layer.remove()
            label = self.layer.label
            if self.right_layer is not None and recon.metadata.get("instruction"):
                label = _short_label(str(recon.metadata["instruction"]))
                self.labels = (label, self.labels[1])
                self.compare_md.content = self._compare_text()
            self.layer = SceneLayer(recon, self.layer.name, self.max_points, label=label)
            self._link_object_layers()
            self.scene_dropdown.disabled = not any(layer.has_objects for layer in self._layers())
            if self.right_layer is not None:
                self._metrics = image_metrics(self.layer.recon, self.right_layer.recon)
            T = self.num_frames
            self.frame_slider.max = max(T - 1, 1)
            self.frame_slider.disabled = self.play_checkbox.disabled = T < 2
            self._frame = 0
            self._rebuild()
            self.frame_slider.value = 0
            self._update_panels(0)
            instruction = recon.metadata.get("instruction")
            if instruction:
                self.instruction_text.value = str(instruction)

    def _start_generation(self) -> None:
        with self._lock:
            if self._generating or self._generate is None or self._stop.is_set():
                return
            self._generating = True
        args = (str(self.instruction_text.value), int(self.seed_number.value), int(self.steps_number.value))
        self._generation_thread = threading.Thread(target=self._run_generation, args=args, name="viewer-generate",
                                                   daemon=True)
        self._generation_thread.start()

    def _cancel_generation(self) -> None:
        """Stop a running generation at its next step and wait for it (the model must not be left
        running in a thread while the process exits)."""
        thread = self._generation_thread
        if thread is None or not thread.is_alive():
            return
        self._cancel.set()
        print("viewer: stopping the generation at its next step", file=sys.stderr, flush=True)
        thread.join(timeout=GENERATION_STOP_WAIT_S)

    def _progress(self, fraction: float, message: str, rgb: np.ndarray | None = None) -> None:
        if self._cancel.is_set():
            raise GenerationCancelled()
        self.progress_bar.value = float(np.clip(100.0 * fraction, 0.0, 100.0))
        self.status_md.content = f"Generating: {message}"
        if rgb is not None:  # streaming: the newest decoded frame, before the whole future is reconstructed
            self.rgb_image.image = _panel_image(rgb)

    def _run_generation(self, instruction: str, seed: int, steps: int) -> None:
        self.generate_button.disabled = True
        self.progress_bar.visible = True
        self.generation_error = None
        self._progress(0.0, f"{instruction!r}, seed {seed}, {steps} steps")
        try:
            if not instruction.strip():
                raise UserError("type an instruction first")
            recon = self._generate(instruction, seed, steps, self._progress)
            if self._cancel.is_set():
                raise GenerationCancelled()
            recon.metadata.setdefault("instruction", instruction)
            self.set_source(recon)
            self.generation_count += 1
            self.progress_bar.value = 100.0
            self.status_md.content = f"Done: {recon.num_frames} frames for {instruction!r} (seed {seed}, {steps} steps)."
        except GenerationCancelled:
            self.status_md.content = "Cancelled: the viewer is stopping."
        except Exception as e:  # shown to the user; the server keeps running
            message = f"{type(e).__name__}: {e}" if not isinstance(e, UserError) else str(e)
            self.generation_error = message
            self.status_md.content = f"**Generation failed:** {message}"
            if not isinstance(e, UserError):
                traceback.print_exc(file=sys.stderr)
            if self.server is not None:
                for client in self.server.get_clients().values():
                    client.add_notification("Generation failed", message, color="red", auto_close_seconds=10.0)
        finally:
            self.progress_bar.visible = False
            self.generate_button.disabled = False
            with self._lock:
                self._generating = False

    @property
    def generating(self) -> bool:
        return self._generating


def _short_label(text: str, max_chars: int = 48) -> str:
    """A label drawn above a point cloud: the text on one line, cut with an ellipsis if long."""
    text = " ".join(text.split())
    return text if len(text) <= max_chars else text[: max_chars - 1].rstrip() + "…"


def point_size_range(size: float) -> tuple[float, float, float, float]:
    """(min, max, step, value) of the point size slider around the size that closes the gaps."""
    return round(size / 4, 5), round(size * 6, 5), round(size / 20, 6) or 1e-5, round(size, 5)


def point_budgets(max_points: int) -> list[int]:
    """The per-frame point budgets offered in the viewer: the given one (at most the points a
    frame has) and smaller steps down to 1,000."""
    return sorted({int(max_points), *(b for b in (max_points // 2, max_points // 5, max_points // 10) if b >= 1000)}, reverse=True)


class _HandshakeErrorFilter:
    """A malformed HTTP/WebSocket request is the client's problem: one line, no traceback (the
    server drops that connection and goes on serving)."""

    def filter(self, record) -> bool:
        if record.exc_info:
            cause = record.exc_info[1]
            detail = f"{cause}: {cause.__cause__}" if cause is not None and cause.__cause__ else repr(cause)
            record.msg, record.args = f"viewer: dropped a malformed request ({record.getMessage()}: {detail})", ()
            record.exc_info = record.exc_text = None
        return True


def _one_line_handshake_errors() -> None:
    import logging

    log = logging.getLogger("websockets.server")
    if not any(isinstance(f, _HandshakeErrorFilter) for f in log.filters):
        log.addFilter(_HandshakeErrorFilter())


def network_warning(host: str) -> str | None:
    """A warning when ``host`` exposes the viewer beyond this machine (no authentication)."""
    import ipaddress

    try:
        loopback = ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:
        loopback = host == "localhost"
    if loopback:
        return None
    return (f"warning: --host {host} makes the viewer reachable from the network, without a password: anyone who "
            f"can reach this machine can watch and, with --checkpoint, run the model; use --host 127.0.0.1 "
            f"(and an SSH tunnel) unless that is intended")


def serve_forever(app: ViewerApp) -> None:
    """Start, print the URL, block until Ctrl-C or SIGTERM, stop."""
    import signal
    import sys


    def _terminate(signum, frame):
        raise Terminated()  # the same clean stop as Ctrl-C

    # Installed before the URL is printed: whoever reads the URL may stop the viewer at once.
    previous = signal.signal(signal.SIGTERM, _terminate) if threading.current_thread() is threading.main_thread() else None
    try:
        url = app.start()  # checks the address first: one that cannot serve warns of nothing
        if note := network_warning(app.host):
            print(note, file=sys.stderr, flush=True)
        print(f"viewer: {url}  (Ctrl-C to stop)", flush=True)
        while True:
            threading.Event().wait(3600)
    finally:
        app.stop()
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)

