"""Object poses perceived from a rendered observation (depth + segmentation camera), never from the
simulator's state.

The plan arms of the closed loop (``tesseract4d.policy.plan``) act on where the objects are now. Each
object's model is built once, from the episode's first observation, by the object layer
(:func:`reconstruction.objects.track_objects` on that one frame: its points in its own frame, their
normals); in every later observation the object's pixels (its segmentation id) are back-projected and
the model is fitted to them by a trimmed point-to-plane ICP (observed point -> nearest model point,
steps by :func:`reconstruction.objects.plane_step`) in translation and a turn about the scene's up
axis, started from the last pose's turn and from the turn the side faces seen now show (their dominant
horizontal normal, modulo 90 degrees: at 128² the ICP alone kept a 30-degree turn wrong at a 3 mm fit).
The pose is the object layer's
``T_world_object`` (origin at the first-frame centroid of the object's seen points, world axes at the
first frame).

What a motion planner needs beside it is read from the first frame, also from the camera only: the
object's centre (the middle of its top face, lowered by half its height; the table top is the world's
z = ``TABLE_Z_M``, as in every ManiSkill tabletop scene), its half height, and the direction of its side
faces (the dominant horizontal normal, modulo 90 degrees), which the grasp closes across.

Measured (tests/policy/test_perception.py): on StackCube at 128² with the cube moved and turned in the
simulator, the perceived centre is within ``CENTRE_TOL_M`` and the face direction within
``FACE_TOL_DEG`` of the simulator's pose.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from reconstruction.hand_track import TABLE_Z_M
from reconstruction.objects import first_frame_masks, plane_step, rotation_about, track_objects, yaw_about
from tesseract4d.geometry import rotate_vectors, scene_up_axis, transform_points, unproject_depth
from tesseract4d.object_colours import OBJECT_COLOUR_TOL, min_colour_distance
from tesseract4d.segments import SCENERY_SEGMENTS

TOP_FACE_M = 0.006  # points this close below an object's highest point form its top face
MIN_PIXELS = 6  # fewer pixels of an object: not seen in this observation (its last pose is kept)
ICP_ITERATIONS = 20
TRIM_SHARE = 0.8  # the share of nearest-point pairs kept (the closest)
PALETTE_SIZE = 48
COLOUR_SEARCH_M = 0.35  # a frame without segmentation: the object's colours this close to where it started
CENTRE_TOL_M = 0.01  # what the sim test asserts
FACE_TOL_DEG = 10.0


@dataclass
class PerceivedObject:
    """One object as the camera shows it now (world metres)."""

    name: str
    colour_name: str
    centre_world_m: np.ndarray  # (3,) the object's centre
    face_yaw_rad: float  # direction of a side face's normal about +z, modulo pi/2
    half_height_m: float
    T_world_object: np.ndarray  # (4, 4) the object layer's pose (see the module docstring)
    seen_px: int  # pixels of the object in this observation (0: not seen, last pose kept)
    fit_rms_m: float  # root mean square distance of the kept ICP pairs (nan when not seen)


@dataclass
class _Model:
    name: str
    seg_id: int
    colour_name: str
    points: np.ndarray  # (N, 3) object frame
    normals: np.ndarray  # (N, 3) object frame
    centre_object: np.ndarray  # (3,) the object's centre in its own frame
    face_yaw0: float
    half_height_m: float
    palette: np.ndarray  # (M, 3) float32: the object's own colours (the object layer's model)
    start_world_m: np.ndarray  # (3,) its origin at the first frame


@dataclass
class _FrameView:
    rgb: np.ndarray
    depth_m: np.ndarray
    normal_cam: np.ndarray
    K: np.ndarray
    T_world_cam: np.ndarray


def _world_points(frame, mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(N, 3) world points and (N, 3) world normals of the pixels of ``mask`` with a depth."""
    sel = mask & (frame.depth_m > 0) & np.isfinite(frame.depth_m)
    pts_cam = unproject_depth(frame.depth_m, frame.K)[sel]
    pts = transform_points(frame.T_world_cam, pts_cam).astype(np.float64)
    normals = rotate_vectors(frame.T_world_cam, np.asarray(frame.normal_cam, np.float64)[sel])
    return pts, normals


