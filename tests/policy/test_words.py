"""The words parser on every training phrasing of the skills and of the tasks the plan arms run."""

from __future__ import annotations

import numpy as np
import pytest

from datagen.instructions import TEMPLATES as TASK_TEMPLATES
from datagen.instructions import direction_words
from datagen.skill_language import TEMPLATES as SKILL_TEMPLATES
from tesseract4d.policy.words import DEFAULT_DISTANCE_M, parse_instruction

CASES = [  # (commanded xy, distance words)
    ((0.1, 0.0), "10 cm"), ((0.0, 0.12), "12 cm"), ((0.0, -0.1), "10 cm"), ((-0.1, 0.0), "10 cm"),
]


def skill_phrasings():
    for skill, splits in SKILL_TEMPLATES.items():
        for template in splits["train"]:
            for cmd, dist in CASES:
                if skill == "pull" and cmd[0] >= 0:
                    continue
                attrs = {"object": "green cylinder", "other": "blue cube", "direction": direction_words(np.array(cmd)),
                         "distance": dist, "place": "left" if cmd[1] >= 0 else "right"}
                yield skill, template, cmd, dist, " ".join(template.format(**attrs).split())


@pytest.mark.parametrize("skill,template,cmd,dist,text", list(skill_phrasings()))
def test_every_training_phrasing_of_the_skills_parses_to_its_skill_object_direction_and_distance(skill, template, cmd, dist, text):
    p = parse_instruction(text)
    assert p.skill == skill, text
    if "{object}" in template:
        assert (p.object_colour, p.object_shape) == ("green", "cylinder"), text
    if "{other}" in template:
        assert (p.other_colour, p.other_shape) == ("blue", "cube"), text
    if "{direction}" in template:
        np.testing.assert_allclose(p.direction_xy, np.asarray(cmd) / np.linalg.norm(cmd), atol=1e-9, err_msg=text)
    if "{distance}" in template:
        assert p.distance_m == pytest.approx(int(dist.split()[0]) / 100), text
    if "{place}" in template:
        assert p.place == ("left" if cmd[1] >= 0 else "right"), text


TASK_SKILL = {"PushCube-v1": "push", "PullCube-v1": "pull", "PickCube-v1": "lift", "StackCube-v1": "stack"}


def task_phrasings():
    for task, skill in TASK_SKILL.items():
        for template in TASK_TEMPLATES[task]["train"]:
            for d in ("forward", "to the left", "back and to the right", ""):
                if task == "PullCube-v1" and d in ("forward", "to the left"):
                    continue
                attrs = {"color": "red", "color2": "green", "direction": d, "height": "up", "side": ""}
                yield task, skill, template, d, " ".join(template.format(**attrs).split())


@pytest.mark.parametrize("task,skill,template,d,text", list(task_phrasings()))
def test_every_training_phrasing_of_the_cube_tasks_parses_to_the_tasks_skill(task, skill, template, d, text):
    p = parse_instruction(text)
    assert p.skill == skill, text
    assert p.object_colour == "red", text
    if skill == "stack":
        assert p.other_colour == "green", text
    if "{direction}" in template and d and skill in ("push", "pull"):
        want = {"forward": (1, 0), "to the left": (0, 1), "back and to the right": (-1, -1)}[d]
        np.testing.assert_allclose(p.direction_xy, np.asarray(want) / np.linalg.norm(want), atol=1e-9, err_msg=text)
    if skill in ("push", "pull"):
        assert p.distance_m is None and p.travel_m() == DEFAULT_DISTANCE_M  # the words say no distance


def test_words_no_rule_knows_leave_the_skill_unknown():
    assert parse_instruction("make it so").skill is None
