"""The tabletop's skills as rollout tasks: per held-out seed one commanded skill, its words and its
success check.

The tabletop scene (``datagen.tabletop``) has no task of its own: the rollout gives each seed one of the
skills push, pull, pick-and-place, lift and stack in turn (seed modulo 5; another skill when the scene
has no feasible target for it), a variant and target drawn from the seed (``datagen.skills.candidates``),
the instruction written by ``datagen.counterfactual.skill_instruction`` in the rollout's instruction
split, and success judged by ``datagen.skills.check_intent`` on the simulator's object poses (the
evaluation's reading, never the arm's).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from datagen import skills as sk
from datagen.counterfactual import skill_instruction

ROLLOUT_SKILLS = ("push", "pull", "pick_place", "lift", "stack")
_STREAM = 16180


@dataclass
class SkillTask:
    variant: sk.SkillVariant
    target: str | None
    other: str | None
    instruction: str
    intent: dict


def skill_task(sim, seed: int) -> SkillTask:
    """The commanded skill of ``seed`` in the tabletop simulator ``sim`` (its env reset to the seed)."""

    env_id, base = sim.env_id, sim.env.unwrapped
    sim.fresh_scene(seed)
    rng = np.random.default_rng([int(seed), _STREAM])
    first = int(seed) % len(ROLLOUT_SKILLS)
    for skill in ROLLOUT_SKILLS[first:] + ROLLOUT_SKILLS[:first]:
        names = [v.name for v in sk.VARIANTS.values() if v.skill == skill]
        for name in rng.permutation(names):
            variant = sk.VARIANTS[str(name)]
            cands = sk.candidates(env_id, base, variant)
            if not cands:
                continue
            target, other = cands[int(rng.integers(len(cands)))]
            intent = sk.commanded_intent(env_id, base, variant, target, other)
            text, _ = skill_instruction(env_id, variant, intent, sk.object_colors(env_id, base), seed,
                                        sim.config.instruction_split)
            return SkillTask(variant, target, other, text, intent)
    raise RuntimeError(f"no skill has a feasible target in {env_id} seed {seed}")


def success_check(sim, task: SkillTask):
    """A function that says whether ``task`` is done now (call it after reset to ``task``'s seed: the
    start poses are read at this call)."""
    env_id, base = sim.env_id, sim.env.unwrapped
    present = task.intent["objects_present"]
    start = {n: sk.object_positions(env_id, base)[n] for n in present}
    tcp_start = sk.tcp_position(base)

    def done() -> bool:
        end = {n: sk.object_positions(env_id, base)[n] for n in present}
        out = sk.check_intent(task.intent, start, end, tcp_start, sk.tcp_position(base),
                              sk.is_grasping(env_id, base, task.target))
        return bool(out["success"])

    return done
