"""The object layer of a 4D reconstruction: the scene's objects as rigid point sets with a pose per
frame, tracked through an RGB-D video (a prediction or a recorded episode).

What it holds (:class:`ObjectLayer`): per object (:class:`ObjectTrack`) a name, a display colour and
its colour name, its points in its own frame (``points_object``, metres), ``T_world_object`` per
frame (4x4, object -> world), a visibility (the share of its expected visible surface seen), a
confidence in [0, 1] and a state per frame (``STATES``). The object frame has its origin at the
centroid of the object's first-frame points and the world's axes at frame 0, so
``T_world_object[0]`` is a pure translation.

How it is made (:func:`track_objects`):

1. objects from the first frame: each object's pixels (a segmentation's scene objects, or the colour
   object finder's masks, :mod:`tesseract4d.object_finder`) are back-projected into a rigid point set,
   with their normals and a palette of the object's own colours (those unlike the table around it);
2. per later frame and object, a robust rigid fit near its last pose: the pixels of its colours within
   ``search_m`` of where it should be (moved on at its last velocity; a wider sphere when nothing is
   found there, wider still once it is lost) are back-projected, and a trimmed ICP with nearest-point
   pairs both ways (observed -> model, and model points that face the camera with nothing in front ->
   observed; point-to-plane steps) solves translation and yaw about the scene's up axis
   (``rotation="yaw"``) or a full rotation (``rotation="full"``), from up to three starts (the guess,
   the last pose, the guess moved onto the observed centroid); the fit that explains the frame best
   both ways wins, a turn of more than ``MAX_TURN_DEG`` per frame is refitted without rotation, and the
   last pose of a still object is kept unless the fit explains the frame at least ``STAY_FACTOR`` times
   better (a blurred still object does not creep; a moving one needs only ``STAY_FACTOR_MOVING``); a fit that leaves its points farther than ``MAX_FIT_RMS_M`` apart counts
   as not found; an object seen again after frames unseen is placed farther than ``REFIND_M`` from where
   it was only when something was at it meanwhile (the arm's unsaturated points or a moving object within
   ``CAUSE_REACH_M`` of it, or what covered it that close in front of it): a prediction that drops an
   object and redraws a look-alike elsewhere does not move it;
3. an object not found (too little of its expected visible surface seen) keeps its pose when
   something stands in front of where it was (``occluded``); it moves with the arm when the evidence
   says it is held (it was moving or lifted when last seen, or already held, and the arm's points touch
   it: their translation, fitted point-to-plane, carries it: ``held``); when nothing covers where it
   should be the video lost it: ``lost``, its pose kept and its confidence 0. No object is ever dropped;
4. "it went with the arm while hidden": while an object is unseen, the arm's points near where it would
   be are followed from frame to frame (a trimmed translation fit that must land on the next frame's arm
   within ``ARM_FIT_M``), moving it only while the arm reaches down to it and trails it (pushes it from
   behind), never below its starting height. Once its old place is seen empty (nothing in front, none of
   its colours) after the arm covered it, and that motion took it at least ``HIDDEN_MOVE_M`` away to a
   place the arm hides, the frames since it was hidden are filled with that motion, state ``inferred``,
   confidence ``INFERRED_CONFIDENCE``; the few pixels of it seen under the hand, if any, pin it (a
   translation fit). A PullCube cube pulled behind the hand, 15-18 cm, ends 1-2 mm from the truth;
5. "it went with the hand": the hand's track through the clip (:mod:`reconstruction.hand_track`: the arm is
   what no object claims) says which object the hand reaches and whether it slides it along the table or
   carries it and sets it down (the closed loop's goal reading decides the same way); where the layer's
   track misses that move (not placed at the end, or moved the hand's way less than ``HAND_LAG_SHARE`` of it:
   the object smeared or vanished under the hand), the object follows the hand's displacement from the
   end of the hand's descent at it, state ``inferred``, confidence ``INFERRED_CONFIDENCE``;
6. rigid bodies move only when touched: an object that neither the hand nor the object it moves ever
   comes within reach of keeps its first pose (a prediction that redraws it elsewhere is a redraw, not a
   move). Steps 5 and 6: :func:`follow_hand`.

Chosen by measurement against the simulator's stored poses (``tesseract4d/evaluation/object_tracks.py``):
on the recorded frames of the held-out sets at 128² (``heldout_cubes``: PickCube, PushCube, PullCube,
StackCube, 20 objects; ``heldout_tabletop``: 84 objects) 102 of 104 objects end within 5 mm of the truth
(the misses: PickCube's cube lifted under the hand, 18 mm, and a push's last 5 mm step); "yaw" fits as
well as "full" (mean largest error along the track 7.4 vs 7.6 mm on an earlier set). A first version
(point-to-point pairs one way, one search sphere) ended 7 of the first 24 objects 7-12 cm off (objects moving faster than the sphere, fits sliding
along a face). Objects are tracked in the input depth (see ``reconstruct.py``). The rules that keep still objects
still were chosen on the default model's predictions of the held-out sets (docs/research/object_layer.md),
where flow + RANSAC fits (AVDC's) and a box's hidden faces mirrored from its seen ones were measured too.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field, replace

import numpy as np

from reconstruction.hand_track import (LIFT_M, MOVING_DEPTH_M, GripperTrack, HandMove, arm_pixels, contact_frame,
                                       hand_move, misses, static_depth, track_gripper)
from tesseract4d.errors import UserError
from tesseract4d.geometry import invert_pose, scene_up_axis, transform_points, unproject_depth
from tesseract4d.object_colours import MIN_OBJECT_PIXELS, OBJECT_COLOUR_TOL, distinctive, min_colour_distance
from tesseract4d.object_finder import find_objects
from tesseract4d.segments import scene_object_ids

# Per-frame states of an object (stored as their index, int8).
STATES = ("tracked", "occluded", "held", "lost", "inferred")
TRACKED, OCCLUDED, HELD, LOST, INFERRED = range(len(STATES))
STATE_MEANING = {
    "tracked": "fitted to the frame's depth and colour",
    "occluded": "not seen: something stands in front of where it was; the pose is kept",
    "held": "not seen, moving with the arm that holds it",
    "lost": "not seen and nothing covers where it should be: the video lost it; the pose is kept",
    "inferred": "not seen where it is: hidden by the arm with its old place seen empty, or lost, smeared or left "
                "behind where the hand reached it and slid or carried it on; placed where the arm's or the hand's "
                "motion since then took it (inferred, low confidence)",
}
TRAJECTORIES_FORMAT = "tesseract4d-trajectories"
TRAJECTORIES_VERSION = 1

# The share of the object's expected visible surface (in pixels) that must be seen to fit it.
MIN_VISIBLE_SHARE = 0.2
# ICP: iterations, the share of nearest-point pairs kept (the closest), the largest pair distance kept.
ICP_ITERATIONS = 15
# ICP stops when a step moves less than this (metres) and turns less than this (radians, per matrix entry).
CONVERGED_M = 1e-4
CONVERGED_RAD = 1e-4
# A fit whose two-way score (root mean square, metres) is this good ends the search among starts.
GOOD_SCORE_M = 0.0015
# The last pose is kept when its two-way score (mean square) is at most this factor of the best fit's plus this floor squared.
STAY_FACTOR = 2.0
STAY_FLOOR_M = 0.001
# ... and for an object already moving (it moved in its last fitted frame), the last pose is kept only when
# it explains the frame nearly as well (this factor; floor STAY_FLOOR_MOVING_M): a moving object keeps moving.
STAY_FACTOR_MOVING = 1.25
STAY_FLOOR_MOVING_M = 0.0005
TRIM_SHARE = 0.8
MAX_PAIR_M = 0.02
# A fit whose kept pairs are farther apart than this (root mean square) did not find the object.
MAX_FIT_RMS_M = 0.01
# The largest turn of an object between two frames a fit may make (beyond it: a flip onto a look-alike face).
MAX_TURN_DEG = 25.0
# Where to look for an object in the next frame: this far beyond its own radius from its predicted place.
SEARCH_M = 0.05
# ... and this many times as far when it is not found there.
WIDE_SEARCH = 3.0
# ... and this many times as far once it is lost.
LOST_SEARCH = 5.0
# Depth difference beyond which a surface is in front of / behind another (metres): the hand track's
# "moving" tolerance, one number.
DEPTH_TOL_M = MOVING_DEPTH_M
# An unseen object counts as covered when at least this share of its expected surface has something in front.
COVERED_SHARE = 0.5
# Evidence of being held: moving at least this much per frame when last seen, or lifted this far above its start.
HELD_SPEED_M = 0.003
HELD_LIFT_M = 0.01
# The arm's points that carry a held object: within this distance of the object's surface.
ARM_RADIUS_M = 0.04
# The arm touches an object when at least this many of its points lie this close to the object's surface.
CONTACT_M = 0.01
# The arm's points moved by a shift must lie this close to its surface in the next frame (median), or the shift is not trusted.
ARM_FIT_M = 0.003
# ... nor when the arm's points around the object grew by more than this factor from one frame to the next.
ARM_GROWTH = 1.5
MIN_CONTACT_POINTS = 3
MIN_ARM_POINTS = 8
# Rigid objects move only when something touches them. While an object is not seen, something is at it
# when at least MIN_CAUSE_POINTS points of the arm (moving, unsaturated points of none of the objects'
# colours) or of another moving object lie within CAUSE_REACH_M of its surface in this frame or the last,
# or as many of the points covering it lie within CAUSE_REACH_M in front of it.
CAUSE_REACH_M = 0.05
# An object seen again after frames unseen is found farther than this from where it was only when
# something was at it meanwhile.
REFIND_M = 0.02
# "It went with the arm while hidden": an object hidden behind the arm whose old place is later seen empty
# moved with the arm. Its inferred pose follows the translation of the arm's points within HIDDEN_ARM_M of
# it (the visible side of a hand over a 4 cm cube lies 5-14 cm from the cube's centre at 128²), never
# sinking below its starting height, and is used once it has gone at least HIDDEN_MOVE_M from where it
# was last seen; the frames since it was hidden are filled with it, state "inferred", this confidence.
HIDDEN_ARM_M = 0.15
HIDDEN_MOVE_M = 0.02
# ... counted only while an arm point within HIDDEN_REACH_M of it across the up axis is lower than its top
# plus HIDDEN_LOW_M (the hand reaches down to it; the arm passing above it leaves it).
HIDDEN_REACH_M = 0.06
HIDDEN_LOW_M = 0.005
INFERRED_CONFIDENCE = 0.3
# The object the hand moves follows the hand when the layer's own track went less than this share of the hand's way:
# below the goal reading's LAG_SHARE, for the hand's point travels a little before it meets the object (a true
# tabletop push, tracked all the way: 92 of the hand's 118 mm).
HAND_LAG_SHARE = 0.7
MIN_CAUSE_POINTS = 5
# Confidence of a fit: visibility times exp(-rms / CONFIDENCE_RMS_M); an occluded/held object's decays by this per frame.
CONFIDENCE_RMS_M = 0.004
UNSEEN_DECAY = 0.8
# The palette of an object's own colours: at most this many of its pixels' colours.
PALETTE_SIZE = 48
# Named colours for naming objects found by colour (hue in degrees, HSV's); grey-ish objects are "grey".
COLOUR_HUES = {"red": 0, "orange": 30, "yellow": 55, "green": 120, "cyan": 185, "blue": 225, "purple": 280}
MIN_NAMED_SATURATION = 0.25


@dataclass
class ObjectTrack:
    """One object through the clip. T frames; N points."""

    name: str
    color: np.ndarray  # (3,) uint8, the display colour (median of its own colours)
    colour_name: str  # "red", "green", ... (nearest named hue) or "grey"
    points_object: np.ndarray  # (N, 3) float32, metres, object frame
    colors: np.ndarray  # (N, 3) uint8
    normals_object: np.ndarray  # (N, 3) float32, object frame (zero where unknown)
    T_world_object: np.ndarray  # (T, 4, 4) float64, object -> world
    visibility: np.ndarray  # (T,) float32 in [0, 1]: share of the expected visible surface seen
    confidence: np.ndarray  # (T,) float32 in [0, 1]
    state: np.ndarray  # (T,) int8, index into STATES

    @property
    def num_frames(self) -> int:
        return len(self.T_world_object)

    def positions_world(self) -> np.ndarray:
        """(T, 3) the object frame's origin (its first-frame centroid, carried along) in the world, metres."""
        return np.asarray(self.T_world_object[:, :3, 3], np.float64)

    def states(self) -> list[str]:
        return [STATES[int(s)] for s in self.state]

    def points_world(self, t: int) -> np.ndarray:
        """(N, 3) the object's points placed at frame t, world metres."""
        return transform_points(self.T_world_object[t], self.points_object).astype(np.float32)


