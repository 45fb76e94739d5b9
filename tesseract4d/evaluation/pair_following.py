"""Which distillation pairs follow their instruction: the held-out contrast check on a teacher's pairs.

A teacher's pairs (:func:`tesseract4d.model.reflow.generate_pairs`) are its clips of training scenes
under those episodes' instructions. ``tesseract4d distill --keep-following`` trains the student only on
the pairs whose teacher clip does what its words say, judged as ``evaluate --heldout`` judges a
prediction (:func:`heldout_believability.contrast_entry` on the pair's own episode, then
:func:`heldout_believability.contrast_by_group` over the pair's counterfactual group): the instructed
object found moved the commanded way (cos > 0.5), and "keep still" still beside its group's active
clips. The teacher's clip is decoded and composited with the first frame as its sampler does
(its preset's static tolerance). Pairs the check does not judge (gripper-only skills, episodes
without a recorded intent) are kept.

The scores go to the pairs folder (``reflow.FOLLOWING``): per pair its skill, whether it was judged
and right, and the indices of the pairs kept.
"""

from __future__ import annotations

from pathlib import Path

from tesseract4d.errors import UserError


def _episode_file(roots: list[Path], episode_id: str) -> Path:
    from tesseract4d import dataset_format as df

    for root in roots:
        path = Path(root) / df.EPISODES_DIR / f"{episode_id}.h5"
        if path.is_file():
            return path
    raise UserError(f"episode {episode_id} is in none of {', '.join(map(str, roots))}; score the pairs where the data "
                    f"they were made from is")


def score_pairs(folder: str | Path, teacher: str | Path, *, batch_size: int = 8, progress: bool = True) -> dict:
    """Score every pair of ``folder`` (made by the ``teacher`` checkpoint) and write the scores there.

    Returns the record written: ``{"num_pairs", "judged", "right", "kept": [pair indices],
    "per_skill": {skill: [right, judged]}, "per_pair": [{"episode", "skill", "judged", "right"}]}``."""
    import torch
    from tqdm import tqdm

    from tesseract4d import dataset_format as df
    from tesseract4d.configs import folder_list
    from tesseract4d.evaluation.heldout_believability import contrast_by_group, contrast_entry
    from tesseract4d.model.checkpoint import weights_digest
    from tesseract4d.model.clips import ClipDataset, merge_clip_datasets
    from tesseract4d.model.predict import load_pipeline
    from tesseract4d.model.reflow import ReflowPairs, pair_sources, write_following
    from tesseract4d.model.static_composite import composite_static

    pairs = ReflowPairs(folder)
    made_by = pairs.manifest.get("teacher_digest")
    if made_by != weights_digest(teacher):
        raise UserError(f"{folder} holds pairs of another teacher (weights {made_by}); pass the --teacher that made them")
    pipe = load_pipeline(teacher)
    p = pipe.preset
    roots = folder_list(pairs.manifest["data"])
    camera = pairs.camera
    data = merge_clip_datasets([ClipDataset(root, num_frames=p.num_frames, height=p.height, width=p.width,
                                            model_space=pipe.model_space, camera=camera) for root in roots])
    sources = pair_sources(pairs, data)
    del data

    entries: list[tuple[str, dict] | None] = []
    skills: list[str | None] = []
    bar = tqdm(total=len(pairs), desc="scoring pairs", unit="clip", disable=not progress)
    for i in range(0, len(pairs), batch_size):
        sl = slice(i, i + batch_size)
        first = pairs.first[sl].float()
        clips = pipe.decode(pairs.x0[sl])
        if p.static_tolerance > 0:
            clips = composite_static(clips, first, p.static_tolerance)
        for k, clip in enumerate(clips):
            episode_id, start = sources[i + k]
            path = _episode_file(roots, episode_id)
            # The check reads the episode from its frame 0: a clip cut later is not judged, and only its skill
            # is read (the file's attributes, not its frames).
            if start == 0:
                gt = df.read_episode(path, cameras=[camera])
                intent = gt.intent
                rgb, _, _ = pipe.model_space.decode(clip)
                entry = contrast_entry(gt, camera, rgb)
            else:
                intent = df.read_episode_attrs(path)["intent"]
                entry = None
            skills.append((intent or {}).get("skill"))
            group = df.group_of_episode_id(episode_id)
            entries.append(None if entry is None else (f"{group or episode_id}#{pairs.group_of[i + k]}", entry))
            bar.update(1)
    bar.close()

    judged = [(i, e) for i, e in enumerate(entries) if e is not None]
    result = contrast_by_group([e for _, e in judged])
    # contrast_by_group keeps each group's entries in the order given: walk them back to their pairs.
    rows_of = {gid: iter(rows) for gid, rows in result["per_group"].items()}
    right = [None] * len(pairs)
    for i, (gid, _) in judged:
        right[i] = bool(next(rows_of[gid])["right"])
    kept = [i for i, r in enumerate(right) if r is not False]
    per_skill: dict[str, list[int]] = {}
    for skill, r in zip(skills, right):
        if r is not None:
            counts = per_skill.setdefault(skill or "?", [0, 0])
            counts[0] += int(r)
            counts[1] += 1
    record = {"format": 1, "teacher_digest": made_by, "num_pairs": len(pairs), "judged": len(judged),
              "right": int(sum(r is True for r in right)), "kept": kept, "per_skill": dict(sorted(per_skill.items())),
              "per_pair": [{"episode": sources[i][0], "skill": skills[i], "judged": right[i] is not None,
                            "right": right[i]} for i in range(len(pairs))],
              "right_way_cosine": result["right_way_cosine"], "still_share": result["still_share"]}
    write_following(Path(folder), record)
    return record


def summary(record: dict) -> str:
    """One line a person reads: how many pairs were judged, right and kept."""
    skills = ", ".join(f"{s} {r}/{n}" for s, (r, n) in record["per_skill"].items())
    share = record["right"] / record["judged"] if record["judged"] else float("nan")
    return (f"teacher pairs following their instruction: {record['right']} of {record['judged']} judged "
            f"({share:.0%}; {skills}); training on {len(record['kept'])} of {record['num_pairs']}")


def scores_of(folder: str | Path) -> dict | None:
    """The scores in ``folder`` when they are of its pairs as they are now (None: none, or it has grown since)."""
    from tesseract4d.model.reflow import count_pairs, read_following

    record = read_following(Path(folder))
    return record if record is not None and record.get("num_pairs") == count_pairs(folder) else None

