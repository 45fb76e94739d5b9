"""The words parser: an instruction -> skill, object, other object, direction and distance, by rules.

The ``words_plan`` arm of the closed loop plans from this alone (no world model): it shows what a
predicted future adds where the words do not state the goal (PushCube's "onto the target", PickCube's
"lift it up", which say no distance) or are phrased in words these rules do not know.

Rules, in order (the first that matches decides the skill):

  keep_still  "stay still", "do nothing", "don't move", "wait without moving", ...
  hover       "hover", "above/over the <object>" (not "above the table")
  reach       no object named, and a side ("left"/"right") named
  stack       "stack", or "on / onto / on top of the <colour> <cube|block|box|cylinder|one>"
  pull        pull, drag, draw, tug, "toward the robot", "closer"
  push        push, slide, nudge, shove, shift
  pick_place  put/set it down, place, carry, relocate, let go
  lift        lift, raise, hold, pick up, grasp, grab

Object: the first "<colour> <cube|block|box|cylinder>" (the second is the other object); a colour word
alone names an object by colour. Direction: forward = +x, back = -x, left = +y, right = -y (the robot's
frame, as ``datagen.instructions``), summed and normalised. Distance: "<n> cm"; when none is said,
``DEFAULT_DISTANCE_M`` (push, pull, pick-and-place) or a height from PickCube's height words.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

import numpy as np

COLOURS = ("red", "green", "blue", "yellow", "purple", "orange", "cyan", "white")
SHAPES = ("cube", "block", "box", "cylinder")
DEFAULT_DISTANCE_M = 0.10  # push / pull / pick-and-place when the words say no distance
LIFT_HEIGHTS_M = {"slightly": 0.05, "up": 0.14, "high": 0.25}  # PickCube's height words
DEFAULT_LIFT_M = 0.12
DIRECTION_VECTORS = {"forward": (1.0, 0.0), "back": (-1.0, 0.0), "left": (0.0, 1.0), "right": (0.0, -1.0)}

_STILL = ("stay still", "keep still", "do nothing", "keep the robot where it is", "stay where you are",
          "don't touch anything", "wait without moving", "stand still", "as they are", "don't move",
          "hold your position", "as it is")
_OBJ = rf"(?:(?:{'|'.join(COLOURS)}) )?(?:{'|'.join(SHAPES)}|one)"


@dataclass
class ParsedInstruction:
    skill: str | None  # push | pull | pick_place | lift | stack | hover | reach | keep_still | None (not understood)
    object_colour: str | None = None
    object_shape: str | None = None
    other_colour: str | None = None
    other_shape: str | None = None
    direction_xy: tuple[float, float] | None = None  # unit vector in the table plane (world), or None
    distance_m: float | None = None  # as said; None when the words say none
    place: str | None = None  # reach: "left" / "right"

    def travel_m(self) -> float:
        """How far to move the object: the distance said, else the default for the skill."""
        if self.distance_m is not None:
            return self.distance_m
        return DEFAULT_LIFT_M if self.skill == "lift" else DEFAULT_DISTANCE_M


def _direction(text: str) -> tuple[float, float] | None:
    v = np.zeros(2)
    for word, d in DIRECTION_VECTORS.items():
        if re.search(rf"\b{word}\b", text):
            v += d
    if "toward the robot" in text or "toward yourself" in text or "closer" in text:
        v += DIRECTION_VECTORS["back"] if not v.any() else 0.0
    n = float(np.linalg.norm(v))
    return None if n < 1e-9 else (float(v[0] / n), float(v[1] / n))


def parse_instruction(instruction: str) -> ParsedInstruction:
    """``instruction`` -> :class:`ParsedInstruction` (skill None when no rule matches)."""
    text = " ".join(instruction.lower().replace(",", " ").replace(".", " ").split())
    objects = re.findall(rf"\b({'|'.join(COLOURS)}) ({'|'.join(SHAPES)})\b", text)
    if not objects:
        objects = [(c, None) for c in re.findall(rf"\b({'|'.join(COLOURS)})\b", text)]
    named = bool(objects) or bool(re.search(rf"\b({'|'.join(SHAPES)})\b", text))
    direction = _direction(text)
    dist = re.search(r"(\d+(?:\.\d+)?) ?cm\b", text)
    distance = float(dist.group(1)) / 100 if dist else None
    height = re.search(rf"\b({'|'.join(LIFT_HEIGHTS_M)})\b", text)

    if any(p in text for p in _STILL):
        skill = "keep_still"
    elif "hover" in text or re.search(rf"\b(above|over) the {_OBJ}\b", text):
        skill = "hover"
    elif not named and re.search(r"\b(left|right)\b", text):
        skill = "reach"
    elif "stack" in text or "tower" in text or re.search(rf"\b(on|onto|on top of) the {_OBJ}\b", text) \
            or re.search(r"\bgoes on\b", text):
        skill = "stack"
    elif re.search(r"\b(pull|pulling|drag|draw|tug)\b", text) or "toward the robot" in text or "closer" in text:
        skill = "pull"
    elif re.search(r"\b(push|pushed|pushing|slide|nudge|shove|shift)\b", text):
        skill = "push"
    elif re.search(r"\b(put it down|put down|place|set it down|carry|carrying|relocate|let go)\b", text) \
            or re.search(r"\bput it\b.*\b(down|cm)\b", text):
        skill = "pick_place"
    elif re.search(r"\b(lift|raise|hold|pick|grasp|grab|up)\b", text):
        skill = "lift"
    else:
        skill = None

    out = ParsedInstruction(skill=skill, direction_xy=direction, distance_m=distance)
    if objects and skill not in ("reach", "keep_still"):
        out.object_colour, out.object_shape = objects[0]
        if len(objects) > 1:
            out.other_colour, out.other_shape = objects[1]
    if skill == "reach":
        side = re.search(r"\b(left|right)\b", text)
        out.place = side.group(1) if side else None
    if skill == "lift" and distance is None and height:
        out.distance_m = LIFT_HEIGHTS_M[height.group(1)]
    if skill == "pull" and direction is None:
        out.direction_xy = DIRECTION_VECTORS["back"]
    return out
