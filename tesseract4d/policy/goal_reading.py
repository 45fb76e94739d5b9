"""Goal reading: what a predicted 4D scene's object layer says should happen, as a primitive's goal.

From the object layer of a clip that starts at the current observation (frame 0 = now;
:class:`reconstruction.objects.ObjectLayer`), :func:`read_goal` finds the object the future moves (the
instructed one when it moves, else the one that moves most), where it ends (its displacement, world
metres), whether it was lifted on the way (``lifted``: up in two frames in a row, or at the end) or is still up at the end (``held_at_end``), and
for stacking, on what it ends: another object under it at the end (centres within ``ON_XY_M`` in the
table plane, its origin ``ON_DZ_M`` higher). The skill follows from those:

  stack       it ends on another object;
  lift        it ends up in the air (held);
  pick_place  it was lifted on the way and ends on the table elsewhere;
  push/pull   it slid on the table (pull when it comes mostly toward the robot, -x);
  none        no object moves more than ``MOVED_M``: the prediction says the goal is reached.

Positions are the object frames' origins (their first-frame centroids), so a displacement is exact
whatever part of the object the camera saw.

**The arm, where the object is lost.** A predicted clip at 128² often draws the arm reaching the
instructed object and carrying on toward the goal while the object smears and vanishes under the gripper:
the layer then sees it move a few centimetres, or not at all. Given the clip's gripper track
(:mod:`tesseract4d.policy.gripper_track`), :func:`read_goal` also reads what the arm does to the object
(:func:`arm_goal`): the object the arm reaches (the instructed one when known, else the one it comes
down to) is the moved object, from the first frame the arm is within ``REACH_XY_M`` of where it is now
in the table plane and at most ``REACH_DZ_M`` above it (both wide, for the gripper's point is the hand's,
about 4 cm beside and 6 cm above the TCP). From the end of its descent there the arm either slides along
the table (it travels ``MOVED_M`` in the plane rising less than ``SLIDE_SLOPE`` of that: a push or pull,
let go where it rises ``LIFT_M`` or at the end) or first rises ``LIFT_M`` (in ``LIFT_FRAMES`` frames in a row;
a grasp: carried until the arm
comes down ``LIFT_M`` below its highest point so far, at the end of that descent, or held at the end), and the object follows the arm's
displacement over that stretch (the descent ends where the arm stops coming down by ``DESCENT_M`` a
frame). Where it ends then says stack (above another object, within ``ARM_ON_XY_M``), lift (held up) or
pick-and-place. That reading replaces the layer's only when the layer does not show the object where the
arm left it: not tracked in the last frame, or moved the arm's way but less than ``LAG_SHARE`` of the arm's
displacement. An object the layer still sees where it was, the arm gone, stays put: the arm left it alone.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from reconstruction.objects import STATES

MOVED_M = 0.02  # an object moving less than this over the clip counts as still
LIFT_M = 0.03  # raised at least this far above its start ...
LIFT_FRAMES = 2  # ... in this many frames in a row: lifted
ON_XY_M = 0.03  # stacked: centres this close in the table plane at the end ...
ON_DZ_M = (0.015, 0.08)  # ... and its origin this much higher than the other's
REACH_XY_M = 0.10  # the arm reaches an object: the gripper's point this close in the table plane ...
REACH_DZ_M = 0.10  # ... and at most this high above the object's origin
DESCENT_M = 0.005  # the arm still comes down when it is this much lower (less: the clip's depth noise)
SLIDE_SLOPE = 0.5  # a slide: when the arm has travelled MOVED_M in the plane it has risen less than this share of it
LAG_SHARE = 0.8  # the layer's object follows the arm's reading when it moved less than this share of it
ARM_ON_XY_M = 0.05  # the arm's reading: set on the object whose centre is this close in the table plane


@dataclass
class Goal:
    """A primitive's goal read from a future (world metres)."""

    skill: str  # push | pull | pick_place | lift | stack | none
    target: str | None  # the object's name in the object layer
    displacement_m: np.ndarray  # (3,) where the object's origin ends relative to where it starts
    lifted: bool = False
    held_at_end: bool = False
    on: str | None = None  # stack: the object it ends on
    moved_m: float = 0.0  # the largest distance from its start over the clip
    source: str = "objects"  # what it was read from: "objects" (the layer's tracks) or "arm" (the gripper's track)
    contact_frame: int | None = None  # the arm's reading: the frames where the arm reaches and lets go of it
    release_frame: int | None = None

    def as_dict(self) -> dict:
        out = {"skill": self.skill, "target": self.target, "displacement_m": [round(float(v), 4) for v in self.displacement_m],
               "lifted": self.lifted, "held_at_end": self.held_at_end, "on": self.on, "moved_m": round(self.moved_m, 4),
               "source": self.source}
        if self.source == "arm":
            out.update(contact_frame=self.contact_frame, release_frame=self.release_frame)
        return out


