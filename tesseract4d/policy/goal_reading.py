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
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

MOVED_M = 0.02  # an object moving less than this over the clip counts as still
LIFT_M = 0.03  # raised at least this far above its start ...
LIFT_FRAMES = 2  # ... in this many frames in a row: lifted
ON_XY_M = 0.03  # stacked: centres this close in the table plane at the end ...
ON_DZ_M = (0.015, 0.08)  # ... and its origin this much higher than the other's


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

    def as_dict(self) -> dict:
        return {"skill": self.skill, "target": self.target, "displacement_m": [round(float(v), 4) for v in self.displacement_m],
                "lifted": self.lifted, "held_at_end": self.held_at_end, "on": self.on, "moved_m": round(self.moved_m, 4)}


def read_goal(layer, up=(0.0, 0.0, 1.0)) -> Goal:
    """The goal the object layer ``layer`` (frame 0 = now) shows; ``up``: the world's up axis."""
    up = np.asarray(up, np.float64)
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
    if on is not None:
        skill = "stack"
    elif held:
        skill = "lift"
    elif lifted:
        skill = "pick_place"
    else:
        skill = "pull" if disp[0] < 0 and abs(disp[0]) >= abs(disp[1]) else "push"
    return Goal(skill, name, disp, lifted=lifted, held_at_end=held, on=on, moved_m=moved[name])
