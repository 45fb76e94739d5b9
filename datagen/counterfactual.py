"""Counterfactual groups: one initial state, K futures decided by the instruction.

``run_group`` resets the env with the same seed before each future, so every future starts
from the same simulator state; it runs K *distinct* skill variants (``datagen.skills``), in an
order drawn from the seed, trying the feasible target objects of a variant until one succeeds
and moving on to the next variant when none does. Only successful futures are rendered. The
first frames of the K episodes are compared bit for bit (RGB, depth, normals, segmentation);
a difference is a determinism bug and raises.

``commanded_future`` gives the words and intent a group would give one skill in a scene without
running it (the demo's instructions come from it).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from datagen import skills as sk
from datagen.simulate import INSTRUCTION_STREAM, EpisodeSimulator, frame_indices
from tesseract4d.dataset_format import Episode
from tesseract4d.errors import UserError
from datagen.skill_language import describe, make_skill_instruction, skill_attributes

PLANNER = "datagen.skills on mani_skill.examples.motionplanning.panda PandaArmMotionPlanningSolver"


@dataclass
class GroupResult:
    """What one (task, seed) group did; the episodes only when all K futures succeeded."""

    env_id: str
    seed: int
    success: bool
    k: int
    num_steps: int = 0
    num_frames: int = 0
    plan_s: float = 0.0
    render_s: float = 0.0
    error: str = ""
    tries: list[dict] = field(default_factory=list)  # every (variant, target) tried: outcome, error
    episodes: list[Episode] = field(default_factory=list)


def run_group(sim: EpisodeSimulator, seed: int, k: int, specs: list[str] | None = None) -> GroupResult:
    """Plan and render K futures of the scene of ``seed`` (see the module docstring).

    specs: skill specs from ``skills.parse_skill_list`` (None = every variant that applies).
    """
    env_id, env = sim.env_id, sim.env
    base = env.unwrapped
    names = sk.available_variants(env_id, specs)
    pinned = {s.partition("@")[0]: s.partition("@")[2] or None for s in (specs or [])}
    rng = np.random.default_rng([int(seed), 271828])
    result = GroupResult(env_id, seed, False, k)
    first: Episode | None = None
    for name in rng.permutation(names):
        if len(result.episodes) == k:
            break
        variant = sk.VARIANTS[str(name)]
        env.reset(seed=seed)
        cands = sk.candidates(env_id, base, variant, pinned.get(variant.name))
        if not cands:
            result.tries.append({"variant": variant.name, "target": None, "success": False,
                                 "error": "no feasible target in this scene"})
            continue
        for i in rng.permutation(len(cands)):
            target, other = cands[int(i)]
            episode = _try(sim, seed, variant, target, other, result, variant_index=len(result.episodes), k=k)
            if episode is None:
                continue
            if first is None:
                first = episode
            else:
                _assert_same_first_frame(first, episode)
            result.episodes.append(episode)
            break
    result.success = len(result.episodes) == k
    if not result.success:
        result.error = f"only {len(result.episodes)} of {k} skills succeeded"
        result.episodes = []
    result.num_frames = sum(e.num_frames for e in result.episodes)
    return result


def _try(sim: EpisodeSimulator, seed: int, variant: sk.SkillVariant, target, other, result: GroupResult,
         variant_index: int, k: int) -> Episode | None:
    env_id, env = sim.env_id, sim.env
    base = env.unwrapped
    sim.fresh_scene(seed)  # each future from a rebuilt scene: it depends on nothing simulated before it
    intent = sk.commanded_intent(env_id, base, variant, target, other)
    present = intent["objects_present"]
    start = {n: sk.object_positions(env_id, base)[n] for n in present}
    tcp_start = sk.tcp_position(base)
    t0 = time.perf_counter()
    record = {"variant": variant.name, "target": target, "other": other}
    try:
        sk.execute(env, env_id, variant, target, other)
    except sk.SkillFailure as e:
        error = str(e)
    except Exception as e:  # the planner raises on unreachable poses: a failed try, reported
        error = f"planner error: {type(e).__name__}: {e}"
    else:
        error = ""
    plan_s = time.perf_counter() - t0
    result.plan_s += plan_s
    result.num_steps += len(env.actions)
    if error:
        result.tries.append(dict(record, success=False, error=error))
        return None
    end = {n: sk.object_positions(env_id, base)[n] for n in present}
    outcome = sk.check_intent(intent, start, end, tcp_start, sk.tcp_position(base), sk.is_grasping(env_id, base, target))
    result.tries.append(dict(record, success=outcome["success"], error="" if outcome["success"] else "success check failed"))
    if not outcome["success"]:
        return None
    intent.update(outcome)
    states, actions = list(env.states), np.stack(env.actions)
    keep = frame_indices(len(states), sim.config.frames)
    scene_colors = dict(base.object_colors) if env_id == sk.TABLETOP_ID else None

    def language(appearance_colors: dict) -> tuple[str, dict]:
        colors = scene_colors if scene_colors is not None else sk.object_colors(env_id, base, appearance_colors)
        return skill_instruction(env_id, variant, intent, colors, seed, sim.config.instruction_split)

    t1 = time.perf_counter()
    episode = sim._render(seed, [states[i] for i in keep], keep, actions, success=True, language=language,
                          variant=variant_index, intent=intent)
    result.render_s += time.perf_counter() - t1
    episode.metadata.update({"num_sim_steps": len(actions), "plan_seconds": round(plan_s, 3), "planner": PLANNER,
                             "group_size": k})
    return episode


def run_skill(sim: EpisodeSimulator, seed: int, variant: sk.SkillVariant, target, other) -> tuple[Episode | None, dict]:
    """Plan and, when it succeeds, render one skill in the scene of ``seed`` (as one future of a group):
    the episode (None on failure) and what the try did (variant, target, other, success, error, steps)."""
    result = GroupResult(sim.env_id, seed, False, 1)
    episode = _try(sim, seed, variant, target, other, result, variant_index=0, k=1)
    return episode, dict(result.tries[-1], num_steps=result.num_steps, plan_s=round(result.plan_s, 3))


def skill_instruction(env_id: str, variant: sk.SkillVariant, intent: dict, colors: dict[str, str], seed: int,
                      split: str) -> tuple[str, dict]:
    """The instruction of one future of a group and the attributes it was written from.

    intent: from ``skills.commanded_intent``; colors: object name -> colour name. The paraphrase
    of ``split`` is drawn from the stream (seed, INSTRUCTION_STREAM, variant index), so a scene's
    future under a variant always gets the same words.
    """
    shapes = {o.name: o.shape for o in sk.SCENES[env_id]}
    descriptions = {n: describe(shapes[n], colors.get(n, "")) for n in intent["objects_present"]}
    attrs = skill_attributes(intent, descriptions)
    idx = list(sk.VARIANTS).index(variant.name)
    text = make_skill_instruction(variant.skill, attrs, np.random.default_rng([int(seed), INSTRUCTION_STREAM, idx]),
                                  split=split)
    return text, dict(attrs, object_colors=colors)


def commanded_future(sim: EpisodeSimulator, seed: int, spec: str) -> tuple[str, dict]:
    """The instruction and structured intent that a group gives skill ``spec`` (``VARIANT`` or
    ``VARIANT@OBJECT``, see ``skills.parse_skill_list``) in the scene of ``seed``, without running
    it: nothing is planned or rendered. The target is the first feasible object of the scene
    (``skills.candidates``, in the scene's object order) unless ``spec`` pins one.

    Raises UserError when the variant has no feasible target in this scene.
    """
    env_id, env = sim.env_id, sim.env
    base = env.unwrapped
    name, _, pinned = spec.partition("@")
    variant = sk.VARIANTS[name]
    env.reset(seed=seed)
    cands = sk.candidates(env_id, base, variant, pinned or None)
    if not cands:
        feasible = [v for v in sk.available_variants(env_id, None) if sk.candidates(env_id, base, sk.VARIANTS[v])]
        raise UserError(f"skill {spec!r} has no feasible target in {env_id} seed {seed}; choose one of "
                        f"{', '.join(feasible)} or another seed")
    target, other = cands[0]
    intent = sk.commanded_intent(env_id, base, variant, target, other)
    text, _ = skill_instruction(env_id, variant, intent, sk.object_colors(env_id, base), seed, sim.config.instruction_split)
    return text, intent


def _assert_same_first_frame(a: Episode, b: Episode) -> None:
    for name, cam in a.cameras.items():
        other = b.cameras[name]
        for key in ("rgb", "depth_m", "normal_cam", "segmentation"):
            x, y = getattr(cam, key), getattr(other, key)
            if x is None and y is None:
                continue
            if not np.array_equal(x[0], y[0]):
                raise RuntimeError(f"{a.group_id}: first frames of futures {a.variant} and {b.variant} differ in "
                                   f"{name}/{key}; the simulator or renderer is not deterministic across resets")