def read_goal(layer, up=(0.0, 0.0, 1.0), gripper=None) -> Goal:
    """The goal the object layer ``layer`` (frame 0 = now) shows; ``up``: the world's up axis. ``gripper``:
    the clip's :class:`~tesseract4d.policy.gripper_track.GripperTrack`, read where the layer lost the
    object the arm moves (see the module docstring)."""
    goal = _layer_goal(layer, np.asarray(up, np.float64))
    if gripper is None:
        return goal
    arm = arm_goal(layer, gripper)
    if arm is None or not _arm_wins(layer, arm):
        return goal
    return arm


def _layer_goal(layer, up: np.ndarray) -> Goal:
    """The goal the object layer's tracks show by themselves."""
    if not len(layer):
        return Goal("none", None, np.zeros(3))
    moved = {}
    for tr in layer.tracks:
        p = tr.positions_world()  # (T, 3)
        moved[tr.name] = float(np.max(np.linalg.norm(p - p[0], axis=1)))
    name = layer.instructed if layer.instructed in moved and moved[layer.instructed] >= MOVED_M else max(moved, key=moved.get)
    if moved[name] < MOVED_M:
        return Goal("none", name, np.zeros(3), moved_m=moved[name])
    tr = layer.track(name)
    p = tr.positions_world()
    disp = p[-1] - p[0]
    rise = (p - p[0]) @ up  # (T,)
    # lifted: up for at least LIFT_FRAMES frames in a row (one frame's rise is a predicted clip's noise)
    up_run = np.convolve((rise >= LIFT_M).astype(int), np.ones(LIFT_FRAMES, int), mode="valid")
    lifted = bool(len(up_run) and up_run.max() >= LIFT_FRAMES) or bool(rise[-1] >= LIFT_M)
    on = None
    for other in layer.tracks:
        if other.name == name:
            continue
        q = other.positions_world()[-1]
        gap = p[-1] - q
        dz = float(gap @ up)
        if np.linalg.norm(gap - dz * up) <= ON_XY_M and ON_DZ_M[0] <= dz <= ON_DZ_M[1]:
            on = other.name
    held = on is None and bool(rise[-1] >= LIFT_M)
    skill = _skill(on, held, lifted, disp)
    return Goal(skill, name, disp, lifted=lifted, held_at_end=held, on=on, moved_m=moved[name])


def _skill(on: str | None, held: bool, lifted: bool, displacement: np.ndarray) -> str:
    """The skill that explains a moved object's end: onto another object, still up, set down elsewhere,
    or slid along the table (toward the robot, -x, a pull; otherwise a push)."""
    if on is not None:
        return "stack"
    if held:
        return "lift"
    if lifted:
        return "pick_place"
    return "pull" if displacement[0] < 0 and abs(displacement[0]) >= abs(displacement[1]) else "push"


def _filled(points: np.ndarray) -> np.ndarray:
    """(T, 3) ``points`` with each unseen (NaN) frame given the last seen one (the first seen before it)."""
    out = np.asarray(points, np.float64).copy()
    seen = np.isfinite(out).all(axis=1)
    idx = np.where(seen, np.arange(len(out)), -1)
    idx = np.maximum.accumulate(idx)
    idx[idx < 0] = np.flatnonzero(seen)[0]
    return out[idx]


