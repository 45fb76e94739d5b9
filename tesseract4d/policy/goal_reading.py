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
the layer then sees it move a few centimetres, or not at all. Given the clip's hand track
(:mod:`reconstruction.hand_track`), :func:`read_goal` also reads what the hand does to the object
(:func:`arm_goal`, from :func:`reconstruction.hand_track.hand_move`: the object it reaches, from the end of
its descent there a slide along the table or a grasp, carried until set down, and the object following the
hand's displacement over that stretch). Where it ends then says stack (set on another object), lift (held
up) or pick-and-place. That reading replaces the layer's only when the layer's track misses the hand's move
(:func:`reconstruction.hand_track.misses`: not tracked in the last frame, or moved the hand's way but less
than ``LAG_SHARE`` of it). An object the layer still sees where it was, the arm gone, stays put: the arm
left it alone. The object layer itself follows the hand the same way (:mod:`reconstruction.objects`), so
its tracks already show such a move, state ``inferred``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from reconstruction.hand_track import LIFT_FRAMES, LIFT_M, MOVED_M, ON_DZ_M, hand_move, misses
from reconstruction.objects import STATES

ON_XY_M = 0.03  # stacked: centres this close in the table plane at the end (and ON_DZ_M higher)


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
    the clip's :class:`~reconstruction.hand_track.GripperTrack`, read where the layer lost the
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


def arm_goal(layer, gripper) -> Goal | None:
    """The goal the hand's motion shows for the object it reaches (:func:`reconstruction.hand_track.hand_move`),
    or None when it reaches none or does not move it. Its ``source`` is ``"arm"``."""
    move = hand_move(layer, gripper)
    if move is None:
        return None
    up = np.asarray(gripper.up, np.float64)
    lifted = move.kind == "grasp"
    displacement = np.asarray(move.displacement_m, np.float64)
    held = lifted and move.on is None and float(displacement @ up) >= LIFT_M
    skill = _skill(move.on, held, lifted, displacement)
    if skill in ("push", "pull", "pick_place"):
        displacement = displacement - (displacement @ up) * up
    return Goal(skill, move.target, displacement, lifted=lifted, held_at_end=held, on=move.on,
                moved_m=float(np.linalg.norm(displacement)), source="arm", contact_frame=move.contact_frame,
                release_frame=move.release_frame)


def _arm_wins(layer, arm: Goal) -> bool:
    """Whether the arm's reading replaces the layer's: the layer's track of the arm's object misses the hand's
    move (:func:`reconstruction.hand_track.misses`)."""
    tr = layer.track(arm.target)
    return misses(tr.positions_world(), STATES[int(tr.state[-1])] == "tracked", arm.displacement_m)
