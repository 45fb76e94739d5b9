"""The hand's track through a clip, and what the hand does to an object it reaches.

**The track.** A predicted clip at 128² often loses the small object the arm moves (it smears and vanishes
under the arriving gripper) while the arm itself stays sharp: the arm is the large, grey-white, moving thing
of the scene. Robot4DGen executes the gripper it tracks in generated RGB-D; here the track tells the object
layer (:mod:`reconstruction.objects`) and the closed loop's goal reading (:mod:`tesseract4d.policy.goal_reading`)
where a lost object went.

The arm in a frame is what the object layer leaves over (:class:`reconstruction.objects.ObjectLayer`'s
``point_object``, -1 = no object) among the pixels that may be the arm (:func:`arm_pixels`: moving, so the
camera must stay still, and grey, white or black, where a blurred object's colours are not), and lies more
than ``ABOVE_TABLE_M`` above the table top (``TABLE_Z_M``; a predicted clip redraws a white target disc on
the table a little nearer now and then). Isolated points (fewer than ``MIN_NEIGHBOURS`` within
``NEIGHBOUR_M``) are noise. The gripper's point is the hand: the arm's points within ``HAND_BAND_M`` above
its lowest (``LOW_QUANTILE``) height along the scene's up axis; in the table plane their median, along up
their ``HEIGHT_QUANTILE``. Its offset from the TCP differs with the view (the fingers hide behind the hand or
the object they push), so only its displacements are used.

Chosen against the simulator's TCP (forward kinematics of the stored joint positions, for the check only)
on the true frames of the 48 held-out episodes (128², ``close`` camera), displacements from the fifth
frame on: in the table plane median 3 mm, 90th percentile 13 mm; along up median 4 mm, 90th percentile
14 mm. The fingers alone (the lowest 1.5 cm of the arm) were worse in the plane: median 11 mm, 90th
percentile 51 mm (they hide behind the hand or the pushed object in many frames).

**What the hand does to an object** (:func:`hand_move`). The object the hand reaches (the instructed one
when known, else the one it reaches first, then the one it comes lowest to) is the moved object, from the
first frame the hand is within ``REACH_XY_M`` of where the object starts in the table plane and at most
``REACH_DZ_M`` above it (both wide, for the hand's point is about 4 cm beside and 6 cm above the TCP). From
the end of its descent there (it stops coming down by ``DESCENT_M`` a frame) the hand either slides along
the table (it travels ``MOVED_M`` in the plane rising less than ``SLIDE_SLOPE`` of that: a push or pull, let
go where it rises ``LIFT_M`` or at the end) or first rises ``LIFT_M`` (in ``LIFT_FRAMES`` frames in a row: a
grasp, carried until the hand comes down ``LIFT_M`` below its highest point so far, at the end of that
descent, or held at the end), and the object follows the hand's displacement over that stretch; carried,
it is set on the object whose start lies within ``ARM_ON_XY_M`` of its end in the table plane and at least
``ON_DZ_M[0]`` lower. A layer's track misses that move (:func:`misses`) when it does not show the object
where the hand left it: not seen at the end, or moved the hand's way but less than ``LAG_SHARE`` of it. An
object the layer still sees where it was, the hand gone, stays put: the hand left it alone.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from tesseract4d.geometry import scene_up_axis, transform_points, unproject_depth

TABLE_Z_M = 0.0  # ManiSkill's table top (world z)
# A pixel is moving where it is this much nearer than the clip's farthest depth there.
MOVING_DEPTH_M = 0.01
# The arm's pixels are unsaturated (grey, white, black): HSV saturation at most this.
ARM_MAX_SATURATION = 0.3
ABOVE_TABLE_M = 0.015  # arm points lie at least this high above the table top (lower: the table's own markings)
MIN_ARM_POINTS = 12  # fewer arm points in a frame: the arm is not seen there (NaN)
NEIGHBOUR_M = 0.015  # an arm point needs MIN_NEIGHBOURS others this close ...
MIN_NEIGHBOURS = 4  # ... or it is depth noise
LOW_QUANTILE = 0.02  # the arm's lowest height, robust to a stray point
HAND_BAND_M = 0.16  # the hand: the arm's points this close above its lowest height ...
HEIGHT_QUANTILE = 0.1  # ... its height: this quantile of theirs (the median in the table plane)

MOVED_M = 0.02  # an object moving less than this over the clip counts as still
LIFT_M = 0.03  # raised at least this far above its start ...
LIFT_FRAMES = 2  # ... in this many frames in a row: lifted
ON_DZ_M = (0.015, 0.08)  # stacked: its origin this much higher than the other's
REACH_XY_M = 0.10  # the hand reaches an object: the hand's point this close in the table plane ...
REACH_DZ_M = 0.10  # ... and at most this high above the object's origin
DESCENT_M = 0.005  # the hand still comes down when it is this much lower (less: the clip's depth noise)
SLIDE_SLOPE = 0.5  # a slide: when the hand has travelled MOVED_M in the plane it has risen less than this share of it
LAG_SHARE = 0.8  # a track misses the hand's move when it moved less than this share of it
ARM_ON_XY_M = 0.05  # the hand's move: set on the object whose centre is this close in the table plane


@dataclass
class GripperTrack:
    """The gripper's point per frame (world metres) and how many arm points each frame had."""

    gripper_world_m: np.ndarray  # (T, 3); NaN where the arm is not seen
    arm_points: np.ndarray  # (T,) int
    up: np.ndarray  # (3,) the scene's up axis

    def seen(self) -> np.ndarray:
        """(T,) bool: frames where the gripper is seen."""
        return np.isfinite(self.gripper_world_m).all(axis=1)


