"""One 4D source drawn into a viser scene: the part shared by the live app and the HTML export.

A :class:`SceneLayer` owns the scene nodes of one :class:`Recon4D` under ``/<name>``:

    /<name>                     a frame at the layer's offset (compare mode moves it sideways)
    /<name>/frames/<t>          one point cloud per time step; only the current one is visible
    /<name>/cams/<t>            one camera frustum per time step, textured with that frame's RGB
    /<name>/background          the fused static background points (if the source has them)
    /<name>/objects/<k>         the object layer (if the source has one): object k's rigid points, named,
                                placed at the current frame's T_world_object; its label says its state
    /<name>/paths/<k>           object k's path over the clip (its origin per frame) as a polyline
    /<name>/reference/<k>       compare mode: the other layer's (the truth's) path of the same object, thin

With the object layer shown, the per-frame clouds leave out the points that belong to an object (the
objects are drawn whole instead); what stays is the arm and the rest of the scene.

Points are decimated to a per-frame budget and sent relative to the layer's centre, so float16
positions keep <= 1 mm rounding error for points within ~2 m of it; larger scenes use float32.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from reconstruction.recon4d import Recon4D
from tesseract4d.colors import depth_range, point_colors
from tesseract4d.geometry import scene_up_axis

DEFAULT_MAX_POINTS = 50_000
# float16 has 11 significant bits: rounding error at |x| = r is at most r * 2**-11. Use it only
# where that error stays below this (metres), i.e. for points within ~2 m of the layer centre.
FLOAT16_MAX_ERROR_M = 1e-3
FRUSTUM_IMAGE_MAX_SIDE = 128
# Camera frustums are drawn this fraction of the way from the first camera to the scene centre.
FRUSTUM_SCALE_OF_DISTANCE = 0.15
# Percentile of the points' distances from the centre used as the scene radius.
RADIUS_PERCENTILE = 90
RADIUS_SAMPLE_PER_FRAME = 10_000
# Which points are drawn: GUI label -> key.
POINT_MODES: dict[str, str] = {
    "Per-frame points": "frames",
    "Static background + moving points": "background+dynamic",
    "Static background only": "background",
}
# Raw predicted points, or the object layer drawn whole (GUI label -> flag).
SCENE_MODES: dict[str, bool] = {"Object layer": True, "Raw points": False}
PATH_THICKNESS_M = 0.003
REFERENCE_THICKNESS_M = 0.0015
REFERENCE_RGB = (250, 250, 250)


@dataclass
class FramePoints:
    """The decimated points of one time step, relative to the layer centre."""

    points_local: np.ndarray  # (N, 3) float32, metres, world axes, origin at the layer centre
    rgb: np.ndarray  # (N, 3) uint8
    normals: np.ndarray  # (N, 3) float32 world frame
    depth_m: np.ndarray  # (N,) float32, depth along this frame's camera axis
    dynamic: np.ndarray  # (N,) bool
    object_index: np.ndarray | None = None  # (N,) int16: the object each point belongs to, -1 none (None: unlabelled)


def decimate(n: int, budget: int, seed: int = 0) -> np.ndarray:
    """Sorted indices of at most ``budget`` of n items, chosen uniformly at random (seeded)."""
    if n <= budget:
        return np.arange(n)
    return np.sort(np.random.default_rng(seed).choice(n, size=budget, replace=False))


def make_server(host: str, port: int):
    """A viser server without its start-up banner (callers print their own URL)."""
    import contextlib
    import io

    import viser

    with contextlib.redirect_stdout(io.StringIO()):
        return viser.ViserServer(host=host, port=port, verbose=False)


def stop_server(server) -> None:
    """Stop a viser server without its "(viser) Server stopped" line."""
    import contextlib
    import io

    with contextlib.redirect_stdout(io.StringIO()):
        server.stop()


def configure_rendering(server) -> None:
    """Scene-wide settings for speed in software WebGL: points are unlit, so no shadow passes
    and no environment map are needed."""
    server.scene.configure_default_lights(enabled=True, cast_shadow=False)
    server.scene.configure_environment_map(hdri=None)


def wxyz_from_matrix(R: np.ndarray) -> np.ndarray:
    import viser.transforms as vtf

    return vtf.SO3.from_matrix(np.asarray(R, np.float64)).wxyz


class SceneLayer:
    """The scene nodes of one source. Build with :meth:`build`, then :meth:`show` a frame."""

    def __init__(self, recon: Recon4D, name: str = "scene", max_points: int = DEFAULT_MAX_POINTS,
                 label: str | None = None):
        recon.validate()
        self.recon = recon
        self.name = name
        self.label = label  # drawn above the points when given (compare mode names its layers)
        self.max_points = int(max_points)
        first = recon.points_world[0] if len(recon.points_world[0]) else np.concatenate(recon.points_world + [recon.background_points])
        self.centre = np.median(first, axis=0).astype(np.float64) if len(first) else recon.T_world_cam[0, :3, 3].copy()
        clouds = [p for p in recon.points_world + [recon.background_points] if len(p)]
        # The scene's size for framing and for compare mode's offset: most points, not the few far
        # ones (a floor seen up to the horizon would otherwise make the scene metres wide). From a
        # fixed sample per frame, so it does not depend on the point budget or cost much at start-up.
        sample = [p[decimate(len(p), RADIUS_SAMPLE_PER_FRAME, seed=i)] - self.centre for i, p in enumerate(clouds)]
        self.radius = float(np.percentile(np.linalg.norm(np.concatenate(sample), axis=1), RADIUS_PERCENTILE)) if sample else 1.0
        # Precision from every point, so that it holds for any point budget.
        max_abs = max((float(np.abs(p - self.centre).max()) for p in clouds), default=0.0)
        self.precision = "float16" if max_abs * 2.0**-11 <= FLOAT16_MAX_ERROR_M else "float32"
        self._decimate()
        self.depth_limits = depth_range(recon.depth_m)
        self.offset = np.zeros(3)
        self.server = None
        self._root = None
        self._clouds: list = []
        self._frustums: list = []
        self._background_node = None
        self._label_node = None
        self._current = 0
        self._point_mode = "frames"
        self._objects_shown = False
        self._object_nodes: list = []
        self._object_labels: list = []
        self._object_clouds: list = []
        self.reference = None  # compare mode: the other source's object layer, its paths drawn thin here

    # ------------------------------------------------------------------ data

    def _decimate(self) -> None:
        """The points sent to the browser under the current budget, and the point size that closes
        the gaps between them."""
        r = self.recon
        self.frames = [self._prepare(t) for t in range(r.num_frames)]
        keep = decimate(len(r.background_points), 2 * self.max_points, seed=12345)
        self.background = FramePoints(
            points_local=(r.background_points[keep] - self.centre).astype(np.float32),
            rgb=r.background_colors[keep], normals=r.background_normals[keep],
            depth_m=self._camera_depth(0, r.background_points[keep]), dynamic=np.zeros(len(keep), bool),
        )
        self.default_point_size = self._pixel_footprint()

    def set_max_points(self, max_points: int) -> None:
        """Change the per-frame point budget (then :meth:`build` again to send the new points)."""
        if max_points < 1:
            raise ValueError(f"the point budget must be positive, got {max_points}")
        self.max_points = int(max_points)
        self._decimate()

    def _camera_depth(self, t: int, points_world: np.ndarray) -> np.ndarray:
        T = self.recon.T_world_cam[t]
        return ((points_world - T[:3, 3]) @ T[:3, 2]).astype(np.float32)

    def _prepare(self, t: int) -> FramePoints:
        r = self.recon
        keep = decimate(len(r.points_world[t]), self.max_points, seed=t)
        pts = r.points_world[t][keep]
        labels = r.objects.point_object if r.objects is not None else []
        return FramePoints(
            points_local=(pts - self.centre).astype(np.float32), rgb=r.colors[t][keep],
            normals=r.normals_world[t][keep], depth_m=self._camera_depth(t, pts), dynamic=r.dynamic[t][keep].astype(bool),
            object_index=np.asarray(labels[t])[keep] if labels else None,
        )

    def _mask(self, fr: FramePoints):
        """Which of a frame's points the per-frame cloud draws under the current point and scene modes."""
        mask = fr.dynamic.copy() if self._point_mode == "background+dynamic" else np.ones(len(fr.dynamic), bool)
        if self._objects_shown and fr.object_index is not None:
            mask &= fr.object_index < 0
        return mask

    def _pixel_footprint(self) -> float:
        """Point size (m) that closes the gaps: one pixel's footprint at the median depth, times
        the decimation's spacing factor."""
        d = self.recon.depth_m[0]
        d = d[np.isfinite(d) & (d > 0)]
        if d.size == 0:
            return 0.01 * self.radius
        f = float(self.recon.K[0, 0, 0])
        n_total = max(len(self.recon.points_world[0]), 1)
        spacing = np.sqrt(n_total / max(len(self.frames[0].points_local), 1))
        return float(1.2 * np.median(d) / f * spacing)

    def colors(self, frame: FramePoints, mode: str) -> np.ndarray:
        return point_colors(mode, frame.rgb, frame.normals, frame.depth_m, frame.dynamic, self.depth_limits)

    def frame_index(self, t: int) -> int:
        """The layer's frame shown at global time t (the last one once this layer has ended)."""
        return int(min(max(t, 0), self.recon.num_frames - 1))

    # ------------------------------------------------------------------ scene nodes

    @property
    def has_objects(self) -> bool:
        return self.recon.objects is not None and len(self.recon.objects) > 0

    def build(self, server, color_mode: str = "rgb", point_size: float | None = None, point_mode: str = "frames",
              show_frustums: bool = True, t: int = 0, objects: bool = True) -> None:
        """(Re)create every node of this layer in ``server.scene``, showing frame t. ``objects``: draw the
        object layer (when the source has one) instead of the objects' raw points."""
        self.remove()
        self.server = server
        size = self.default_point_size if point_size is None else point_size
        self._current = self.frame_index(t)
        self._point_mode = point_mode
        self._objects_shown = bool(objects) and self.has_objects
        with server.atomic():
            self._root = server.scene.add_frame(f"/{self.name}", show_axes=False, position=tuple(self.offset))
            if self.label:
                up = -self.recon.T_world_cam[0, :3, 1]  # the first camera's up (OpenCV y points down)
                self._label_node = server.scene.add_label(
                    f"/{self.name}/label", self.label, position=tuple(self.centre + 0.8 * self.radius * up),
                    anchor="bottom-center", font_screen_scale=1.2)
            for i, fr in enumerate(self.frames):
                mask = self._mask(fr)
                self._clouds.append(server.scene.add_point_cloud(
                    f"/{self.name}/frames/{i}", points=fr.points_local[mask], colors=self.colors(fr, color_mode)[mask],
                    point_size=size, precision=self.precision, position=tuple(self.centre),
                    point_shape="square", point_shading="flat",
                    visible=(i == self._current and point_mode != "background"),
                ))
                self._frustums.append(self._add_frustum(server, i, visible=show_frustums and i == self._current))
            if len(self.background.points_local):
                self._background_node = server.scene.add_point_cloud(
                    f"/{self.name}/background", points=self.background.points_local,
                    colors=self.colors(self.background, color_mode), point_size=size, precision=self.precision,
                    position=tuple(self.centre), point_shape="square", point_shading="flat",
                    visible=point_mode != "frames",
                )
            if self._objects_shown:
                self._add_objects(server, size)
        self._show_frustums = show_frustums

    def _add_objects(self, server, point_size: float) -> None:
        """The object layer's nodes: each object whole at the current frame, named, and its path."""
        layer = self.recon.objects
        up = scene_up_axis(self.recon.T_world_cam[0])
        for k, tr in enumerate(layer.tracks):
            T = tr.T_world_object[self._current]
            node = server.scene.add_frame(f"/{self.name}/objects/{k}", show_axes=False,
                                          wxyz=wxyz_from_matrix(T[:3, :3]), position=tuple(T[:3, 3]))
            self._object_clouds.append(server.scene.add_point_cloud(
                f"/{self.name}/objects/{k}/points", points=tr.points_object.astype(np.float32), colors=tr.colors,
                point_size=point_size, point_shape="square", point_shading="flat"))
            height = float(np.max(tr.points_object @ up)) if len(tr.points_object) else 0.0
            label = server.scene.add_label(f"/{self.name}/objects/{k}/label", self._object_text(k),
                                           position=tuple((height + 0.015) * up), anchor="bottom-center",
                                           font_screen_scale=0.9)
            self._object_nodes.append(node)
            self._object_labels.append(label)
            path = tr.positions_world()
            if len(path) > 1:
                server.scene.add_line_segments(
                    f"/{self.name}/paths/{k}", points=np.stack([path[:-1], path[1:]], 1).astype(np.float32),
                    colors=tuple(int(c) for c in tr.color), thickness=PATH_THICKNESS_M)
        if self.reference is not None:
            for k, tr in enumerate(self.reference.tracks):
                path = tr.positions_world()
                if len(path) > 1:
                    server.scene.add_line_segments(
                        f"/{self.name}/reference/{k}", points=np.stack([path[:-1], path[1:]], 1).astype(np.float32),
                        colors=REFERENCE_RGB, thickness=REFERENCE_THICKNESS_M)

    def _object_text(self, k: int) -> str:
        tr = self.recon.objects.tracks[k]
        state = tr.states()[self._current]
        return tr.name if state == "tracked" else f"{tr.name} ({state})"

    def _add_frustum(self, server, t: int, visible: bool):
        import cv2

        r = self.recon
        H, W = r.rgb.shape[1:3]
        scale = FRUSTUM_IMAGE_MAX_SIDE / max(H, W)
        image = r.rgb[t] if scale >= 1 else cv2.resize(r.rgb[t], (max(1, round(W * scale)), max(1, round(H * scale))), interpolation=cv2.INTER_AREA)
        fov_y = 2.0 * np.arctan2(H / 2.0, float(r.K[t, 1, 1]))
        T = r.T_world_cam[t]
        size_m = FRUSTUM_SCALE_OF_DISTANCE * float(np.linalg.norm(r.T_world_cam[0, :3, 3] - self.centre)) or 0.15 * self.radius
        return server.scene.add_camera_frustum(
            f"/{self.name}/cams/{t}", fov=float(fov_y), aspect=W / H, scale=size_m,
            thickness=0.03 * size_m, color=(40, 40, 40), image=image, format="jpeg", jpeg_quality=85, cast_shadow=False, receive_shadow=False,
            wxyz=wxyz_from_matrix(T[:3, :3]), position=tuple(T[:3, 3]), visible=visible,
        )

    def show(self, t: int) -> None:
        """Make global time t visible (call inside ``server.atomic()`` together with other layers)."""
        i = self.frame_index(t)
        if i == self._current or not self._clouds:
            return
        per_frame = self._point_mode != "background"
        self._clouds[self._current].visible = False
        self._clouds[i].visible = per_frame
        self._frustums[self._current].visible = False
        self._frustums[i].visible = self._show_frustums
        self._current = i
        for k, (node, label) in enumerate(zip(self._object_nodes, self._object_labels)):
            T = self.recon.objects.tracks[k].T_world_object[i]
            node.wxyz = wxyz_from_matrix(T[:3, :3])
            node.position = tuple(T[:3, 3])
            text = self._object_text(k)
            if label.text != text:
                label.text = text

    def set_color_mode(self, mode: str) -> None:
        with self.server.atomic():
            for fr, cloud in zip(self.frames, self._clouds):
                cloud.colors = self.colors(fr, mode)[self._mask(fr)]
            if self._background_node is not None:
                self._background_node.colors = self.colors(self.background, mode)

    def set_point_size(self, size: float) -> None:
        with self.server.atomic():
            for cloud in self._clouds + self._object_clouds + ([self._background_node] if self._background_node is not None else []):
                cloud.point_size = float(size)

    def set_frustums_visible(self, visible: bool) -> None:
        self._show_frustums = visible
        if self._frustums:
            self._frustums[self._current].visible = visible

    def set_visible(self, visible: bool) -> None:
        if self._root is not None:
            self._root.visible = visible

    def set_offset(self, offset: np.ndarray) -> None:
        self.offset = np.asarray(offset, np.float64)
        if self._root is not None:
            self._root.position = tuple(self.offset)

    def remove(self) -> None:
        if self._root is not None:
            self._root.remove()  # removes the children too
        self._root, self._clouds, self._frustums, self._background_node, self._label_node = None, [], [], None, None
        self._object_nodes, self._object_labels, self._object_clouds = [], [], []


