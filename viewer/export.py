"""Standalone HTML recording of the playback (viser's scene serializer): opens from disk, no server.

Only the 3D scene is recorded (GUI panels are not): every frame's point cloud and frustum,
with visibility switched at the source's fps. The page's own player plays it back.
"""

from __future__ import annotations

import os
from pathlib import Path

from reconstruction.recon4d import Recon4D
from viewer.scene import DEFAULT_MAX_POINTS, SceneLayer, configure_rendering, initial_view, make_server, stop_server
from tesseract4d.outputs import OutputFile
from viewer.sources import load_source


HTML_MARK = "<!-- tesseract4d view --export -->"


def is_export(path: Path) -> bool:
    """An earlier export (safe to replace)."""
    try:
        with open(path, "rb") as f:
            return f.read(len(HTML_MARK)) == HTML_MARK.encode()
    except OSError:
        return False


def export_html(source: Recon4D | str | os.PathLike, out_path: str | os.PathLike,
                max_points: int = DEFAULT_MAX_POINTS, color_mode: str = "rgb", fps: float | None = None,
                inputs: tuple = (), overwrite: bool = False) -> Path:
    """Write the recording to ``out_path`` (atomically) and return it. An existing file is replaced
    only if it is an earlier export (or with ``overwrite``); ``inputs`` are never written."""
    out = Path(out_path)
    output = OutputFile(out, inputs=inputs, overwrite=overwrite, flag="--export", is_ours=is_export)
    if not isinstance(source, Recon4D):
        source = load_source(source)
    layer = SceneLayer(source, "scene", max_points)
    server = make_server("127.0.0.1", 0)
    try:
        configure_rendering(server)
        layer.build(server, color_mode=color_mode)
        view = initial_view(source, layer.centre)
        server.scene.set_up_direction(view["up_axis"])
        server.initial_camera.position = tuple(view["position"])
        server.initial_camera.look_at = tuple(view["look_at"])
        server.initial_camera.up = tuple(view["up"])
        serializer = server.get_scene_serializer()
        dt = 1.0 / (fps or source.fps or 10.0)
        for t in range(source.num_frames):
            with server.atomic():
                layer.show(t)
            serializer.insert_sleep(dt)
        html = serializer.as_html()
    finally:
        stop_server(server)
    with output as tmp:
        tmp.write_text(HTML_MARK + "\n" + html)
    return out