def static_depth(depth_m: np.ndarray, valid: np.ndarray, T_world_cam: np.ndarray) -> np.ndarray | None:
    """(H, W) the farthest depth seen at each pixel over the clip (the background moving things pass in
    front of), or None when the camera moves."""
    if len(depth_m) < 2 or not np.allclose(T_world_cam, T_world_cam[:1], atol=1e-6):
        return None
    return np.where(valid, depth_m, 0.0).max(axis=0)


def arm_pixels(rgb: np.ndarray, depth_m: np.ndarray, valid: np.ndarray, static_depth_m: np.ndarray) -> np.ndarray:
    """(H, W) bool: the pixels of one frame that may be the arm: nearer than the clip's farthest depth there
    (:func:`static_depth`: moving things) and grey, white or black (the blurred outline of a coloured
    object or the table is not)."""
    c = np.asarray(rgb, np.float32)
    hi, lo = c.max(-1), c.min(-1)
    grey = (hi - lo) <= ARM_MAX_SATURATION * np.maximum(hi, 1.0)
    return valid & (depth_m < static_depth_m - MOVING_DEPTH_M) & grey


def gripper_point(points_world: np.ndarray, up: np.ndarray) -> np.ndarray | None:
    """(3,) the gripper's point of an arm given as points (N, 3) (world metres; see the module docstring),
    or None when too few are left after dropping isolated ones."""
    from scipy.spatial import cKDTree  # scipy loads with the tracker only

    p = np.asarray(points_world, np.float64)
    p = p[p @ up >= TABLE_Z_M + ABOVE_TABLE_M]
    if len(p) < MIN_ARM_POINTS:
        return None
    # MIN_NEIGHBOURS others within NEIGHBOUR_M: the (MIN_NEIGHBOURS + 1)-th nearest point (itself the first) is
    # that close (a k-nearest query; counting every point in the ball cost ten times as much)
    dist, _ = cKDTree(p).query(p, k=MIN_NEIGHBOURS + 1, distance_upper_bound=NEIGHBOUR_M)
    p = p[np.isfinite(dist[:, -1])]
    if len(p) < MIN_ARM_POINTS:
        return None
    h = p @ up
    hand = p[h <= float(np.quantile(h, LOW_QUANTILE)) + HAND_BAND_M]
    h_hand = hand @ up
    flat = hand - np.outer(h_hand, up)  # (N, 3) in the table plane
    return np.median(flat, axis=0) + float(np.quantile(h_hand, HEIGHT_QUANTILE)) * up