@dataclass
class ObjectLayer:
    """The objects of a reconstruction, and which of its per-frame points belong to them."""

    tracks: list[ObjectTrack]
    source: str  # how the objects were found: "segmentation", "colour finder" or "simulator poses"
    instructed: str | None = None  # name of the object the instruction is about, when known
    # T x (N_t,) int16 per reconstruction point: the index of the object it belongs to, -1 for none (the
    # arm where dynamic, else the table and the rest of the scene). Empty where the points are not labelled.
    point_object: list[np.ndarray] = field(default_factory=list)
    # The hand's track through the clip that the tracker's hand steps read (:func:`follow_hand`), for a reader
    # of the same clip (the closed loop's goal reading); None when they did not run. Not saved with the layer.
    hand: GripperTrack | None = field(default=None, repr=False, compare=False)

    def __len__(self) -> int:
        return len(self.tracks)

    def names(self) -> list[str]:
        return [t.name for t in self.tracks]

    def track(self, name: str) -> ObjectTrack:
        for t in self.tracks:
            if t.name == name:
                return t
        raise KeyError(f"no object {name!r} in the object layer; it has {self.names()}")

    def instructed_track(self) -> ObjectTrack | None:
        """The track of the object the instruction is about, or None when it is not known."""
        return None if self.instructed is None or self.instructed not in self.names() else self.track(self.instructed)

    def trajectories(self, fps: float, instruction: str | None = None) -> dict:
        """The layer as plain JSON data (what ``trajectories.json`` holds): readable without the project."""
        return {
            "format": TRAJECTORIES_FORMAT, "format_version": TRAJECTORIES_VERSION,
            "frame": "world, metres; position = the object frame's origin (the centroid of the object's first-frame "
                     "points) in the world; quaternion_wxyz = the object's rotation (object -> world), identity at "
                     "frame 0; T_world_object = the 4x4 row-major matrix of both",
            "fps": float(fps), "num_frames": self.tracks[0].num_frames if self.tracks else 0,
            "instruction": instruction, "instructed_object": self.instructed, "objects_from": self.source,
            "states": STATE_MEANING,
            "objects": [{
                "name": t.name, "colour": t.colour_name, "color_rgb": [int(c) for c in t.color],
                "num_points": int(len(t.points_object)),
                "position_m": np.round(t.positions_world(), 5).tolist(),
                "quaternion_wxyz": np.round([quaternion_wxyz(T[:3, :3]) for T in t.T_world_object], 6).tolist(),
                "T_world_object": np.round(t.T_world_object, 6).tolist(),
                "visibility": np.round(t.visibility.astype(np.float64), 4).tolist(),
                "confidence": np.round(t.confidence.astype(np.float64), 4).tolist(),
                "state": t.states(),
            } for t in self.tracks],
        }

    def trajectories_json(self, fps: float, instruction: str | None = None) -> str:
        return json.dumps(self.trajectories(fps, instruction), indent=1)


# ---------------------------------------------------------------------- rotations


def quaternion_wxyz(R: np.ndarray) -> np.ndarray:
    """(4,) unit quaternion (w, x, y, z), w >= 0, of the rotation matrix R (3, 3)."""
    R = np.asarray(R, np.float64)
    w = np.sqrt(max(0.0, 1.0 + R[0, 0] + R[1, 1] + R[2, 2])) / 2
    x = np.sqrt(max(0.0, 1.0 + R[0, 0] - R[1, 1] - R[2, 2])) / 2
    y = np.sqrt(max(0.0, 1.0 - R[0, 0] + R[1, 1] - R[2, 2])) / 2
    z = np.sqrt(max(0.0, 1.0 - R[0, 0] - R[1, 1] + R[2, 2])) / 2
    x = np.copysign(x, R[2, 1] - R[1, 2])
    y = np.copysign(y, R[0, 2] - R[2, 0])
    z = np.copysign(z, R[1, 0] - R[0, 1])
    q = np.array([w, x, y, z])
    return q / np.linalg.norm(q)


