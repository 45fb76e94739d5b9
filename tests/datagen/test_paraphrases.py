"""Training wordings of an instruction (datagen/paraphrases.py) and the ``rephrase`` draw that uses them
(model/recipe.py; the trainer's use of it: tests/model/test_latent_model.py)."""

from __future__ import annotations

import itertools
from string import Formatter

import pytest
import torch

from datagen import instructions, skill_language
from datagen.paraphrases import FIELD_PATTERNS, train_paraphrases
from tesseract4d.model.recipe import rephrase

SKILL_VALUES = [
    {"object": "green cylinder", "other": "red cube", "direction": "back and to the left", "distance": "12 cm",
     "place": "left"},
    {"object": "yellow cube", "other": "blue cube", "direction": "forward", "distance": "5 cm", "place": "right"},
]
TASK_VALUES = [
    {"color": "red", "color2": "green", "direction": "to the right", "height": "high", "side": "middle"},
    {"color": "cyan", "color2": "purple", "direction": "back", "height": "slightly", "side": "left"},
]


def _fields(template: str) -> list[str]:
    return [f for _, f, _, _ in Formatter().parse(template) if f]


def _fill(template: str, values: dict) -> str:
    return " ".join(template.format(**values).split())


def _families():
    for values in SKILL_VALUES:
        for kind, splits in skill_language.TEMPLATES.items():
            yield kind, splits, values
    for values in TASK_VALUES:
        for kind, splits in instructions.TEMPLATES.items():
            yield kind, splits, values


def test_every_train_wording_has_its_whole_train_family_and_no_heldout_wording():
    heldout = {_fill(t, v) for _, splits, v in _families() for t in splits["heldout"]}
    for kind, splits, values in _families():
        for template in splits["train"]:
            text = _fill(template, values)
            # Its family: the train templates that say nothing it does not (a stack without a direction
            # has no wording with one).
            family = {_fill(t, values) for t in splits["train"] if set(_fields(t)) <= set(_fields(template))}
            got = train_paraphrases(text)
            assert text in got and family <= set(got), (kind, text)
            assert not set(got) & heldout, (kind, text)


def test_a_field_the_datagen_left_empty_stays_empty():
    """PickCube's goal straight above the cube has no direction words (datagen.instructions)."""
    values = {"color": "red", "direction": "", "height": "high"}
    family = {_fill(t, values) for t in instructions.TEMPLATES["PickCube-v1"]["train"]}
    for text in family:
        assert set(train_paraphrases(text)) == family


def test_paraphrases_keep_the_words_that_decide_the_future():
    """Object, direction and distance survive every rewording (the meaning stays)."""
    values = SKILL_VALUES[0]
    for skill in ("push", "pull", "pick_place"):
        for text in train_paraphrases(_fill(skill_language.TEMPLATES[skill]["train"][0], values)):
            assert all(values[f] in text for f in ("object", "direction", "distance")), text
    for text in train_paraphrases("stack the red cube on the green cube"):
        assert text.index("red") < text.index("green"), text  # which cube goes on which


def test_keep_still_has_many_train_wordings_and_heldout_ones_stay_unseen():
    still = train_paraphrases("stay still")
    assert set(still) == set(skill_language.TEMPLATES["keep_still"]["train"]) and len(still) >= 8
    for text in skill_language.TEMPLATES["keep_still"]["heldout"] + ["push the square to the right", "  "]:
        assert train_paraphrases(text) == [" ".join(text.split())]  # nothing parses: only itself


def test_train_and_heldout_templates_stay_apart():
    for _, splits, values in _families():
        assert not {_fill(t, values) for t in splits["train"]} & {_fill(t, values) for t in splits["heldout"]}


def test_field_patterns_cover_the_datagen_vocabulary():
    import re

    import numpy as np

    for dx, dy in itertools.product((-1.0, -0.5, 0.0, 0.5, 1.0), repeat=2):
        words = instructions.direction_words(np.array([dx, dy]) * 0.1)
        assert re.fullmatch(FIELD_PATTERNS["direction"], words), words
    assert re.fullmatch(FIELD_PATTERNS["distance"], skill_language.distance_words(0.123))


def test_rephrase_draws_the_same_numbers_whatever_the_probability():
    texts = ["a", "b", "c"]
    words = {"a": ["a", "a1", "a2"], "b": ["b"], "c": ["c", "c1"]}
    assert rephrase(texts, words.get, 0.0, torch.Generator().manual_seed(0)) == texts
    seen = set()
    for seed in range(30):
        g = torch.Generator().manual_seed(seed)
        out = rephrase(texts, words.get, 1.0, g)
        assert [o in words[t] for t, o in zip(texts, out)] == [True] * 3
        seen.update(out)
        after = torch.rand(1, generator=g)
        h = torch.Generator().manual_seed(seed)
        rephrase(texts, words.get, 0.0, h)
        assert torch.equal(after, torch.rand(1, generator=h))  # same draws at any probability
    assert seen == {"a", "a1", "a2", "b", "c", "c1"}