def track_gripper(rgb: np.ndarray, depth_m: np.ndarray, K: np.ndarray, T_world_cam: np.ndarray, layer) -> GripperTrack | None:
    """The gripper's track through a clip. rgb (T, H, W, 3) uint8, depth_m (T, H, W) metres, K (T, 3, 3),
    T_world_cam (T, 4, 4); ``layer``: the clip's object layer with ``point_object`` labels (every valid
    pixel, pixel order). None when the camera moves (what moves cannot be told from the background) or
    the layer has no labels."""
    depth = np.asarray(depth_m, np.float32)
    T_world_cam = np.asarray(T_world_cam, np.float64)
    valid = np.isfinite(depth) & (depth > 0)
    static = static_depth(depth, valid, T_world_cam)  # (H, W); None when the camera moves
    if static is None or len(layer.point_object) != len(depth):
        return None
    up = scene_up_axis(T_world_cam[0])
    points = np.full((len(depth), 3), np.nan)
    counts = np.zeros(len(depth), int)
    for t in range(len(depth)):
        label = np.full(depth.shape[1:], -1, np.int32)
        label[valid[t]] = layer.point_object[t]
        arm = arm_pixels(rgb[t], depth[t], valid[t], static) & (label < 0)  # moving, grey, of no object
        counts[t] = int(arm.sum())
        pts = transform_points(T_world_cam[t], unproject_depth(depth[t], K[t])[arm])
        point = gripper_point(pts, up)
        if point is not None:
            points[t] = point
    return GripperTrack(points, counts, up)


# ---------------------------------------------------------------------- what the hand does to an object


@dataclass
class HandMove:
    """How the hand moves one object (world metres; see the module docstring)."""

    target: str  # the object's name in the object layer
    kind: str  # "slide" (pushed or pulled along the table) | "grasp" (lifted and carried)
    contact_frame: int  # the last frame of the hand's descent at it: the object moves from here on
    release_frame: int  # the frame the hand lets go (the clip's last when it holds on)
    displacement_m: np.ndarray  # (3,) the hand's displacement over the stretch (in the table plane for a slide)
    path_m: np.ndarray  # (T, 3) the object's displacement from its place at contact_frame: zero before, the
    #   hand's displacement since then over the stretch (in the table plane for a slide), displacement_m after
    on: str | None = None  # carried: the object it is set on


def filled(points: np.ndarray) -> np.ndarray:
    """(T, 3) ``points`` with each unseen (NaN) frame given the last seen one (the first seen before it)."""
    out = np.asarray(points, np.float64).copy()
    seen = np.isfinite(out).all(axis=1)
    idx = np.where(seen, np.arange(len(out)), -1)
    idx = np.maximum.accumulate(idx)
    idx[idx < 0] = np.flatnonzero(seen)[0]
    return out[idx]


def contact_frame(p0: np.ndarray, g: np.ndarray, seen: np.ndarray, up: np.ndarray) -> int | None:
    """The first frame the hand (T, 3) is within reach of an object at p0 (3,), or None when never."""
    gap = g - p0
    dz = gap @ up
    flat = np.linalg.norm(gap - np.outer(dz, up), axis=1)
    near = np.flatnonzero(seen & (flat <= REACH_XY_M) & (dz <= REACH_DZ_M))
    return int(near[0]) if len(near) else None


