"""Language instructions: per-task templates filled with the scene's attributes.

ManiSkill's tabletop tasks have no language, so each task gets several paraphrases here. They
are split in two sets: ``train`` (datagen's default) and ``heldout`` (never used for training
data; the demo and held-out evaluation use them to test generalisation to new wording).

Attributes come from the scene after reset (``scene_attributes``): object colours (which
``--randomize-colors`` changes) and where the goal lies relative to the object, in words.
Directions are from the robot's point of view: it stands at x < 0 facing +x, so
``forward`` = +x (away from the robot), ``back`` = -x, ``left`` = +y, ``right`` = -y.
"""

from __future__ import annotations

import numpy as np

from datagen.tasks import get_task
from tesseract4d.errors import UserError

SPLITS = ("train", "heldout")

# Paraphrases per task. Fields: {color}, {color2}, {direction}, {height}, {side}.
TEMPLATES: dict[str, dict[str, list[str]]] = {
    "PickCube-v1": {
        "train": [
            "pick up the {color} cube and lift it {height} {direction}",
            "grasp the {color} cube and raise it {height} {direction}",
            "lift the {color} block {height} {direction}",
            "take the {color} cube and hold it {height} {direction}",
            "pick the {color} cube up and hold it {height} {direction}",
            "raise the {color} block {height} {direction} with the gripper",
        ],
        "heldout": [
            "grab the {color} box and carry it {height} {direction}",
            "move the {color} cube up, {height} {direction}",
        ],
    },
    "PushCube-v1": {
        "train": [
            "push the {color} cube {direction} onto the target",
            "slide the {color} cube {direction} to the red and white target",
            "push the {color} block {direction} until it reaches the goal",
            "slide the {color} block {direction} onto the goal",
            "move the {color} cube {direction} onto the target by pushing it",
        ],
        "heldout": [
            "nudge the {color} box {direction} onto the bullseye",
            "shove the {color} cube {direction} to the goal marker",
        ],
    },
    "PullCube-v1": {
        "train": [
            "pull the {color} cube {direction} onto the target",
            "drag the {color} cube {direction} to the red and white target",
            "pull the {color} block {direction} until it reaches the goal",
            "drag the {color} block {direction} onto the goal",
            "move the {color} cube {direction} onto the target by pulling it",
        ],
        "heldout": [
            "draw the {color} box {direction} onto the bullseye",
            "bring the {color} cube {direction} to the goal marker",
        ],
    },
    "StackCube-v1": {
        "train": [
            "stack the {color} cube on the {color2} cube",
            "put the {color} cube on top of the {color2} cube",
            "pick up the {color} block and place it on the {color2} block {direction}",
            "stack the {color} block on top of the {color2} block",
            "stack the {color} cube {direction} on the {color2} cube",
        ],
        "heldout": [
            "place the {color} box onto the {color2} box",
            "move the {color} cube {direction} and set it on the {color2} one",
        ],
    },
    "LiftPegUpright-v1": {
        "train": [
            "stand the peg on the {side} upright",
            "lift the peg on the {side} so it stands upright",
            "turn the lying peg upright",
            "put the peg on the {side} upright",
            "raise the peg on the {side} until it is upright",
        ],
        "heldout": [
            "set the peg on its end",
            "make the peg on the {side} stand up vertically",
        ],
    },
    "PullCubeTool-v1": {
        "train": [
            "use the L-shaped tool to pull the {color} cube toward the robot",
            "grab the hook and drag the {color} cube closer",
            "pick up the tool and pull the {color} cube {direction}",
            "use the hook to drag the {color} cube {direction}",
            "pull the {color} cube {direction} with the L-shaped tool",
        ],
        "heldout": [
            "with the hook, bring the {color} block back within reach",
            "hook the {color} cube with the tool and draw it in",
        ],
    },
    "PlugCharger-v1": {
        "train": [
            "plug the charger into the socket {direction}",
            "insert the charger into the receptacle {direction}",
            "pick up the charger and plug it in {direction}",
            "plug the charger in {direction}",
            "put the charger into the socket {direction}",
        ],
        "heldout": [
            "connect the charger to the wall socket {direction}",
            "push the plug into the outlet {direction}",
        ],
    },
    "PegInsertionSide-v1": {
        "train": [
            "insert the peg into the hole of the box {direction}",
            "pick up the peg and push it sideways into the hole {direction}",
            "put the peg into the box's hole {direction}",
            "push the peg into the hole of the box {direction}",
            "insert the peg sideways into the box {direction}",
        ],
        "heldout": [
            "slide the stick into the opening of the box {direction}",
            "fit the peg into the side hole {direction}",
        ],
    },
}

