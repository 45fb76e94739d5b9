"""Instructions for skill episodes, written from the skill's parameters.

Every paraphrase names what tells one future of a scene from another: the object (colour and
shape, "the green cylinder"), the direction (the robot-frame words of
``datagen.instructions.direction_words``) and how far. As for the task templates, there is a
``train`` set and a ``heldout`` set of paraphrases (``datagen.instructions.SPLITS``).
"""

from __future__ import annotations

import numpy as np

from datagen.instructions import SPLITS, direction_words
from tesseract4d.errors import UserError

# Fields: {object}, {other}, {direction}, {distance}, {place}.
TEMPLATES: dict[str, dict[str, list[str]]] = {
    "push": {
        "train": ["push the {object} {direction} by {distance}", "slide the {object} {distance} {direction}",
                  "nudge the {object} {direction}, about {distance}",
                  "could you push the {object} {direction} by {distance}", "give the {object} a {distance} push {direction}",
                  "shift the {object} {direction} by {distance} with the gripper",
                  "use the gripper to push the {object} {direction} by {distance}",
                  "with a push, move the {object} {distance} {direction}",
                  "the {object} should be pushed {direction} by {distance}"],
        "heldout": ["shove the {object} {distance} {direction}", "move the {object} {direction} by pushing it {distance}"],
    },
    "pull": {
        "train": ["pull the {object} {direction} toward the robot by {distance}",
                  "drag the {object} {distance} {direction}, closer to you",
                  "draw the {object} {direction} by {distance}", "please pull the {object} {distance} {direction}",
                  "grab the {object} and pull it {direction} by {distance}", "pull the {object} in, {distance} {direction}",
                  "use the gripper to pull the {object} {distance} {direction}",
                  "drag the {object} {direction} by {distance}",
                  "get hold of the {object} and pull it {distance} {direction}"],
        "heldout": ["bring the {object} {distance} {direction} toward yourself",
                    "tug the {object} {direction} about {distance}"],
    },
    "pick_place": {
        "train": ["pick up the {object} and put it down {distance} {direction}",
                  "move the {object} {distance} {direction} by carrying it",
                  "grasp the {object}, carry it {direction} by {distance} and place it",
                  "pick the {object} up and place it {distance} {direction}",
                  "carry the {object} {distance} {direction} and put it down",
                  "take the {object} and put it down {distance} {direction}",
                  "grab the {object} and place it {distance} {direction}",
                  "carry the {object} {direction} by {distance}",
                  "pick the {object} up, move it {distance} {direction} and let go"],
        "heldout": ["lift the {object} and set it down {distance} {direction}",
                    "relocate the {object} {direction}, {distance} away"],
    },
    "lift": {
        "train": ["pick up the {object} and lift it {distance}", "lift the {object} {distance} up and hold it",
                  "grasp the {object} and raise it by {distance}",
                  "lift up the {object} by {distance}", "take the {object} and hold it {distance} above the table",
                  "grab the {object} and lift it up {distance}",
                  "pick the {object} up {distance} and hold it there", "grasp the {object} and hold it {distance} up",
                  "lift the {object} by {distance}"],
        "heldout": ["raise the {object} {distance} off the table", "hold the {object} up in the air, {distance} high"],
    },
    "stack": {
        "train": ["stack the {object} on the {other}", "put the {object} on top of the {other}",
                  "place the {object} onto the {other}", "pick up the {object} and stack it on the {other}",
                  "the {object} goes on top of the {other}", "move the {object} onto the {other}",
                  "put the {object} onto the {other}", "place the {object} on top of the {other}",
                  "pick up the {object} and put it on the {other}"],
        "heldout": ["set the {object} on the {other}", "build a tower: the {object} on the {other}"],
    },
    "hover": {
        "train": ["move the gripper above the {object} without touching anything",
                  "hover over the {object}", "bring the hand just above the {object} and wait",
                  "hold the gripper over the {object} without contact", "move the hand over the {object} and stop there",
                  "hover above the {object} without touching it",
                  "hover the gripper above the {object}", "bring the gripper over the {object} and hold it there",
                  "keep the hand above the {object} without contact"],
        "heldout": ["position the gripper over the {object}", "go above the {object} but do not touch it"],
    },
    "reach": {
        "train": ["move the gripper to the {place} without touching anything", "reach out to the {place} side",
                  "move the arm over to the {place}", "move the hand to the {place}",
                  "reach to the {place} without touching anything", "put the gripper out to the {place} side",
                  "reach over to the {place}", "bring the gripper over to the {place} side",
                  "extend the arm to the {place}",
                  "go to the {place} with the gripper"],
        "heldout": ["swing the gripper to the {place}", "point the hand to the {place} side of the table"],
    },
    "keep_still": {
        "train": ["do nothing and keep the arm still", "stay still", "keep the robot where it is", "keep still",
                  "stay where you are", "don't touch anything", "wait without moving", "stand still",
                  "keep the arm and the objects as they are"],
        "heldout": ["don't move", "hold your position and leave everything as it is"],
    },
}


def describe(shape: str, color: str) -> str:
    """'green' + 'cylinder' -> 'green cylinder' (the words that identify an object)."""
    return f"{color} {shape}".strip()


def distance_words(distance_m: float) -> str:
    return f"{round(distance_m * 100):d} cm"


def skill_attributes(intent: dict, descriptions: dict[str, str]) -> dict:
    """The words of an intent (see datagen.skills.commanded_intent): object, other, direction,
    distance, place. descriptions: object name -> 'green cylinder'."""
    cmd = np.asarray(intent["commanded_displacement_world_m"], np.float64)
    attrs = {
        "object": descriptions.get(intent["target"], "") if intent["target"] else "",
        "other": descriptions.get(intent["other"], "") if intent["other"] else "",
        "direction": direction_words(cmd[:2]) if intent["skill"] in ("push", "pull", "pick_place") else "",
        "distance": distance_words(intent["distance_m"]) if intent["distance_m"] else "",
        "place": intent["direction"] if intent["skill"] == "reach" else "",
    }
    return attrs


def make_skill_instruction(skill: str, attributes: dict, rng: np.random.Generator, split: str = "train") -> str:
    """One paraphrase of ``split`` for ``skill`` chosen by ``rng``, filled with ``attributes``."""
    if split not in SPLITS:
        raise UserError(f"instruction split must be one of {SPLITS}, got {split!r}")
    templates = TEMPLATES[skill][split]
    text = templates[int(rng.integers(len(templates)))].format(**attributes)
    return " ".join(text.split())