def face_yaw(normals_world: np.ndarray) -> float:
    """The direction (radians, in [-pi/4, pi/4)) of the side faces of a box whose surface normals are
    ``normals_world`` (N, 3): the circular mean of four times the horizontal normals' angle, over 4.
    0.0 when there is no side face (a cylinder's normals cancel out; any direction grasps it)."""
    n = np.asarray(normals_world, np.float64)
    side = n[np.abs(n[:, 2]) < 0.5] if len(n) else n
    if len(side) == 0:
        return 0.0
    ang = np.arctan2(side[:, 1], side[:, 0])
    z = np.exp(4j * ang).mean()
    return float(np.angle(z) / 4) if abs(z) > 0.2 else 0.0


def wrap_quarter(angle_rad: float) -> float:
    """An angle modulo pi/2, in [-pi/4, pi/4) (a box looks the same turned by a quarter)."""
    return float((angle_rad + np.pi / 4) % (np.pi / 2) - np.pi / 4)


class ObjectPerception:
    """The scene's objects from the first observation; their poses in any later one.

    first_frame: a ``datagen.capture.Frame`` (rgb, depth_m, normal_cam, segmentation, K, T_world_cam);
    seg_id_to_name: the segmentation camera's id -> name table (its scene objects are the objects).
    """

    def __init__(self, first_frame, seg_id_to_name: dict):
        from scipy.spatial import cKDTree  # scipy loads with the perception only

        self._tree = cKDTree
        f = first_frame
        masks, source = first_frame_masks(f.rgb, f.segmentation, seg_id_to_name)
        layer = track_objects(f.rgb[None], f.depth_m[None].astype(np.float32), f.normal_cam[None], f.K[None],
                              f.T_world_cam[None], masks, source)
        ids = {str(n): int(i) for i, n in seg_id_to_name.items()}
        self.up = scene_up_axis(f.T_world_cam)
        # the colours of what is not an object nor the robot (table, ground): a frame without segmentation
        # tells an object from them by which palette is nearer
        scenery = np.isin(f.segmentation, [i for i, n in seg_id_to_name.items() if str(n) in SCENERY_SEGMENTS])
        cols = np.asarray(f.rgb)[scenery].astype(np.float32)
        self.scenery_palette = cols[np.random.default_rng(0).choice(len(cols), min(len(cols), 2 * PALETTE_SIZE), replace=False)]
        self.models: list[_Model] = []
        self.last: dict[str, PerceivedObject] = {}
        for tr in layer.tracks:
            T0 = tr.T_world_object[0]
            pts_w, nrm_w = _world_points(f, f.segmentation == ids[tr.name])
            top_z = float(np.max(pts_w[:, 2]))
            top = pts_w[pts_w[:, 2] >= top_z - TOP_FACE_M]
            half = max((top_z - TABLE_Z_M) / 2, 0.005)
            centre = np.array([*top[:, :2].mean(0), top_z - half])
            cols = np.asarray(tr.colors, np.float32)
            palette = cols[np.random.default_rng(0).choice(len(cols), min(len(cols), PALETTE_SIZE), replace=False)]
            m = _Model(tr.name, ids[tr.name], tr.colour_name, np.asarray(tr.points_object, np.float64),
                       np.asarray(tr.normals_object, np.float64), centre - T0[:3, 3], face_yaw(nrm_w), half, palette,
                       T0[:3, 3].copy())
            self.models.append(m)
            self.last[m.name] = PerceivedObject(m.name, m.colour_name, centre, m.face_yaw0, half, T0.copy(),
                                                len(pts_w), 0.0)

    def names(self) -> list[str]:
        return [m.name for m in self.models]

    def perceive(self, frame) -> dict[str, PerceivedObject]:
        """Each object's pose in ``frame`` (a ``capture.Frame`` of the same camera)."""
        out = {}
        for m in self.models:
            obs, obs_n = _world_points(frame, frame.segmentation == m.seg_id)
            prev = self.last[m.name]
            if len(obs) < MIN_PIXELS:
                out[m.name] = PerceivedObject(m.name, m.colour_name, prev.centre_world_m, prev.face_yaw_rad,
                                              m.half_height_m, prev.T_world_object, 0, float("nan"))
                continue
            # The side faces seen now give the turn since the first frame (modulo a quarter); the ICP starts
            # from it and from the last pose.
            sides = int((np.abs(obs_n[:, 2]) < 0.5).sum())
            face_now = face_yaw(obs_n) if sides >= MIN_PIXELS else None
            turns = [yaw_about(prev.T_world_object[:3, :3], self.up)]
            if face_now is not None:
                turns.append(wrap_quarter(face_now - m.face_yaw0))
            T, rms = self._fit(m, obs, obs_n, turns)
            if face_now is None:
                face_now = wrap_quarter(m.face_yaw0 + yaw_about(T[:3, :3], self.up))
            out[m.name] = PerceivedObject(m.name, m.colour_name, transform_points(T, m.centre_object[None])[0].astype(np.float64),
                                          face_now, m.half_height_m, T, len(obs), rms)
        self.last = out
        return out

    def fit_by_colour(self, name: str, rgb: np.ndarray, depth_m: np.ndarray, normal_cam: np.ndarray, K: np.ndarray,
                      T_world_cam: np.ndarray) -> tuple[np.ndarray, float] | None:
        """The object's pose (T_world_object (4, 4), fit rms) in a frame without a segmentation (a predicted
        one): the largest connected patch of its own colours within ``COLOUR_SEARCH_M`` of where it started,
        fitted as in :meth:`perceive`; None when too few of its colours are seen."""
        import cv2  # OpenCV loads with this fit only

        m = next(mm for mm in self.models if mm.name == name)
        frame = _FrameView(np.asarray(rgb), np.asarray(depth_m, np.float32), np.asarray(normal_cam, np.float32), K, T_world_cam)
        valid = (frame.depth_m > 0) & np.isfinite(frame.depth_m)
        pts = transform_points(T_world_cam, unproject_depth(frame.depth_m, K))
        near = valid & (np.linalg.norm(pts - m.start_world_m, axis=-1) <= COLOUR_SEARCH_M)
        H, W = near.shape
        match = np.zeros((H, W), bool)
        colours = frame.rgb[near].astype(np.float32)
        d_own = min_colour_distance(colours, m.palette)
        own = d_own < OBJECT_COLOUR_TOL
        own[own] = d_own[own] < min_colour_distance(colours[own], self.scenery_palette)  # only where it may match
        match[near] = own
        n, labels, stats, _ = cv2.connectedComponentsWithStats(match.astype(np.uint8), connectivity=8)
        if n < 2:
            return None
        biggest = 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))
        mask = labels == biggest
        if mask.sum() < MIN_PIXELS:
            return None
        obs, obs_n = _world_points(frame, mask)
        sides = int((np.abs(obs_n[:, 2]) < 0.5).sum())
        turns = [0.0] + ([wrap_quarter(face_yaw(obs_n) - m.face_yaw0)] if sides >= MIN_PIXELS else [])
        return self._fit(m, obs, obs_n, turns)

    def _fit(self, m: _Model, obs: np.ndarray, obs_n: np.ndarray, turns: list[float]) -> tuple[np.ndarray, float]:
        tree = self._tree(m.points)
        best = (None, np.inf)
        for turn in turns:
            T = np.eye(4)
            T[:3, :3] = rotation_about(self.up, turn)
            # start with the model's centroid on the observed points' centroid
            T[:3, 3] = obs.mean(0) - T[:3, :3] @ m.points.mean(0)
            rms = np.inf
            for _ in range(ICP_ITERATIONS):
                # observed -> nearest model point (the observation may show only part of the object)
                local = (obs - T[:3, 3]) @ T[:3, :3]
                dist, idx = tree.query(local)
                keep = dist <= np.quantile(dist, TRIM_SHARE)
                src = transform_points(T, m.points[idx[keep]]).astype(np.float64)
                # point-to-plane pairs, and the same pairs point to point: a patch seen from one side only
                # (a top face) leaves point-to-plane steps free along it, and they diverged
                dst, nrm = obs[keep], obs_n[keep]
                step = plane_step(np.concatenate([src, src]), np.concatenate([dst, dst]),
                                  np.concatenate([nrm, np.zeros_like(nrm)]), self.up)
                T = step @ T
                rms = float(np.sqrt(np.mean(dist[keep] ** 2)))
                if np.linalg.norm(step[:3, 3]) < 1e-5:
                    break
            if rms < best[1]:
                best = (T, rms)
        return best