# A goal closer than this (metres) to the object in the table plane counts as "straight up".
_SAME_PLACE_M = 0.02


def direction_words(delta_xy: np.ndarray) -> str:
    """Where a displacement (dx, dy) in world metres points, in the robot's words.

    Returns e.g. "forward", "to the left", "back and to the right". A component counts when it
    is at least 40 % of the larger one, so diagonal goals get both words.
    """
    dx, dy = float(delta_xy[0]), float(delta_xy[1])
    big = max(abs(dx), abs(dy))
    if big < _SAME_PLACE_M:
        return "in place"
    parts = []
    if abs(dx) >= 0.4 * big:
        parts.append("forward" if dx > 0 else "back")
    if abs(dy) >= 0.4 * big:
        parts.append("to the left" if dy > 0 else "to the right")
    return " and ".join(parts)


def side_words(xy: np.ndarray) -> str:
    """Which part of the table a point (x, y) is on, from the robot: 'left', 'right' or 'middle'."""
    y = float(xy[1])
    return "left" if y > 0.03 else "right" if y < -0.03 else "middle"


def height_words(dz: float) -> str:
    """How far up a goal is (metres above the object) in words."""
    return "slightly" if dz < 0.08 else "high" if dz > 0.2 else "up"


def scene_attributes(env_id: str, positions: dict[str, np.ndarray], colors: dict[str, str]) -> dict:
    """Instruction attributes of a scene.

    positions: recorded object name -> world xyz (3,) in metres (TaskSpec.objects in tasks.py).
    colors: recorded object name -> colour name for the task's colourable actors.
    Returns a JSON-able dict of words (color, color2, direction, height, side as the task uses).
    """
    spec = get_task(env_id)
    attrs: dict = {}
    if spec.colorable:
        attrs["color"] = colors.get(spec.colorable[0], spec.default_colors[0])
    if len(spec.colorable) > 1:
        attrs["color2"] = colors.get(spec.colorable[1], spec.default_colors[1])
    p = {k: np.asarray(v, dtype=np.float64) for k, v in positions.items()}
    if env_id == "PickCube-v1":
        d = p["goal"] - p["cube"]
        words = direction_words(d[:2])
        attrs["direction"] = "" if words == "in place" else words
        attrs["height"] = height_words(d[2])
    elif env_id in ("PushCube-v1", "PullCube-v1"):
        attrs["direction"] = direction_words((p["goal"] - p["cube"])[:2])
    elif env_id == "StackCube-v1":
        attrs["direction"] = direction_words((p["cubeB"] - p["cubeA"])[:2])
    elif env_id == "LiftPegUpright-v1":
        attrs["side"] = side_words(p["peg"][:2])
    elif env_id == "PullCubeTool-v1":
        attrs["direction"] = "back toward the robot"
    elif env_id == "PlugCharger-v1":
        attrs["direction"] = _sentence_direction(p["receptacle"] - p["charger"])
    elif env_id == "PegInsertionSide-v1":
        attrs["direction"] = _sentence_direction(p["box"] - p["peg"])
    return attrs


def _sentence_direction(delta: np.ndarray) -> str:
    words = direction_words(delta[:2])
    return "right where it is" if words == "in place" else words


def make_instruction(env_id: str, attributes: dict, rng: np.random.Generator, split: str = "train") -> str:
    """One instruction for a scene: a paraphrase of ``split`` chosen by ``rng``, filled with attributes."""
    if split not in SPLITS:
        raise UserError(f"instruction split must be one of {SPLITS}, got {split!r}")
    if env_id not in TEMPLATES:
        raise UserError(f"no instruction templates for {env_id!r}; tasks with templates: {', '.join(TEMPLATES)}")
    templates = TEMPLATES[env_id][split]
    template = templates[int(rng.integers(len(templates)))]
    text = template.format(**{k: attributes.get(k, "") for k in ("color", "color2", "direction", "height", "side")})
    return " ".join(text.split())