def _contact(p0: np.ndarray, g: np.ndarray, seen: np.ndarray, up: np.ndarray) -> int | None:
    """The first frame the gripper (T, 3) is within reach of an object at p0 (3,), or None when never."""
    gap = g - p0
    dz = gap @ up
    flat = np.linalg.norm(gap - np.outer(dz, up), axis=1)
    near = np.flatnonzero(seen & (flat <= REACH_XY_M) & (dz <= REACH_DZ_M))
    return int(near[0]) if len(near) else None


def _motion(g: np.ndarray, c: int, up: np.ndarray) -> tuple[str, int, int] | None:
    """What the arm (T, 3) does from its contact frame c: ("slide" | "grasp", k, r): from its lowest point k
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
            # let go: the arm comes down LIFT_M below its highest point so far, at the end of that descent
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
    """Whether the arm's heights ``h`` (T,) are ``LIFT_M`` above ``base`` in ``LIFT_FRAMES`` frames in a row from
    t (fewer at the clip's end): one frame's rise is the clip's depth noise."""
    return bool(np.all(h[t:t + LIFT_FRAMES] - base >= LIFT_M))


def arm_goal(layer, gripper) -> Goal | None:
    """The goal the arm's motion shows for the object it reaches (see the module docstring), or None when
    it reaches none or does not move it. Its ``source`` is ``"arm"``."""
    seen = gripper.seen()
    if seen.sum() < 2 or not len(layer):
        return None
    up = np.asarray(gripper.up, np.float64)
    g = _filled(gripper.gripper_world_m)
    contacts = {tr.name: _contact(tr.positions_world()[0], g, seen, up) for tr in layer.tracks}
    name = layer.instructed if layer.instructed in contacts else None
    if name is None:  # the object the arm reaches first (then the one it comes lowest to)
        reached = [n for n, c in contacts.items() if c is not None]
        if not reached:
            return None
        name = min(reached, key=lambda n: (contacts[n], float((g[contacts[n]] - layer.track(n).positions_world()[0]) @ up)))
    c = contacts[name]
    if c is None:
        return None
    motion = _motion(g, c, up)
    if motion is None:
        return None
    kind, k, r = motion
    disp = g[r] - g[k]
    slides = kind == "slide"
    if slides:
        disp = disp - (disp @ up) * up
    if np.linalg.norm(disp) < MOVED_M:
        return None
    p = layer.track(name).positions_world()
    end = p[0] + disp  # still until the arm reaches it (a blurred object's track may drift before)
    lifted = not slides
    on = None
    if lifted:
        best = ARM_ON_XY_M
        for other in layer.tracks:
            if other.name == name:
                continue
            q = other.positions_world()[0]  # the arm moves one object; the others stay where they are
            gap = end - q
            dz = float(gap @ up)
            flat = float(np.linalg.norm(gap - dz * up))
            if flat <= best and dz >= ON_DZ_M[0]:
                on, best = other.name, flat
    held = lifted and on is None and float((end - p[0]) @ up) >= LIFT_M
    displacement = end - p[0]
    skill = _skill(on, held, lifted, displacement)
    if skill in ("push", "pull", "pick_place"):
        displacement = displacement - (displacement @ up) * up
    return Goal(skill, name, displacement, lifted=lifted, held_at_end=held, on=on,
                moved_m=float(np.linalg.norm(displacement)), source="arm", contact_frame=k, release_frame=r)


def _arm_wins(layer, arm: Goal) -> bool:
    """Whether the arm's reading replaces the layer's: the layer does not show the arm's object where the arm
    left it (not tracked at the end, or moved the arm's way by less than ``LAG_SHARE`` of the arm's reading)."""
    tr = layer.track(arm.target)
    if STATES[int(tr.state[-1])] != "tracked":
        return True
    p = tr.positions_world()
    own = p[-1] - p[0]
    along = float(own @ arm.displacement_m) / max(float(np.linalg.norm(arm.displacement_m)), 1e-9)
    return MOVED_M <= along < LAG_SHARE * float(np.linalg.norm(arm.displacement_m))
