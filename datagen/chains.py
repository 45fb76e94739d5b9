"""Chained episodes: 2-4 skills in a row in one tabletop scene, one instruction per segment.

``run_chain`` rebuilds the scene of ``seed`` and runs ``n`` skills one after another from where the
last one left the scene ("push the red cube left, then lift the blue cylinder"). Each segment's
skill variant and target are drawn from the seed among the variants that are feasible in the scene
as it is then (``skills.candidates``); the variants of one chain are distinct, and a skill that ends
holding its object (lift) comes only last. Each segment is judged by ``skills.check_intent`` from
the object positions at its own start and end; one failed segment fails the chain (the seed is
logged as failed, like a failed plan). Nothing is random but the seed: a chain is the same on every
run, in any process.

Frames: the episode keeps ``frames`` frames in all (``SimConfig.frames``; 0 = every step), split
evenly over the segments (``instruction_schedule.segment_boundaries``), and each segment's frames are
spread evenly over its own simulator steps, so every segment plays at the pace of a one-skill
episode whatever its length in steps. The schedule (each segment's words, intent, frame and step
range) is stored in ``metadata["instruction_schedule"]``; ``instruction`` is the segments' words
joined by ", then ". Words come from the ``instruction_split`` paraphrases (held-out wordings for
evaluation sets).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from datagen import skills as sk
from datagen.simulate import INSTRUCTION_STREAM, EpisodeSimulator, frame_indices
from datagen.skill_language import describe, make_skill_instruction, skill_attributes
from tesseract4d.dataset_format import Episode
from tesseract4d.errors import UserError
from tesseract4d.instruction_schedule import SCHEDULE_KEY, Segment, chained_instruction, segment_boundaries

MIN_SKILLS, MAX_SKILLS = 2, 4
CHAIN_STREAM = 577215  # the seed's random stream for the chain's choices (independent of the others)
HOLDING_SKILLS = ("lift",)  # end with the object in the gripper: nothing can follow them
PLANNER = "datagen.chains on datagen.skills (mani_skill PandaArmMotionPlanningSolver)"


@dataclass
class ChainResult:
    """What one chained attempt did; the episode only when every segment succeeded."""

    env_id: str
    seed: int
    success: bool
    k: int  # segments asked for
    num_steps: int = 0
    num_frames: int = 0
    plan_s: float = 0.0
    render_s: float = 0.0
    error: str = ""
    tries: list[dict] = field(default_factory=list)  # one per segment run: variant, target, outcome
    episodes: list[Episode] = field(default_factory=list)


def check_chain(n: int, env_ids: list[str], frames: int, specs: list[str] | None) -> None:
    """Refuse a chain length, task or frame count that cannot make chained episodes, with the fix."""
    if not MIN_SKILLS <= n <= MAX_SKILLS:
        raise UserError(f"chain_skills must be {MIN_SKILLS} to {MAX_SKILLS} skills in a row (0: no chains), got {n}")
    others = [t for t in env_ids if t != sk.TABLETOP_ID]
    if others:
        raise UserError(f"chained episodes run in the tabletop scene only; use --tasks {sk.TABLETOP_ID} "
                        f"(not {', '.join(others)})")
    if frames:
        segment_boundaries(frames, n)
    pool = chain_pool(specs)
    if len(pool) < n:
        raise UserError(f"chain_skills={n} needs {n} distinct skills but --skills gives {len(pool)}: {', '.join(pool)}")


def chain_pool(specs: list[str] | None) -> list[str]:
    """The variants a chain draws from: --skills' (default: all that move something; keep_still is
    left out, it adds nothing a chain can show)."""
    names = sk.available_variants(sk.TABLETOP_ID, specs)
    return names if specs is not None else [v for v in names if sk.VARIANTS[v].skill != "keep_still"]


def run_chain(sim: EpisodeSimulator, seed: int, n: int, specs: list[str] | None = None) -> ChainResult:
    """Plan ``n`` skills in a row in the scene of ``seed`` and render the chained episode (see the
    module docstring). specs: skill specs from ``skills.parse_skill_list`` (None = the default pool)."""
    env_id, env = sim.env_id, sim.env
    base = env.unwrapped
    check_chain(n, [env_id], sim.config.frames, specs)
    pinned = {s.partition("@")[0]: s.partition("@")[2] or None for s in (specs or [])}
    rng = np.random.default_rng([int(seed), CHAIN_STREAM])
    result = ChainResult(env_id, seed, False, n)
    sim.fresh_scene(seed)  # depends on nothing this process simulated before
    used: list[str] = []
    step_bounds = [0]
    intents: list[dict] = []
    t0 = time.perf_counter()
    for i in range(n):
        last = i == n - 1
        choice = None
        for name in rng.permutation(chain_pool(specs)):
            variant = sk.VARIANTS[str(name)]
            if variant.name in used or (not last and variant.skill in HOLDING_SKILLS):
                continue
            cands = sk.candidates(env_id, base, variant, pinned.get(variant.name))
            if cands:
                choice = (variant, *cands[int(rng.integers(len(cands)))])
                break
        if choice is None:
            result.error = f"no feasible skill for segment {i + 1} of {n}"
            break
        variant, target, other = choice
        used.append(variant.name)
        outcome = _run_segment(env, env_id, variant, target, other)
        result.tries.append({"variant": variant.name, "target": target, "other": other, "segment": i,
                             "success": outcome["success"], "error": outcome.get("error", "")})
        if not outcome["success"]:
            result.error = f"segment {i + 1} of {n} ({variant.name}): {outcome.get('error') or 'success check failed'}"
            break
        intents.append(outcome["intent"])
        step_bounds.append(len(env.actions))
    result.plan_s = time.perf_counter() - t0
    result.num_steps = len(env.actions)
    if len(intents) < n:
        return result
    try:
        keep, frame_bounds = chain_frames(step_bounds, sim.config.frames)
    except UserError as e:
        result.error = str(e)
        return result
    t1 = time.perf_counter()
    episode = _render(sim, seed, intents, step_bounds, keep, frame_bounds)
    result.render_s = time.perf_counter() - t1
    episode.metadata.update({"num_sim_steps": len(env.actions), "plan_seconds": round(result.plan_s, 3),
                             "planner": PLANNER, "chain_skills": n})
    result.episodes = [episode]
    result.num_frames = episode.num_frames
    result.success = True
    return result


def _run_segment(env, env_id: str, variant: sk.SkillVariant, target, other) -> dict:
    """Execute one skill from the scene as it is and judge it from its own start and end."""
    base = env.unwrapped
    intent = sk.commanded_intent(env_id, base, variant, target, other)
    present = intent["objects_present"]
    start = {name: sk.object_positions(env_id, base)[name] for name in present}
    tcp_start = sk.tcp_position(base)
    try:
        sk.execute(env, env_id, variant, target, other)
    except sk.SkillFailure as e:
        return {"success": False, "error": str(e)}
    except Exception as e:  # the planner raises on unreachable poses: a failed segment, reported
        return {"success": False, "error": f"planner error: {type(e).__name__}: {e}"}
    end = {name: sk.object_positions(env_id, base)[name] for name in present}
    judged = sk.check_intent(intent, start, end, tcp_start, sk.tcp_position(base),
                             sk.is_grasping(env_id, base, target))
    intent.update(judged)
    return {"success": judged["success"], "intent": intent}


def chain_frames(step_bounds: list[int], frames: int) -> tuple[np.ndarray, list[int]]:
    """The simulator states kept as frames and the frame where each segment starts and ends.

    step_bounds: the step where each segment starts, then the last step (n + 1 values; state s is
    the state after s steps). frames: frames in all (0 = every state). Returns ((T,) strictly
    increasing state indices, n + 1 frame boundaries)."""
    n = len(step_bounds) - 1
    if frames <= 0:
        return np.arange(step_bounds[-1] + 1), list(step_bounds)
    frame_bounds = segment_boundaries(frames, n)
    keep = [0]
    for i in range(n):
        count = frame_bounds[i + 1] - frame_bounds[i] + 1
        steps = step_bounds[i + 1] - step_bounds[i] + 1
        idx = frame_indices(steps, count)
        if len(idx) < count:
            raise UserError(f"segment {i + 1} has {steps} simulator states for {count} frames; keep fewer --frames")
        keep += list(step_bounds[i] + idx[1:])
    return np.asarray(keep, np.int64), frame_bounds


def _render(sim: EpisodeSimulator, seed: int, intents: list[dict], step_bounds: list[int], keep: np.ndarray,
            frame_bounds: list[int]) -> Episode:
    env = sim.env
    base = env.unwrapped
    colors = dict(base.object_colors)
    shapes = {o.name: o.shape for o in sk.SCENES[sim.env_id]}
    texts, attributes = [], []
    for i, intent in enumerate(intents):
        descriptions = {name: describe(shapes[name], colors.get(name, "")) for name in intent["objects_present"]}
        attrs = skill_attributes(intent, descriptions)
        rng = np.random.default_rng([int(seed), INSTRUCTION_STREAM, CHAIN_STREAM, i])
        texts.append(make_skill_instruction(intent["skill"], attrs, rng, split=sim.config.instruction_split))
        attributes.append(attrs)

    def language(_appearance_colors: dict) -> tuple[str, dict]:
        return chained_instruction(texts), {"object_colors": colors, "segments": attributes}

    states = [env.states[i] for i in keep]
    episode = sim._render(seed, states, keep, np.stack(env.actions), success=True, language=language)
    schedule = [Segment(texts[i], frame_bounds[i], frame_bounds[i + 1], intents[i], step_bounds[i], step_bounds[i + 1])
                for i in range(len(intents))]
    episode.metadata[SCHEDULE_KEY] = [s.to_dict() for s in schedule]
    return episode
