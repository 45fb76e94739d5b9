"""Does a model keep still under every way of saying "keep still"? A probe of language generalisation.

Every scene of a held-out dataset of counterfactual groups (``datagen --instructions-per-scene``) is
predicted from its first frame under each phrasing of the skill library's ``keep_still`` skill (the
training paraphrases and the held-out ones, or --phrase ...), once per noise seed, with the noise
``evaluate --heldout`` gives that scene. A clip keeps still when its motion (mean |RGB change| from
its first predicted frame, as ``evaluate``'s instruction contrast measures it) is at most 10 % of
the mean motion of the scene's true active futures (the group's episodes whose skill moves an
object; contrast's "active instructions"). ``evaluate --heldout`` judges "keep still" only under
the one phrasing each group was generated with; this asks every phrasing in every scene.

  .venv/bin/python scripts/still_phrasings.py --heldout data/heldout_groups128 \\
      --checkpoint tesseract4d/checkpoints/v2 tesseract4d/checkpoints/v2-2step --sample-seed 0 1
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))


def keep_still_phrasings() -> list[tuple[str, str]]:
    """(phrase, split) for every keep-still paraphrase of the skill library."""
    from datagen.skill_language import TEMPLATES

    return [(p, split) for split in ("train", "heldout") for p in TEMPLATES["keep_still"][split]]


def scenes(heldout: Path, max_scenes: int | None) -> list[dict]:
    """One entry per scene (environment and seed): its first frame, camera and still threshold."""
    import numpy as np

    from tesseract4d import dataset_format as df
    from tesseract4d.errors import UserError
    from tesseract4d.evaluation.believability import STILL_SHARE
    from tesseract4d.evaluation.heldout_believability import GRIPPER_ONLY_SKILLS, clip_motion

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
    import numpy as np

    from tesseract4d.evaluation.heldout import predict_at_data_resolution, scene_noise_seed
    from tesseract4d.evaluation.heldout_believability import clip_motion
    from tesseract4d.model.predict import load_pipeline

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


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--heldout", type=Path, required=True, help="held-out dataset of counterfactual groups")
    parser.add_argument("--checkpoint", type=Path, nargs="+", default=None,
                        help="inference checkpoint(s) (default: the shipped default)")
    parser.add_argument("--sample-seed", type=int, nargs="+", default=[0], help="noise seeds, as evaluate's (default 0)")
    parser.add_argument("--phrase", nargs="+", default=None,
                        help="phrasings to ask (default: every keep-still paraphrase of the skill library)")
    parser.add_argument("--max-scenes", type=int, default=None, help="scenes at most (default: all)")
    parser.add_argument("--precision", choices=["auto", "fp32", "bf16"], default="auto")
    parser.add_argument("--json", type=Path, default=None, help="also write the per-clip numbers here (a new file)")
    args = parser.parse_args(argv)

    from tesseract4d import runtime
    from tesseract4d.errors import UserError
    from tesseract4d.evaluation.believability import STILL_SHARE
    from tesseract4d.model.checkpoint import SHIPPED_CHECKPOINT

    runtime.configure()
    try:
        if args.json is not None and args.json.exists():
            raise UserError(f"{args.json} exists; give a new file for --json")
        if not (args.heldout / "episodes").is_dir():
            raise UserError(f"{args.heldout} is not a dataset folder (no episodes/); make one with `tesseract4d datagen`")
        phrasings = [(p, "given") for p in args.phrase] if args.phrase else keep_still_phrasings()
        scene_list = scenes(args.heldout, args.max_scenes)
        checkpoints = args.checkpoint or [SHIPPED_CHECKPOINT]
        report = {str(c): probe(c, scene_list, phrasings, args.sample_seed, args.precision) for c in checkpoints}
    except UserError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    print(f"\n{len(scene_list)} scenes x {len(args.sample_seed)} noise seeds; a clip keeps still at motion <= "
          f"{STILL_SHARE:.0%} of its scene's true active futures' (limits {min(s['limit'] for s in scene_list):.2f}-"
          f"{max(s['limit'] for s in scene_list):.2f})\n")
    print("| phrasing | split | " + " | ".join(f"{c}: still / median motion" for c in report) + " |")
    print("|---|---|" + "---|" * len(report))
    for phrase, split in phrasings:
        cells = [f"{r[phrase]['still']} / {r[phrase]['clips']}, {statistics.median(r[phrase]['motion']):.2f}"
                 for r in report.values()]
        print(f"| {phrase} | {split} | " + " | ".join(cells) + " |")
    if args.json is not None:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        part = args.json.with_name(args.json.name + ".part")  # never a half-written report
        part.write_text(json.dumps(report, indent=1))
        part.replace(args.json)
    return 0


if __name__ == "__main__":
    sys.exit(main())
