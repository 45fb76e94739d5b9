"""Does a model keep still under every way of saying "keep still"? A probe of language generalisation.

Every scene of a held-out dataset of counterfactual groups (``datagen --instructions-per-scene``) is
predicted from its first frame under each phrasing of the skill library's ``keep_still`` skill (the
training paraphrases and the held-out ones, or --phrase ...), once per noise seed, with the noise
``evaluate --heldout`` gives that scene. A clip keeps still when its motion (mean |RGB change| from
its first predicted frame, as ``evaluate``'s instruction contrast measures it) is at most 10 % of
the mean motion of the scene's true active futures (the group's episodes whose skill moves an
object; contrast's "active instructions"). ``evaluate --heldout`` judges "keep still" only under
the one phrasing each group was generated with; this asks every phrasing in every scene.

  tesseract4d research phrasings --heldout data/heldout_groups128 \\
      --checkpoint tesseract4d/checkpoints/v2 tesseract4d/checkpoints/v2-2step --sample-seed 0 1
"""

from __future__ import annotations

import json
import statistics
from pathlib import Path

import numpy as np

from datagen.skill_language import TEMPLATES
from tesseract4d import dataset_format as df
from tesseract4d.errors import UserError
from tesseract4d.evaluation.believability import STILL_SHARE
from tesseract4d.evaluation.heldout import predict_at_data_resolution, scene_noise_seed
from tesseract4d.evaluation.heldout_believability import GRIPPER_ONLY_SKILLS, clip_motion


def keep_still_phrasings() -> list[tuple[str, str]]:
    """(phrase, split) for every keep-still paraphrase of the skill library."""
    return [(p, split) for split in ("train", "heldout") for p in TEMPLATES["keep_still"][split]]


def scenes(heldout: Path, max_scenes: int | None) -> list[dict]:
    """One entry per scene (environment and seed): its first frame, camera and still threshold."""
    groups: dict[tuple[str, int], list[Path]] = {}
    for path in sorted((heldout / "episodes").glob("*/*.h5")):
        attrs = df.read_episode_attrs(path)
        groups.setdefault((path.parent.name, int(attrs["seed"])), []).append(path)
    out = []
    for (env_id, seed), paths in sorted(groups.items()):
        active = []
        for path in paths:
            ep = df.read_episode(path)
            if (ep.intent or {}).get("skill") not in ("keep_still", *GRIPPER_ONLY_SKILLS):
                active.append(clip_motion(np.asarray(next(iter(ep.cameras.values())).rgb)))
        if not active:
            continue
        first = df.read_episode(paths[0], frames=slice(0, 1))
        out.append({"env_id": env_id, "seed": seed, "first": first, "camera": next(iter(first.cameras)),
                    "limit": STILL_SHARE * float(np.mean(active))})
        if max_scenes is not None and len(out) >= max_scenes:
            break
    if not out:
        raise UserError(f"{heldout} has no scene with an active instruction; give a held-out dataset of "
                        "counterfactual groups (datagen --instructions-per-scene N --instruction-split heldout)")
    return out


def probe(checkpoint: Path, scene_list: list[dict], phrasings: list[tuple[str, str]], sample_seeds: list[int],
          precision: str = "auto") -> dict:
    """{phrase: {"split", "motion": [...], "limit": [...], "still": n, "clips": n}} for one checkpoint."""
    from tesseract4d.model.predict import load_pipeline  # deferred: torch and diffusers load only when a model runs

    pipeline = load_pipeline(checkpoint, precision=precision)
    result = {}
    for phrase, split in phrasings:
        motion, limit = [], []
        for sample_seed in sample_seeds:
            preds = predict_at_data_resolution(
                pipeline, [s["first"] for s in scene_list], [phrase] * len(scene_list),
                [s["camera"] for s in scene_list], [pipeline.num_frames] * len(scene_list), seed=sample_seed,
                num_steps=None, batch_size=None,
                noise_seeds=[scene_noise_seed(sample_seed, s["env_id"], s["seed"]) for s in scene_list])
            for s, (_, model_rgb) in zip(scene_list, preds):
                motion.append(clip_motion(np.asarray(model_rgb)))
                limit.append(s["limit"])
        still = sum(m <= lim for m, lim in zip(motion, limit))
        result[phrase] = {"split": split, "motion": motion, "limit": limit, "still": still, "clips": len(motion)}
    return result


def run_probe(heldout: Path, checkpoints: list[Path], sample_seeds: list[int], phrases: list[str] | None = None,
              json_path: Path | None = None, max_scenes: int | None = None, precision: str = "auto") -> dict:
    """Ask every phrasing (``phrases``, or every keep-still paraphrase) in every scene of ``heldout`` with
    every checkpoint; print the Markdown table; write the per-clip numbers to ``json_path`` (a new file)."""
    if json_path is not None and json_path.exists():
        raise UserError(f"{json_path} exists; give a new file for --json")
    if not (heldout / "episodes").is_dir():
        raise UserError(f"{heldout} is not a dataset folder (no episodes/); make one with `tesseract4d datagen`")
    phrasings = [(p, "given") for p in phrases] if phrases else keep_still_phrasings()
    scene_list = scenes(heldout, max_scenes)
    report = {str(c): probe(c, scene_list, phrasings, sample_seeds, precision) for c in checkpoints}
    print(f"\n{len(scene_list)} scenes x {len(sample_seeds)} noise seeds; a clip keeps still at motion <= "
          f"{STILL_SHARE:.0%} of its scene's true active futures' (limits {min(s['limit'] for s in scene_list):.2f}-"
          f"{max(s['limit'] for s in scene_list):.2f})\n")
    print("| phrasing | split | " + " | ".join(f"{c}: still / median motion" for c in report) + " |")
    print("|---|---|" + "---|" * len(report))
    for phrase, split in phrasings:
        cells = [f"{r[phrase]['still']} / {r[phrase]['clips']}, {statistics.median(r[phrase]['motion']):.2f}"
                 for r in report.values()]
        print(f"| {phrase} | {split} | " + " | ".join(cells) + " |")
    if json_path is not None:
        json_path.parent.mkdir(parents=True, exist_ok=True)
        part = json_path.with_name(json_path.name + ".part")  # never a half-written report
        part.write_text(json.dumps(report, indent=1))
        part.replace(json_path)
    return report