def hand_motion(g: np.ndarray, c: int, up: np.ndarray) -> tuple[str, int, int] | None:
    """What the hand (T, 3) does from its contact frame c: ("slide" | "grasp", k, r): from its lowest point k
    (the last frame of its descent) it slides along the table or first rises, and lets go at r; None when
    it does neither."""
    h = g @ up
    k = c
    for t in range(c + 1, len(g)):
        step = g[t] - g[k]
        rise = float(step @ up)
        travel = float(np.linalg.norm(step - rise * up))
        if rise <= -DESCENT_M and (travel < MOVED_M or -rise >= SLIDE_SLOPE * travel):
            k = t  # still coming down (in place or steeply)
            continue
        if rise >= LIFT_M and rise >= SLIDE_SLOPE * travel and _stays_up(h, t, h[k]):
            # let go: the hand comes down LIFT_M below its highest point so far, at the end of that descent
            down = np.flatnonzero(h[t:] <= np.maximum.accumulate(h[t:]) - LIFT_M)
            if not len(down):
                return "grasp", k, len(g) - 1
            r = t + int(down[0])
            while r + 1 < len(g) and h[r + 1] < h[r]:
                r += 1
            return "grasp", k, r
        if travel >= MOVED_M and abs(rise) < SLIDE_SLOPE * travel:
            up_at = [u for u in range(t, len(g)) if _stays_up(h, u, h[k])]
            return "slide", k, (up_at[0] - 1) if up_at else len(g) - 1
    return None


def _stays_up(h: np.ndarray, t: int, base: float) -> bool:
    """Whether the hand's heights ``h`` (T,) are ``LIFT_M`` above ``base`` in ``LIFT_FRAMES`` frames in a row from
    t (fewer at the clip's end): one frame's rise is the clip's depth noise."""
    return bool(np.all(h[t:t + LIFT_FRAMES] - base >= LIFT_M))


def hand_move(layer, gripper: GripperTrack) -> HandMove | None:
    """How the hand moves the object it reaches in ``layer`` (an object layer: its tracks' first positions
    and its ``instructed`` name; see the module docstring), or None when it reaches none or does not move it
    at least ``MOVED_M``."""
    seen = gripper.seen()
    if seen.sum() < 2 or not len(layer):
        return None
    up = np.asarray(gripper.up, np.float64)
    g = filled(gripper.gripper_world_m)
    contacts = {tr.name: contact_frame(tr.positions_world()[0], g, seen, up) for tr in layer.tracks}
    name = layer.instructed if layer.instructed in contacts else None
    if name is None:  # the object the hand reaches first (then the one it comes lowest to)
        reached = [n for n, c in contacts.items() if c is not None]
        if not reached:
            return None
        name = min(reached, key=lambda n: (contacts[n], float((g[contacts[n]] - layer.track(n).positions_world()[0]) @ up)))
    c = contacts[name]
    if c is None:
        return None
    motion = hand_motion(g, c, up)
    if motion is None:
        return None
    kind, k, r = motion
    path = g - g[k]  # (T, 3)
    path[:k] = 0.0
    path[r + 1:] = path[r]
    if kind == "slide":
        path = path - np.outer(path @ up, up)
    disp = path[-1]
    if np.linalg.norm(disp) < MOVED_M:
        return None
    on = None
    if kind == "grasp":
        end = layer.track(name).positions_world()[0] + disp
        best = ARM_ON_XY_M
        for other in layer.tracks:
            if other.name == name:
                continue
            q = other.positions_world()[0]  # the hand moves one object; the others stay where they are
            gap = end - q
            dz = float(gap @ up)
            flat = float(np.linalg.norm(gap - dz * up))
            if flat <= best and dz >= ON_DZ_M[0]:
                on, best = other.name, flat
    return HandMove(name, kind, k, r, disp, path, on)


def misses(positions_world: np.ndarray, seen_at_end: bool, displacement_m: np.ndarray, share: float = LAG_SHARE) -> bool:
    """Whether an object's track (positions (T, 3), world metres; ``seen_at_end``: fitted to the last frame)
    misses a move of the hand's (its displacement (3,), world metres): not seen at the end, or moved the
    hand's way at least ``MOVED_M`` but less than ``share`` of the hand's displacement. A track that still sees the object where it was, the hand
    gone, does not miss it: the hand left it alone."""
    if not seen_at_end:
        return True
    p = np.asarray(positions_world, np.float64)
    own = p[-1] - p[0]
    disp = np.asarray(displacement_m, np.float64)
    norm = float(np.linalg.norm(disp))
    along = float(own @ disp) / max(norm, 1e-9)
    return MOVED_M <= along < share * norm