def matrix_from_wxyz(q: np.ndarray) -> np.ndarray:
    """(3, 3) rotation of the quaternion (w, x, y, z) (any norm > 0)."""
    w, x, y, z = np.asarray(q, np.float64) / np.linalg.norm(q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


def rotation_about(axis: np.ndarray, angle_rad: float) -> np.ndarray:
    """(3, 3) rotation by ``angle_rad`` about the unit vector ``axis`` (Rodrigues)."""
    k = np.asarray(axis, np.float64)
    K = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + np.sin(angle_rad) * K + (1 - np.cos(angle_rad)) * K @ K


def yaw_about(R: np.ndarray, up: np.ndarray) -> float:
    """The rotation angle (radians, in (-pi, pi]) of R (3, 3) about the unit axis ``up``: the turn of a
    horizontal vector, measured in the plane across ``up``."""
    up = np.asarray(up, np.float64)
    a = np.eye(3)[int(np.argmin(np.abs(up)))]
    a = a - a.dot(up) * up
    a /= np.linalg.norm(a)
    b = np.asarray(R, np.float64) @ a
    b = b - b.dot(up) * up
    if np.linalg.norm(b) < 1e-9:
        return 0.0
    return float(np.arctan2(np.dot(up, np.cross(a, b)), np.dot(a, b)))


def plane_step(src: np.ndarray, dst: np.ndarray, normals: np.ndarray, up: np.ndarray | None) -> np.ndarray:
    """(4, 4) one Gauss-Newton step of point-to-plane alignment: the small rigid motion that moves the
    points ``src`` (N, 3) toward the planes through ``dst`` (N, 3) with unit ``normals`` (N, 3), rotating
    about ``up`` only (a yaw) when given, any axis when None; pairs whose normal is zero count point to
    point; a zero ``up`` allows no rotation (translation only). Flat faces converge in a few steps where
    point-to-point pairs slide along them."""
    c = src.mean(0)
    arm = src - c
    has_n = np.linalg.norm(normals, axis=1) > 0.5
    rows, rhs = [], []
    # Point-to-plane rows: r = (p - q) . n; d r / d t = n; d r / d w = (p - c) x n.
    rot = np.cross(arm[has_n], normals[has_n])
    rows.append(np.concatenate([rot @ up[:, None] if up is not None else rot, normals[has_n]], 1))
    rhs.append(-np.einsum("ij,ij->i", src[has_n] - dst[has_n], normals[has_n]))
    for axis in np.eye(3):  # point-to-point rows for pairs without a normal
        a = arm[~has_n]
        # d (p . e) / d w = (w x (p - c)) . e = w . ((p - c) x e)
        rot = np.cross(a, np.broadcast_to(axis, a.shape)) if len(a) else np.zeros((0, 3))
        rows.append(np.concatenate([rot @ up[:, None] if up is not None else rot, np.broadcast_to(axis, (len(a), 3))], 1))
        rhs.append(-(src[~has_n] - dst[~has_n]) @ axis)
    A, b = np.concatenate(rows), np.concatenate(rhs)
    n_rot = 1 if up is not None else 3
    damping = 1e-9 * np.eye(A.shape[1])
    x = np.linalg.solve(A.T @ A + damping, A.T @ b)
    if up is not None:
        R = rotation_about(up, float(x[0]))
    else:
        angle = float(np.linalg.norm(x[:3]))
        R = rotation_about(x[:3] / angle, angle) if angle > 1e-12 else np.eye(3)
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = c - R @ c + x[n_rot:]
    return T


# ---------------------------------------------------------------------- objects from the first frame


def colour_name(rgb: np.ndarray) -> str:
    """The nearest named hue of an RGB colour (3,) 0-255, or "grey" for an unsaturated one."""
    import colorsys

    h, s, v = colorsys.rgb_to_hsv(*(np.asarray(rgb, np.float64) / 255.0))
    if s < MIN_NAMED_SATURATION or v < 0.15:
        return "grey"
    hue = 360.0 * h
    return min(COLOUR_HUES, key=lambda n: min(abs(hue - COLOUR_HUES[n]), 360 - abs(hue - COLOUR_HUES[n])))


def first_frame_masks(rgb0: np.ndarray, segmentation0: np.ndarray | None, seg_id_to_name: dict | None
                      ) -> tuple[list[tuple[str, np.ndarray]], str]:
    """The scene's objects in the first frame as (name, (H, W) mask) pairs, and where they came from:
    the segmentation's scene objects when there is one, else the colour object finder's (named by
    colour: "red object", "red object 2", ...)."""
    if segmentation0 is not None and seg_id_to_name:
        seg = np.asarray(segmentation0)
        out = []
        for i in scene_object_ids(seg_id_to_name):
            mask = seg == i
            if mask.sum() >= MIN_OBJECT_PIXELS:
                out.append((str(seg_id_to_name[i]), mask))
        return out, "segmentation"
    out, seen = [], {}
    for mask in find_objects(rgb0):
        word = colour_name(np.median(np.asarray(rgb0)[mask], axis=0))
        seen[word] = seen.get(word, 0) + 1
        out.append((f"{word} object" + (f" {seen[word]}" if seen[word] > 1 else ""), mask))
    return out, "colour finder"


@dataclass
class _Model:
    """What the tracker keeps of one object."""

    points: np.ndarray  # (N, 3) object frame
    normals: np.ndarray  # (N, 3) object frame
    colors: np.ndarray  # (N, 3) uint8
    palette: np.ndarray  # (M, 3) float32: the object's own colours
    radius_m: float


def _object_model(rgb: np.ndarray, points_world: np.ndarray, normals_world: np.ndarray, valid: np.ndarray,
                  mask: np.ndarray, colour_tol: float = OBJECT_COLOUR_TOL) -> tuple[_Model, np.ndarray] | None:
    """The rigid point set of one object from its first-frame pixels, and its centroid (world); None
    when too few of its pixels have a depth."""
    sel = mask & valid
    if sel.sum() < MIN_OBJECT_PIXELS:
        return None
    pts = points_world[sel]
    # Pixels on the object's outline may carry the depth of what lies behind it: keep the points near
    # the bulk (within 3 median distances of the median point, at least 1 cm).
    med = np.median(pts, axis=0)
    dist = np.linalg.norm(pts - med, axis=1)
    keep = dist <= max(3.0 * float(np.median(dist)), 0.01)
    ordered = np.asarray(rgb)[sel]
    own = distinctive(rgb, mask, 2)[valid[mask]] if mask.sum() else np.zeros(0, bool)
    palette_src = ordered[own] if own.sum() >= MIN_OBJECT_PIXELS else ordered
    if len(palette_src) > PALETTE_SIZE:
        palette_src = palette_src[np.random.default_rng(0).choice(len(palette_src), PALETTE_SIZE, replace=False)]
    palette = np.asarray(palette_src, np.float32)
    # The model is what the tracker will see of it: its pixels of its own colours (not those blended
    # into the table at its outline).
    keep &= min_colour_distance(ordered, palette) < colour_tol
    if keep.sum() < MIN_OBJECT_PIXELS:
        return None
    pts, cols, nrm = pts[keep], ordered[keep], normals_world[sel][keep]
    centre = pts.mean(0)
    radius = float(np.linalg.norm(pts - centre, axis=1).max())
    return _Model(points=(pts - centre).astype(np.float32), normals=nrm.astype(np.float32), colors=cols.astype(np.uint8),
                  palette=palette, radius_m=radius), centre


# ---------------------------------------------------------------------- tracking


@dataclass
class TrackConfig:
    """Tracker settings (see the module docstring)."""

    rotation: str = "yaw"  # "yaw": translation + turn about the scene's up axis; "full": any rotation
    search_m: float = SEARCH_M
    min_visible_share: float = MIN_VISIBLE_SHARE
    colour_tol: float = OBJECT_COLOUR_TOL
    follow_hand: bool = True  # an object the layer loses where the hand moves it follows the hand's track
    keep_unreached: bool = True  # an object the hand (and what it moves) never reaches keeps its first pose

    def validate(self) -> None:
        if self.rotation not in ("yaw", "full"):
            raise UserError(f"TrackConfig.rotation is 'yaw' or 'full', got {self.rotation!r}")
        if not self.search_m > 0:
            raise UserError(f"TrackConfig.search_m must be > 0 metres, got {self.search_m}")


def _project(points_world: np.ndarray, K: np.ndarray, T_world_cam: np.ndarray, H: int, W: int):
    """Pixels (rows, cols), camera depths and an in-image mask of world points."""
    pc = transform_points(invert_pose(T_world_cam), points_world)
    z = pc[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        u = K[0, 0] * pc[:, 0] / z + K[0, 2]
        v = K[1, 1] * pc[:, 1] / z + K[1, 2]
    inside = (z > 1e-6) & np.isfinite(u) & np.isfinite(v) & (u >= 0) & (v >= 0) & (u < W) & (v < H)
    return np.where(inside, v, 0).astype(np.int64), np.where(inside, u, 0).astype(np.int64), z, inside


def _window(centre_world: np.ndarray, radius_m: float, K: np.ndarray, T_world_cam: np.ndarray, H: int, W: int):
    """The image rows/cols slice that holds a sphere (centre, radius) seen from the camera."""
    pc = transform_points(invert_pose(T_world_cam), centre_world[None])[0]
    if pc[2] <= radius_m:
        return slice(0, H), slice(0, W)
    u = K[0, 0] * pc[0] / pc[2] + K[0, 2]
    v = K[1, 1] * pc[1] / pc[2] + K[1, 2]
    r = max(K[0, 0], K[1, 1]) * radius_m / (pc[2] - radius_m) + 1
    r0, r1 = int(np.clip(np.floor(v - r), 0, H)), int(np.clip(np.ceil(v + r) + 1, 0, H))
    c0, c1 = int(np.clip(np.floor(u - r), 0, W)), int(np.clip(np.ceil(u + r) + 1, 0, W))
    return slice(r0, r1), slice(c0, c1)


def _icp(model_tree, model: "_Model", observed: np.ndarray, T_init: np.ndarray, up: np.ndarray | None,
         depth_m: np.ndarray, K: np.ndarray, T_world_cam: np.ndarray) -> tuple[np.ndarray, float, np.ndarray]:
    """Rigid fit of the model (object frame) to observed points (world) from T_init, with nearest-point
    pairs both ways: each observed point with its nearest model point, and each model point that faces
    the camera and has nothing in front of it in ``depth_m`` (H, W) with its nearest observed point (so
    the model cannot slide along a face whose far edge is not seen); the worst ``1 - TRIM_SHARE`` of each set and pairs beyond ``MAX_PAIR_M`` dropped.
    Returns (T_world_object, rms of the kept observed pairs, kept mask of ``observed``)."""
    from scipy.spatial import cKDTree  # scipy loads with the tracker only

    obs_tree = cKDTree(observed)
    has_normal = np.linalg.norm(model.normals, axis=1) >= 0.5

    def trim(dist):
        return dist <= min(_quantile(dist, TRIM_SHARE), MAX_PAIR_M) if len(dist) > 4 else dist <= MAX_PAIR_M

    T = T_init.copy()
    for _ in range(ICP_ITERATIONS):
        dist, idx = model_tree.query(transform_points(invert_pose(T), observed))
        kept = trim(dist)
        model_world = transform_points(T, model.points)
        normals_world = model.normals @ T[:3, :3].T
        facing = ~has_normal | (np.einsum("ij,ij->i", normals_world, model_world - T_world_cam[:3, 3]) < 0)
        rows, cols, z, inside = _project(model_world, K, T_world_cam, *depth_m.shape)
        d = depth_m[rows, cols]
        facing &= inside & ~((d > 0) & (d < z - DEPTH_TOL_M))  # seen from the camera, nothing in front
        back_dist, back_idx = obs_tree.query(model_world[facing])
        back_kept = trim(back_dist) if len(back_dist) else np.zeros(0, bool)
        if kept.sum() < 3:
            return T, np.inf, kept
        src = np.concatenate([model_world[idx[kept]], model_world[facing][back_kept]])
        dst = np.concatenate([observed[kept], observed[back_idx[back_kept]]])
        nrm = np.concatenate([normals_world[idx[kept]], normals_world[facing][back_kept]])
        step = plane_step(src, dst, nrm, up)
        T = step @ T
        if np.linalg.norm(step[:3, 3]) < CONVERGED_M and np.abs(step[:3, :3] - np.eye(3)).max() < CONVERGED_RAD:
            break
    return (T, *_residual(model_tree, observed, T))


def _residual(model_tree, observed: np.ndarray, T: np.ndarray) -> tuple[float, np.ndarray]:
    """(rms, kept) of the observed points' nearest model points at pose T, the worst pairs dropped as in ICP."""
    dist = model_tree.query(transform_points(invert_pose(T), observed))[0]
    kept = dist <= min(_quantile(dist, TRIM_SHARE), MAX_PAIR_M) if len(dist) > 4 else dist <= MAX_PAIR_M
    rms = float(np.sqrt(np.mean(dist[kept] ** 2))) if kept.any() else np.inf
    return rms, kept


def _quantile(x: np.ndarray, q: float) -> float:
    """The q-quantile of x (the lower value at the rank; ``np.quantile`` costs ten times as much here)."""
    k = min(int(q * (len(x) - 1)), len(x) - 1)
    return float(np.partition(x, k)[k])


def _fit_score(model: "_Model", observed: np.ndarray, T: np.ndarray, model_tree, depth_m: np.ndarray, K: np.ndarray,
               T_world_cam: np.ndarray) -> float:
    """How badly a pose explains the frame, both ways and untrimmed (pair distances capped at
    ``MAX_PAIR_M``): every observed point's distance to the model and every model point's that should be
    seen (facing the camera, nothing in front) to the observed points. Used to choose between fits: a
    partial view fits many places on a face one way, only the right one both ways."""
    from scipy.spatial import cKDTree  # scipy loads with the tracker only

    forward = np.minimum(model_tree.query(transform_points(invert_pose(T), observed))[0], MAX_PAIR_M)
    model_world = transform_points(T, model.points)
    normals_world = model.normals @ T[:3, :3].T
    has_normal = np.linalg.norm(model.normals, axis=1) >= 0.5
    seen = ~has_normal | (np.einsum("ij,ij->i", normals_world, model_world - T_world_cam[:3, 3]) < 0)
    rows, cols, z, inside = _project(model_world, K, T_world_cam, *depth_m.shape)
    d = depth_m[rows, cols]
    seen &= inside & ~((d > 0) & (d < z - DEPTH_TOL_M))
    back = np.minimum(cKDTree(observed).query(model_world[seen])[0], MAX_PAIR_M) if seen.any() else np.zeros(0)
    return float(np.mean(np.concatenate([forward, back]) ** 2))


def _best_fit(model_tree, model: "_Model", observed: np.ndarray, guess: np.ndarray, expected: np.ndarray,
              T_prev: np.ndarray, up: np.ndarray | None, depth_m: np.ndarray, K: np.ndarray, T_world_cam: np.ndarray,
              moving: bool = False):
    """The best of :func:`_icp` from up to three starts: the guess, the last pose (when the guess moved
    on at the last velocity), and the guess moved so that the model's expected visible points' centroid
    meets the observed points' (a fast motion leaves the guess far behind); a fit that turns more than ``MAX_TURN_DEG`` from the last pose (a flip onto a look-alike
    face of a symmetric object) is redone without rotation. Returns (T, rms, kept) of the fit that best
    explains the frame both ways (:func:`_fit_score`)."""
    starts = [guess] if np.allclose(guess, T_prev) else [guess, T_prev]
    shown = transform_points(guess, model.points[expected]) if expected.any() else transform_points(guess, model.points)
    shift = np.median(observed, axis=0) - shown.mean(0)
    if np.linalg.norm(shift) > 0.25 * model.radius_m:
        moved = guess.copy()
        moved[:3, 3] += shift
        starts.append(moved)
    best, best_score = (guess, np.inf, np.zeros(len(observed), bool)), np.inf
    for start in starts:
        fit = _icp(model_tree, model, observed, start, up, depth_m, K, T_world_cam)
        turn = np.degrees(np.arccos(np.clip((np.trace(fit[0][:3, :3] @ T_prev[:3, :3].T) - 1) / 2, -1, 1)))
        if turn > MAX_TURN_DEG:
            fit = _icp(model_tree, model, observed, start, np.zeros(3), depth_m, K, T_world_cam)
        score = _fit_score(model, observed, fit[0], model_tree, depth_m, K, T_world_cam)
        if np.isfinite(fit[1]) and score < best_score:
            best, best_score = fit, score
        if best_score <= GOOD_SCORE_M ** 2:  # explained both ways to a millimetre or so: no need to look further
            break
    # Objects stay put unless the frame says otherwise: the last pose wins when it explains the frame
    # nearly as well as the best fit (a blurred or partly covered still object otherwise creeps).
    if best[0] is not T_prev and np.isfinite(best_score):
        stay = _fit_score(model, observed, T_prev, model_tree, depth_m, K, T_world_cam)
        factor, floor = (STAY_FACTOR_MOVING, STAY_FLOOR_MOVING_M) if moving else (STAY_FACTOR, STAY_FLOOR_M)
        if stay <= factor * best_score + floor ** 2:
            return (T_prev.copy(), *_residual(model_tree, observed, T_prev))
    return best


def _translation_icp(source: np.ndarray, target: np.ndarray, target_normals: np.ndarray) -> np.ndarray | None:
    """(3,) the translation that best lays ``source`` points onto the surface of ``target`` points
    (N, 3) with their normals (point-to-plane; trimmed nearest points)."""
    from scipy.spatial import cKDTree  # scipy loads only when an object is carried

    tree = cKDTree(target)
    shift = np.zeros(3)
    for _ in range(ICP_ITERATIONS):
        dist, idx = tree.query(source + shift)
        keep = dist <= _quantile(dist, TRIM_SHARE)
        if keep.sum() < 3:
            return None
        step = plane_step(source[keep] + shift, target[idx[keep]], target_normals[idx[keep]], np.zeros(3))[:3, 3]
        shift += step
        if np.linalg.norm(step) < 1e-5:
            break
    # The arm's points must land on its surface: where they do not (its visible shape changed, e.g. the
    # hand came into view), the shift is not measured.
    dist, idx = tree.query(source + shift)
    off_plane = np.abs(np.einsum("ij,ij->i", source + shift - target[idx], target_normals[idx]))
    return shift if np.median(np.where(np.linalg.norm(target_normals[idx], axis=1) > 0.5, off_plane, dist)) <= ARM_FIT_M else None


def track_objects(rgb: np.ndarray, depth_m: np.ndarray, normal_cam: np.ndarray, K: np.ndarray,
                  T_world_cam: np.ndarray, masks: list[tuple[str, np.ndarray]], source: str,
                  instructed: str | None = None, config: TrackConfig = TrackConfig()) -> ObjectLayer:
    """Track the objects given by their first-frame masks through the clip (see the module docstring).

    rgb (T, H, W, 3) uint8, depth_m (T, H, W) metres (0 or NaN = none), normal_cam (T, H, W, 3),
    K (T, 3, 3), T_world_cam (T, 4, 4); masks: (name, (H, W) bool) of frame 0. Objects whose mask has
    too few pixels with a depth are left out (there is nothing to track). Returns an ObjectLayer whose
    ``point_object`` labels every valid pixel of every frame, in pixel order (as ``backproject.frame_points``).
    """
    from scipy.spatial import cKDTree  # scipy loads with the tracker only

    config.validate()
    rgb = np.asarray(rgb)
    depth = np.asarray(depth_m, np.float32)
    T_frames, H, W = depth.shape
    valid = np.isfinite(depth) & (depth > 0)
    depth = np.where(valid, depth, 0.0)
    K = np.asarray(K, np.float64)
    T_world_cam = np.asarray(T_world_cam, np.float64)
    up_axis = scene_up_axis(T_world_cam[0])
    up = up_axis if config.rotation == "yaw" else None
    static = static_depth(depth, valid, T_world_cam)

    def world_points(t):
        return transform_points(T_world_cam[t], unproject_depth(depth[t], K[t]).reshape(-1, 3)).reshape(H, W, 3)

    pts0 = world_points(0)
    n0 = np.asarray(normal_cam[0], np.float64) @ T_world_cam[0, :3, :3].T  # camera -> world, row vectors
    labels = np.full((T_frames, H, W), -1, np.int16)
    models, names, T_all = [], [], []
    for name, mask in masks:
        made = _object_model(rgb[0], pts0, n0, valid[0], np.asarray(mask, bool), config.colour_tol)
        if made is None:
            continue
        model, centre = made
        models.append(model)
        names.append(name)
        T0 = np.eye(4)
        T0[:3, 3] = centre
        T_all.append(np.repeat(T0[None], T_frames, 0))
        labels[0][np.asarray(mask, bool) & valid[0]] = len(models) - 1
    n_obj = len(models)
    trees = [cKDTree(m.points) for m in models]
    visibility = np.zeros((n_obj, T_frames), np.float32)
    confidence = np.zeros((n_obj, T_frames), np.float32)
    state = np.zeros((n_obj, T_frames), np.int8)
    visibility[:, 0] = 1.0
    confidence[:, 0] = 1.0
    start_height = [float(T[0, :3, 3] @ up_axis) for T in T_all]
    was_moving = [False] * n_obj  # moving when last seen
    touched_unseen = [False] * n_obj  # the arm or a moving object touched it while it was not seen
    # While an object is unseen: where the arm's motion would have taken it ({frame: T_world_object}, from
    # its last pose), whether something covered it meanwhile, and whether that hypothesis is in use.
    hidden: list[dict | None] = [None] * n_obj
    hidden_covered = [False] * n_obj
    hidden_used = [False] * n_obj
    hidden_arm_moved = [0.0] * n_obj  # how far (metres, summed) the arm's points at it moved while it was hidden
    heights = [float((m.points @ up_axis).max()) for m in models]  # its top above its centre
    arm_cache: dict[int, np.ndarray] = {}

    def arm_at(f, pts):
        if f not in arm_cache:
            arm_cache[f] = _arm_points(pts, rgb[f], depth[f], valid[f], static, palettes, config.colour_tol)
        return arm_cache[f]

    pts_prev = pts0
    palettes = np.concatenate([m.palette for m in models]) if models else np.zeros((0, 3), np.float32)
    for t in range(1, T_frames):
        pts_t = world_points(t)
        taken = np.zeros((H, W), bool)
        causes = None  # made when an object is not seen (what may be at it)
        for k, model in enumerate(models):
            T_prev = T_all[k][t - 1]
            guess = T_prev.copy()
            if t >= 2 and state[k, t - 1] == TRACKED and state[k, t - 2] == TRACKED:
                guess[:3, 3] += T_prev[:3, 3] - T_all[k][t - 2][:3, 3]  # on at its last velocity
            # Where the model's surface would be seen from the camera at the guess.
            model_world = transform_points(guess, model.points)
            normals_world = model.normals @ guess[:3, :3].T
            cam_centre = T_world_cam[t, :3, 3]
            facing = np.einsum("ij,ij->i", normals_world, model_world - cam_centre) < 0
            facing |= np.linalg.norm(model.normals, axis=1) < 0.5  # unknown normals: assume it faces the camera
            rows, cols, z, inside = _project(model_world, K[t], T_world_cam[t], H, W)
            expected = inside & facing
            n_expected = max(int(expected.sum()), MIN_OBJECT_PIXELS)
            # Observed points of the object's colours within a search sphere around the guess, widened
            # when nothing is found there (fast motion between frames), the whole frame once it is lost.
            found, seen_share = False, 0.0
            reaches = [model.radius_m + config.search_m, model.radius_m + WIDE_SEARCH * config.search_m]
            if state[k, t - 1] == LOST:
                reaches = [model.radius_m + LOST_SEARCH * config.search_m]
            for reach in reaches:
                rs, cs = (slice(0, H), slice(0, W)) if not np.isfinite(reach) else _window(guess[:3, 3], reach, K[t], T_world_cam[t], H, W)
                win_rgb = rgb[t][rs, cs].reshape(-1, 3)
                cand = (valid[t][rs, cs] & ~taken[rs, cs]).reshape(-1)
                cand &= np.linalg.norm(pts_t[rs, cs].reshape(-1, 3) - guess[:3, 3], axis=1) <= reach
                cand[cand] = min_colour_distance(win_rgb[cand], model.palette) < config.colour_tol
                observed = pts_t[rs, cs].reshape(-1, 3)[cand]
                seen_share = max(seen_share, len(observed) / n_expected)
                if len(observed) < MIN_OBJECT_PIXELS or len(observed) / n_expected < config.min_visible_share:
                    continue
                T_fit, rms, kept = _best_fit(trees[k], model, observed, guess, expected, T_prev, up,
                                             depth[t], K[t], T_world_cam[t], moving=was_moving[k] or state[k, t - 1] == HELD)
                if rms > MAX_FIT_RMS_M:
                    continue
                # Seen again after frames unseen: somewhere else only if something was at it meanwhile;
                # else it stays, if its last pose still explains what is seen.
                if (state[k, t - 1] in (OCCLUDED, LOST) and not touched_unseen[k]
                        and np.linalg.norm(T_fit[:3, 3] - T_prev[:3, 3]) > REFIND_M):
                    if _fit_score(model, observed, T_prev, trees[k], depth[t], K[t], T_world_cam[t]) > MAX_FIT_RMS_M ** 2:
                        break
                    rms, kept = _residual(trees[k], observed, T_prev)
                    T_fit = T_prev.copy()
                found = True
                T_all[k][t] = T_fit
                visibility[k, t] = min(1.0, seen_share)
                confidence[k, t] = min(1.0, seen_share) * float(np.exp(-rms / CONFIDENCE_RMS_M))
                state[k, t] = TRACKED
                was_moving[k] = np.linalg.norm(T_fit[:3, 3] - T_prev[:3, 3]) >= HELD_SPEED_M
                touched_unseen[k] = False
                hidden[k], hidden_covered[k], hidden_used[k] = None, False, False
                lab = labels[t][rs, cs]  # a view: rows and columns are slices
                win_lab = lab.reshape(-1).copy()
                win_lab[np.flatnonzero(cand)[kept]] = k
                lab[...] = win_lab.reshape(lab.shape)
                taken[rs, cs] |= lab == k
                break
            if found:
                continue
            visibility[k, t] = min(1.0, seen_share)
            if causes is None and static is not None:
                causes = _Causes([_arm_points(p, rgb[f], depth[f], valid[f], static, palettes, config.colour_tol)
                                  for p, f in ((pts_prev, t - 1), (pts_t, t))], models, trees, T_all, t)
            touched = causes is not None and causes.touches(k, T_prev)
            # Not found: is something in front of where it was, and is it being carried?
            prev_rows, prev_cols, prev_z, prev_in = _project(transform_points(T_prev, model.points), K[t], T_world_cam[t], H, W)
            look = prev_in & facing
            if look.any():
                d = depth[t][prev_rows[look], prev_cols[look]]
                in_front = (d > 0) & (d < prev_z[look] - DEPTH_TOL_M)
                covered = float(np.mean(in_front))
                # What covers it is at it (the hand over it), not passing far in front of it.
                at_it = in_front & (d >= prev_z[look] - CAUSE_REACH_M)
                if at_it.any():  # of other colours than its own (not the object itself, drawn elsewhere)
                    at_it[at_it] = min_colour_distance(rgb[t][prev_rows[look][at_it], prev_cols[look][at_it]],
                                                       model.palette) >= config.colour_tol
                touched = touched or int(at_it.sum()) >= MIN_CAUSE_POINTS
            else:
                covered = 1.0  # out of view: nothing says it is gone
            # Unseen while something is at it: it may be somewhere else when it is seen again.
            touched_unseen[k] = touched_unseen[k] or touched
            T_all[k][t] = T_prev
            # Held: the arm touches it and it was moving or lifted when last seen (or is already held); the
            # arm's motion around it then carries it. A still object the arm passes over stays put.
            moving = was_moving[k]
            lifted = float(T_prev[:3, 3] @ up_axis) - start_height[k] >= HELD_LIFT_M
            carried = None
            if static is not None and (moving or lifted or state[k, t - 1] == HELD):
                normals_t = np.asarray(normal_cam[t], np.float64) @ T_world_cam[t, :3, :3].T  # camera -> world
                arm = _arm_shift(pts_prev, pts_t, normals_t, depth, static, valid, labels, t,
                                 transform_points(T_prev, model.points))
                if arm is not None and arm[1] and np.linalg.norm(arm[0]) <= config.search_m:
                    carried = arm[0]
                elif arm is None and state[k, t - 1] == HELD and covered >= COVERED_SHARE:
                    carried = np.zeros(3)  # still in the hand; how the hand moved is not measured this frame
            if carried is not None:
                T_all[k][t] = T_prev.copy()
                T_all[k][t][:3, 3] += carried
                state[k, t] = HELD
                hidden[k], hidden_covered[k], hidden_used[k] = None, False, False
            elif covered >= COVERED_SHARE:
                state[k, t] = OCCLUDED
            else:
                state[k, t] = LOST
            if static is not None and state[k, t] != HELD:
                # It went with the arm while hidden? Follow the arm's motion near where it would now be.
                if hidden[k] is None:
                    hidden[k], hidden_arm_moved[k] = {t - 1: T_prev.copy()}, 0.0
                last = hidden[k][t - 1]
                T_hyp = last.copy()
                step = _arm_step(arm_at(t - 1, pts_prev), arm_at(t, pts_t), last[:3, 3], up_axis,
                                 float(last[:3, 3] @ up_axis) + heights[k] + HIDDEN_LOW_M)
                if step is not None:
                    hidden_arm_moved[k] += float(np.linalg.norm(step[0]))
                if step is not None and step[1]:
                    T_hyp[:3, 3] += step[0]
                    sink = start_height[k] - float(T_hyp[:3, 3] @ up_axis)
                    if sink > 0:  # it rests on what it stood on, or higher
                        T_hyp[:3, 3] += sink * up_axis
                if hidden_used[k] or state[k, t] == LOST:
                    T_hyp = _refine_hidden(trees[k], model, T_hyp, pts_t, rgb[t], valid[t] & ~taken, depth[t], K[t],
                                           T_world_cam[t], config.colour_tol, up_axis, lifted)
                hidden[k][t] = T_hyp
                hidden_covered[k] = hidden_covered[k] or state[k, t] == OCCLUDED
                # The arm that covered it moved at it: it may be found elsewhere when seen again.
                touched_unseen[k] = touched_unseen[k] or (hidden_covered[k] and hidden_arm_moved[k] >= HIDDEN_MOVE_M)
                first = min(hidden[k])
                went = np.linalg.norm(T_hyp[:3, 3] - hidden[k][first][:3, 3]) >= HIDDEN_MOVE_M
                # Used once its old place is seen empty (its colours too: not an object the fit refused),
                # after the arm covered it and took it away.
                empty = state[k, t] == LOST and seen_share < config.min_visible_share
                # ... and only where the arm hides it at its inferred place (else the frame refutes it).
                hides = _covered_share(model, T_hyp, depth[t], K[t], T_world_cam[t]) >= COVERED_SHARE
                if hides and (hidden_used[k] or (empty and hidden_covered[k] and went)):
                    frames = sorted(f for f in hidden[k] if f > first and (f == t or state[k, f] in (OCCLUDED, LOST, INFERRED)))
                    for f in frames:
                        T_all[k][f] = hidden[k][f]
                        state[k, f] = INFERRED
                        confidence[k, f] = INFERRED_CONFIDENCE
                    hidden_used[k] = True
                    touched_unseen[k] = True
                    continue
            if state[k, t] == LOST:
                confidence[k, t] = 0.0
                continue
            confidence[k, t] = UNSEEN_DECAY * confidence[k, t - 1]
        pts_prev = pts_t

    tracks = []
    for k, (name, model) in enumerate(zip(names, models)):
        color = np.median(model.palette, axis=0).astype(np.uint8)
        tracks.append(ObjectTrack(
            name=name, color=color, colour_name=colour_name(color), points_object=model.points, colors=model.colors,
            normals_object=model.normals, T_world_object=T_all[k], visibility=visibility[k],
            confidence=confidence[k], state=state[k],
        ))
    layer = ObjectLayer(tracks=tracks, source=source, instructed=instructed,
                        point_object=[labels[t][valid[t]] for t in range(T_frames)])
    if config.follow_hand or config.keep_unreached:
        follow_hand(layer, rgb, depth, K, T_world_cam, config)
    return layer


def follow_hand(layer: ObjectLayer, rgb: np.ndarray, depth_m: np.ndarray, K: np.ndarray, T_world_cam: np.ndarray,
                config: TrackConfig = TrackConfig()) -> GripperTrack | None:
    """Steps 5 and 6 of the tracker, in place on ``layer`` (its ``point_object`` labels of the clip rgb
    (T, H, W, 3), depth_m (T, H, W), K (T, 3, 3), T_world_cam (T, 4, 4)): the hand's track
    (:func:`reconstruction.hand_track.track_gripper`) and what it does to the objects. Returns the track,
    also kept as ``layer.hand`` (None when the camera moves or the layer has no labels: then nothing changes).

    5. ``config.follow_hand``, when ``layer.instructed`` names the object the instruction is about: that
       object, when the hand moves it (:func:`reconstruction.hand_track.hand_move`) and its track
       misses that move (:func:`reconstruction.hand_track.misses`: not placed at the end by a fit, the arm's
       points that hold it or the arm's motion while hidden, or moved the hand's way less than
       ``HAND_LAG_SHARE`` of it), follows the hand's displacement from the end of the hand's
       descent at it (``contact_frame``) on: along the table for a slide, carried for a grasp and set down
       where the hand lets go (on the table, or on the object under it), never below its starting height;
       state ``inferred``, confidence ``INFERRED_CONFIDENCE``.
       (Not knowing which object the words are about, the layer moves none: the closed loop's goal reading
       names it afterwards and reads the hand itself.)
    6. ``config.keep_unreached``: an object that neither the hand nor the object it moves ever comes within
       reach of (:func:`reconstruction.hand_track.contact_frame`) keeps its first pose in every frame (rigid
       bodies move only when touched: a prediction that redraws it elsewhere is a redraw, not a move); frames
       where the tracker had fitted it farther than ``REFIND_M`` away count as ``lost`` (the video lost it
       where it is).
    """
    gripper = layer.hand = track_gripper(rgb, depth_m, K, T_world_cam, layer)
    if gripper is None or gripper.seen().sum() < 2:
        return gripper
    up = np.asarray(gripper.up, np.float64)
    move = hand_move(layer, gripper)
    if config.follow_hand and move is not None and layer.instructed is not None:
        tr = layer.track(move.target)
        # the layer's own placement at the end (fitted, held in the arm's points, or inferred while hidden)
        # counts as showing it, if it went the hand's way
        if misses(tr.positions_world(), int(tr.state[-1]) in (TRACKED, HELD, INFERRED), move.displacement_m,
                  HAND_LAG_SHARE):
            _carry(tr, move, up)
    if config.keep_unreached:
        g = np.where(gripper.seen()[:, None], gripper.gripper_world_m, 0.0)
        moved = None if move is None else layer.track(move.target).positions_world()
        for tr in layer.tracks:
            if move is not None and tr.name == move.target:
                continue
            p0 = tr.positions_world()[0]
            if contact_frame(p0, g, gripper.seen(), up) is not None:
                continue
            if moved is not None and contact_frame(p0, moved, np.ones(len(moved), bool), up) is not None:
                continue
            _keep(tr)
    return gripper


def _carry(tr: ObjectTrack, move: HandMove, up: np.ndarray) -> None:
    """``tr`` follows ``move``'s path from its contact frame on (see :func:`follow_hand`), in place."""
    k = move.contact_frame
    base = tr.T_world_object[k].copy()
    start_height = float(tr.T_world_object[0, :3, 3] @ up)
    path = np.asarray(move.path_m, np.float64).copy()  # (T, 3)
    if move.kind == "grasp" and move.on is None and float(path[-1] @ up) < LIFT_M:
        # set down on the table where the hand lets go (the hand's point stops a little above or below)
        path[move.release_frame:] -= np.outer(path[move.release_frame:] @ up, up)
    T_all, state, confidence = tr.T_world_object.copy(), tr.state.copy(), tr.confidence.copy()
    for t in range(k + 1, tr.num_frames):
        T_all[t] = base
        T_all[t, :3, 3] = base[:3, 3] + path[t]
        sink = start_height - float(T_all[t, :3, 3] @ up)
        if sink > 0:  # it rests on what it stood on, or higher
            T_all[t, :3, 3] += sink * up
        state[t] = INFERRED
        confidence[t] = INFERRED_CONFIDENCE
    tr.T_world_object, tr.state, tr.confidence = T_all, state, confidence


def _keep(tr: ObjectTrack) -> None:
    """``tr`` keeps its first pose in every frame (see :func:`follow_hand`), in place."""
    away = np.linalg.norm(tr.T_world_object[:, :3, 3] - tr.T_world_object[0, :3, 3], axis=1) > REFIND_M
    state, confidence = tr.state.copy(), tr.confidence.copy()
    state[away] = LOST
    confidence[away] = 0.0
    tr.T_world_object = np.repeat(tr.T_world_object[:1], tr.num_frames, 0)
    tr.state, tr.confidence = state, confidence


def _arm_points(pts: np.ndarray, rgb: np.ndarray, depth: np.ndarray, valid: np.ndarray, static: np.ndarray,
                palettes: np.ndarray, colour_tol: float) -> np.ndarray:
    """(N, 3) world points of the arm in one frame: its pixels (:func:`arm_pixels`) of none of the
    objects' colours."""
    moving = arm_pixels(rgb, depth, valid, static)
    p = pts[moving]
    if len(p) and len(palettes):
        p = p[min_colour_distance(rgb[moving], palettes) >= colour_tol]
    return p


class _Causes:
    """What may move an object at frame t: the arm's points at t-1 and t, and the other objects that are
    moving (their last step, this frame's where already fitted)."""

    def __init__(self, arm_points: list[np.ndarray], models: list, trees: list, T_all: list, t: int):
        self.arm = np.concatenate(arm_points)
        self.models, self.trees, self.T_all, self.t = models, trees, T_all, t

    def touches(self, k: int, T_world_object: np.ndarray) -> bool:
        """Whether the arm or a moving object comes within ``CAUSE_REACH_M`` of object k at the given pose."""
        inv = invert_pose(T_world_object)
        if len(self.arm):
            near = np.isfinite(self.trees[k].query(transform_points(inv, self.arm), distance_upper_bound=CAUSE_REACH_M)[0])
            if near.sum() >= MIN_CAUSE_POINTS:
                return True
        for j, model in enumerate(self.models):
            if j == k:
                continue
            # Objects before k are fitted in this frame already; the others are where they were.
            now = self.t if j < k else self.t - 1
            if now < 1:
                continue
            T_j = self.T_all[j]
            if np.linalg.norm(T_j[now][:3, 3] - T_j[now - 1][:3, 3]) < HELD_SPEED_M:
                continue
            pts = transform_points(inv @ T_j[now], model.points)
            if np.isfinite(self.trees[k].query(pts, distance_upper_bound=CAUSE_REACH_M)[0]).sum() >= MIN_CAUSE_POINTS:
                return True
        return False


def _arm_shift(pts_prev: np.ndarray, pts_t: np.ndarray, normals_t: np.ndarray, depth: np.ndarray, static: np.ndarray,
               valid: np.ndarray, labels: np.ndarray, t: int, object_world: np.ndarray) -> tuple[np.ndarray, bool] | None:
    """How the arm's points around an object moved from frame t-1 to t ((3,) metres), and whether the
    arm touches the object (points within ``CONTACT_M`` of its surface at t-1); None when too few arm
    points are near it. The arm: pixels nearer than the clip's farthest depth there (moving things),
    not labelled as an object."""
    from scipy.spatial import cKDTree  # scipy loads only when an object is carried

    tree = cKDTree(object_world)

    def arm_near(pts, f, reach):
        moving = valid[f] & (depth[f] < static - DEPTH_TOL_M) & (labels[f] < 0)
        p = pts[moving]
        dist = tree.query(p, distance_upper_bound=reach)[0] if len(p) else np.zeros(0)
        return moving, dist <= reach, dist

    moving, near, dist = arm_near(pts_prev, t - 1, ARM_RADIUS_M)
    before, dist = pts_prev[moving][near], dist[near]
    moving, near, dist_t = arm_near(pts_t, t, ARM_RADIUS_M + SEARCH_M)
    after, after_normals = pts_t[moving][near], normals_t[moving][near]
    if len(before) < MIN_ARM_POINTS or len(after) < MIN_ARM_POINTS:
        return None
    # As much arm around it as before: where much more arm came into view (the hand closing over it),
    # its points cannot be matched to the last frame's.
    if (dist_t[near] <= ARM_RADIUS_M).sum() > ARM_GROWTH * len(before):
        return None
    shift = _translation_icp(before, after, after_normals)
    return None if shift is None else (shift, int((dist <= CONTACT_M).sum()) >= MIN_CONTACT_POINTS)


def _covered_share(model: "_Model", T_world_object: np.ndarray, depth_m: np.ndarray, K: np.ndarray,
                   T_world_cam: np.ndarray) -> float:
    """The share of the object's surface facing the camera at the given pose that has something in front
    of it in ``depth_m`` (H, W); 1 when none of it is in view."""
    pts = transform_points(T_world_object, model.points)
    nrm = model.normals @ T_world_object[:3, :3].T
    facing = (np.einsum("ij,ij->i", nrm, pts - T_world_cam[:3, 3]) < 0) | (np.linalg.norm(model.normals, axis=1) < 0.5)
    rows, cols, z, inside = _project(pts, K, T_world_cam, *depth_m.shape)
    look = inside & facing
    if not look.any():
        return 1.0
    d = depth_m[rows[look], cols[look]]
    return float(np.mean((d > 0) & (d < z[look] - DEPTH_TOL_M)))


def _arm_step(arm_prev: np.ndarray, arm_now: np.ndarray, centre: np.ndarray, up: np.ndarray,
              low_m: float) -> tuple[np.ndarray, bool] | None:
    """How the arm may have moved an unseen object at ``centre`` (world) from one frame to the next: the
    translation of the arm's points within ``HIDDEN_ARM_M`` of it (a trimmed point-to-point fit onto the
    next frame's arm points, from no motion), counted only while the arm reaches down to it (its points
    within ``HIDDEN_REACH_M`` across ``up`` of it that lie lower than ``low_m``, its top and a margin, along
    ``up``) and those points trail it along the motion: a hand that approaches from above, or moves away
    from it, does not move it. Returns (translation, whether it pushes the object), or None when too few
    arm points are near or they do not land on the next frame's arm (trimmed rms over ``ARM_FIT_M``: on
    recorded frames 1.3-2.8 mm, on predictions whose arm changes shape 3.4-18 mm)."""
    from scipy.spatial import cKDTree  # scipy loads only when an object is hidden

    src = arm_prev[np.linalg.norm(arm_prev - centre, axis=1) <= HIDDEN_ARM_M]
    dst = arm_now[np.linalg.norm(arm_now - centre, axis=1) <= HIDDEN_ARM_M + SEARCH_M]
    if len(src) < MIN_ARM_POINTS or len(dst) < MIN_ARM_POINTS:
        return None
    rel = src - centre
    height = rel @ up
    across = np.linalg.norm(rel - height[:, None] * up, axis=1)
    reach = (across <= HIDDEN_REACH_M) & (height + float(centre @ up) <= low_m)
    tree = cKDTree(dst)
    shift = np.zeros(3)
    for _ in range(2 * ICP_ITERATIONS):
        dist, idx = tree.query(src + shift)
        keep = dist <= _quantile(dist, TRIM_SHARE)
        step = np.mean(dst[idx[keep]] - src[keep] - shift, axis=0)
        shift += step
        if np.linalg.norm(step) < 1e-5:
            break
    # It pushes the object only from behind: the arm's low points trail it along the motion (an arm
    # leaving an object, or passing ahead of it, does not take it along).
    across_shift = shift - (shift @ up) * up
    pushes = bool(reach.any()) and float((rel[reach].mean(0)) @ across_shift) < 0
    dist = tree.query(src + shift)[0]
    rms = float(np.sqrt(np.mean(dist[dist <= _quantile(dist, TRIM_SHARE)] ** 2)))
    # The arm's points must land on the next frame's arm (a rigid motion of a drawn arm); a video whose arm
    # changes shape between frames measures nothing.
    return (shift, pushes) if rms <= ARM_FIT_M else None


def _refine_hidden(model_tree, model: "_Model", T_hyp: np.ndarray, pts: np.ndarray, rgb: np.ndarray, free: np.ndarray,
                   depth_m: np.ndarray, K: np.ndarray, T_world_cam: np.ndarray, colour_tol: float, up: np.ndarray,
                   lifted: bool) -> np.ndarray:
    """An inferred pose moved onto the few pixels of the object's colours seen near it (too few to track it:
    a corner under the hand), by a translation fit, across ``up`` only unless it is lifted; unchanged
    when fewer than ``MIN_OBJECT_PIXELS`` are seen, or the fit is poor or moves it farther than ``REFIND_M``."""
    reach = model.radius_m + REFIND_M
    near = free & (np.linalg.norm(pts - T_hyp[:3, 3], axis=-1) <= reach)
    if near.sum() < MIN_OBJECT_PIXELS:
        return T_hyp
    near[near] = min_colour_distance(rgb[near], model.palette) < colour_tol
    observed = pts[near]
    if len(observed) < MIN_OBJECT_PIXELS:
        return T_hyp
    T_fit, rms, _ = _icp(model_tree, model, observed, T_hyp, np.zeros(3), depth_m, K, T_world_cam)
    move = T_fit[:3, 3] - T_hyp[:3, 3]
    if not lifted:
        move -= (move @ up) * up
    if not rms <= MAX_FIT_RMS_M or np.linalg.norm(move) > REFIND_M:
        return T_hyp
    out = T_hyp.copy()
    out[:3, 3] += move
    return out


def truth_layer(first: ObjectLayer, object_poses: dict[str, np.ndarray]) -> ObjectLayer:
    """The simulator's own tracks of the objects of ``first`` (matched by name): each object's first-frame
    point set carried by its recorded poses (``object_poses/<name>``, (T, 7) xyz + wxyz). The viewer's
    compare mode draws these beside a prediction's. Objects without a recorded pose keep ``first``'s track."""
    tracks = []
    for tr in first.tracks:
        pose = object_poses.get(tr.name)
        if pose is None:
            tracks.append(tr)
            continue
        pose = np.asarray(pose, np.float64)
        T_sim = np.repeat(np.eye(4)[None], len(pose), 0)
        for t, p in enumerate(pose):
            T_sim[t, :3, :3] = matrix_from_wxyz(p[3:7])
            T_sim[t, :3, 3] = p[:3]
        # object -> world at t = T_sim[t] inv(T_sim[0]) T_world_object[0]
        T = np.einsum("tij,jk->tik", T_sim, invert_pose(T_sim[0]) @ tr.T_world_object[0])
        n = len(T)
        tracks.append(ObjectTrack(
            name=tr.name, color=tr.color, colour_name=tr.colour_name, points_object=tr.points_object, colors=tr.colors,
            normals_object=tr.normals_object, T_world_object=T, visibility=np.ones(n, np.float32),
            confidence=np.ones(n, np.float32), state=np.zeros(n, np.int8),
        ))
    return ObjectLayer(tracks=tracks, source="simulator poses", instructed=first.instructed, point_object=first.point_object)


def instructed_object(names: list[str], colour_names: list[str], intent: dict | None, instruction: str | None) -> str | None:
    """The object the instruction is about: the episode's intent target when it names one of ``names``;
    else the one object whose colour word the instruction says first ("place the red box onto the green
    box": the red one); else the scene's only object; else None."""
    target = (intent or {}).get("target")
    if target in names:
        return target
    for word in str(instruction or "").lower().replace(",", " ").split():
        hits = [n for n, c in zip(names, colour_names) if c == word]
        if len(hits) == 1:
            return hits[0]
    return names[0] if len(names) == 1 else None


def episode_objects(episode, camera: str, depth_m: np.ndarray | None = None, objects_from=None,
                    config: TrackConfig = TrackConfig(), truth: bool = False) -> ObjectLayer:
    """The object layer of one camera of an episode (a dataset episode or a prediction).

    The objects come from the first frame of ``objects_from`` (an Episode with the same camera, e.g. the
    dataset episode a prediction started from: its segmentation names them) when given, else from the
    episode's own first-frame segmentation, else from the colour object finder. ``depth_m`` (T, H, W):
    the depth to track in (e.g. a refined one; default the episode's). ``truth``: take the poses from the
    episode's recorded ``object_poses`` instead of tracking (:func:`truth_layer`), the raw points labelled
    by the segmentation of every frame.
    """
    cam = episode.cameras[camera]
    ref = episode if objects_from is None else objects_from
    ref_cam = ref.cameras.get(camera) or next(iter(ref.cameras.values()))
    if tuple(np.shape(ref_cam.rgb)[1:3]) != tuple(np.shape(cam.rgb)[1:3]):
        raise UserError(f"the objects' first frame is {np.shape(ref_cam.rgb)[1:3]} pixels but the video is "
                        f"{np.shape(cam.rgb)[1:3]}; give the episode the video was predicted from, at its resolution")
    seg0 = None if ref_cam.segmentation is None else np.asarray(ref_cam.segmentation[0])
    masks, source = first_frame_masks(np.asarray(ref_cam.rgb[0]), seg0, ref_cam.seg_id_to_name)
    depth = np.asarray(cam.depth_m if depth_m is None else depth_m, np.float32)
    frames = slice(0, 1) if truth else slice(None)
    rgb, K, T_world_cam = np.asarray(cam.rgb)[frames], np.asarray(cam.K)[frames], np.asarray(cam.T_world_cam)[frames]
    # the hand's steps once the instructed object is known (the hand moves that one)
    layer = track_objects(rgb, depth[frames], np.asarray(cam.normal_cam)[frames], K, T_world_cam, masks, source,
                          config=replace(config, follow_hand=False, keep_unreached=False))
    layer.instructed = instructed_object(layer.names(), [t.colour_name for t in layer.tracks],
                                         getattr(ref, "intent", None), episode.instruction)
    if not truth and (config.follow_hand or config.keep_unreached):
        follow_hand(layer, rgb, np.where(np.isfinite(depth), depth, 0.0).astype(np.float32), K, T_world_cam, config)
    if not truth:
        return layer
    out = truth_layer(layer, episode.object_poses)
    valid = np.isfinite(depth) & (depth > 0)
    if cam.segmentation is not None:
        index = {name: k for k, name in enumerate(out.names())}
        lut = {int(i): index[n] for i, n in cam.seg_id_to_name.items() if n in index}
        seg = np.asarray(cam.segmentation)
        labels = np.full(seg.shape, -1, np.int16)
        for i, k in lut.items():
            labels[seg == i] = k
        out.point_object = [labels[t][valid[t]] for t in range(len(seg))]
    else:
        out.point_object = []
    return out
