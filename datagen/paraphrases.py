"""Other training wordings of an instruction the datagen wrote (for rephrasing at training time).

An instruction of a ``train`` template (``datagen.instructions.TEMPLATES`` for the tasks,
``datagen.skill_language.TEMPLATES`` for the skills) is parsed back into its template's fields
(object, direction, distance, ...), and every ``train`` template of the same task or skill that uses
only those fields is filled with them. The words that tell one future from another (the object,
the direction, how far) stay; only the wording changes. ``heldout`` templates are never parsed nor
written, so rephrasing never shows the model a held-out phrasing.

    >>> train_paraphrases("stay still")[:3]
    ['do nothing and keep the arm still', 'stay still', 'keep the robot where it is']

An instruction no train template writes (a held-out phrasing, a user's own words) has only itself.
"""

from __future__ import annotations

import functools
import itertools
import re
from string import Formatter

import numpy as np

from datagen import instructions, skill_language, skills

# What each field's words can be: the datagen's own word functions over every case (so a word added
# there is parsed here), the names of things loosely.
_DIRECTIONS = ({instructions.direction_words(np.array(v, float)) for v in itertools.product((-1, 0, 1), repeat=2)}
               | {"back toward the robot", "right where it is"})  # PullCubeTool's and _sentence_direction's
_NAME = r"[a-z]+(?: [a-z]+)?"  # 'red', 'green cylinder'


def _alternatives(words) -> str:
    return "|".join(map(re.escape, sorted(set(words), key=len, reverse=True)))


FIELD_PATTERNS: dict[str, str] = {
    "object": _NAME, "other": _NAME, "color": r"[a-z]+", "color2": r"[a-z]+",
    "direction": _alternatives(_DIRECTIONS),
    "distance": r"\d+ cm",
    "height": _alternatives(instructions.height_words(dz) for dz in (0.0, 0.1, 0.3)),
    "side": _alternatives(instructions.side_words(np.array([0.0, y])) for y in (-1.0, 0.0, 1.0)),
    "place": _alternatives(skills.PLACES),
}


def _fields(template: str) -> list[str]:
    return [f for _, f, _, _ in Formatter().parse(template) if f]


def _fill(template: str, values: dict[str, str]) -> str:
    """As the datagen writes it: fields filled, runs of spaces (an empty field's) collapsed."""
    return " ".join(template.format(**values).split())


@functools.lru_cache(maxsize=None)
def _patterns() -> list[tuple[tuple[str, ...], re.Pattern, dict[str, str]]]:
    """One pattern per train template and set of fields it may leave empty."""
    out = []  # (the family's train templates, pattern, the fields it leaves empty)
    families = {**instructions.TEMPLATES, **skill_language.TEMPLATES}
    for splits in families.values():
        train = tuple(splits["train"])
        for template in train:
            fields = _fields(template)
            for n_empty in range(len(fields) + 1):
                for empty in itertools.combinations(fields, n_empty):
                    marks = {f: "" if f in empty else f"\x00{f}\x00" for f in fields}
                    regex = re.escape(_fill(template, marks))
                    for f in fields:
                        if f not in empty:
                            regex = regex.replace(re.escape(marks[f]), f"(?P<{f}>{FIELD_PATTERNS[f]})", 1)
                    out.append((train, re.compile(regex), dict.fromkeys(empty, "")))
    return out


@functools.lru_cache(maxsize=65536)
def _paraphrases(instruction: str) -> tuple[str, ...]:
    # The readings with the fewest empty fields win: "stack the red cube on the green cube" is a stack
    # without a direction, not one whose direction was left out.
    readings = []
    for train, pattern, empty in _patterns():
        m = pattern.fullmatch(instruction)
        if m is not None:
            readings.append((len(empty), train, {**empty, **m.groupdict()}))
    fewest = min((n for n, _, _ in readings), default=0)
    found: dict[str, None] = {}
    for n, train, values in readings:
        for template in train if n == fewest else ():
            if set(_fields(template)) <= set(values):
                found.setdefault(_fill(template, values))
    return tuple(found) if instruction in found else (instruction,)


def train_paraphrases(instruction: str) -> list[str]:
    """Every train wording of ``instruction``'s meaning, itself included (first when nothing parses)."""
    return list(_paraphrases(" ".join(instruction.split())))