def initial_view(recon: Recon4D, look_at: np.ndarray, extra_distance: float = 0.0) -> dict:
    """Initial viewer camera: behind and above the first recording camera, looking at the scene
    (``extra_distance`` metres further back, e.g. to fit two side-by-side layers).

    Returns position, look_at and up (world vectors) and the scene's up axis as "+z"-style text.
    """
    T = np.asarray(recon.T_world_cam[0], np.float64)
    eye = T[:3, 3]
    up_world = scene_up_axis(T)
    axis = int(np.argmax(np.abs(up_world)))
    up_axis = ("+" if up_world[axis] > 0 else "-") + "xyz"[axis]
    # Swing 50 degrees around the up axis and pull back, so the recording camera's frustum is
    # seen from the side instead of covering the points it recorded.
    back = eye - look_at
    angle = np.deg2rad(50.0)
    along = np.dot(back, up_world) * up_world
    across = back - along
    swung = along + np.cos(angle) * across + np.sin(angle) * np.cross(up_world, across)
    distance = 1.6 * np.linalg.norm(back) + extra_distance
    position = look_at + distance * swung / np.linalg.norm(swung) + 0.2 * np.linalg.norm(back) * up_world
    return {"position": position, "look_at": np.asarray(look_at, np.float64), "up": up_world, "up_axis": up_axis}
