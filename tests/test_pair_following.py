"""`distill --keep-following`: a teacher's pairs scored with the held-out contrast check on their own
episodes (synthetic counterfactual groups with known motion, no simulator), and a student trained only
on the pairs kept."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch
from safetensors.torch import load_file, save_file
from synthetic_scene import GROUP, group_episode, write_grouped_dataset

from tesseract4d import dataset_format as df
from tesseract4d.cli import main
from tesseract4d.errors import UserError
from tesseract4d.evaluation.pair_following import score_pairs, scores_of
from tesseract4d.model.reflow import (FOLLOWING, PairsConfig, ReflowPairs, generate_pairs, pair_sources, task_balance,
                                      write_following)

pytestmark = pytest.mark.usefixtures("micro_preset")


def _group_data(root: Path, scenes: int = 2) -> Path:
    """``scenes`` counterfactual groups of the held-out believability test (push the red cube right,
    push the green cube up, keep still; 32², 8 frames, the micro preset's size)."""
    df.init_dataset(root, df.DatasetInfo(height=32, width=32, cameras=["close"]))
    for s in range(scenes):
        for k in range(len(GROUP)):
            df.write_episode(root, group_episode(k, seed=100000 + s))
    return root


def _clip_data(pipe, data: Path):
    from tesseract4d.model.clips import ClipDataset

    p = pipe.preset
    return ClipDataset(data, num_frames=p.num_frames, height=p.height, width=p.width, model_space=pipe.model_space)


def _set_teacher_clips(pairs_dir: Path, clip_of) -> None:
    """Overwrite every pair's teacher clip with ``clip_of(episode_id)`` (a (T, 7, H, W) model-space clip) in
    the network's space: a teacher known to be right, or wrong."""
    from tesseract4d.model.predict import load_pipeline

    pairs = ReflowPairs(pairs_dir)
    pipe = load_pipeline(pairs.manifest["teacher"])
    sources = pair_sources(pairs, _clip_data(pipe, Path(pairs.manifest["data"])))
    offset = 0
    for shard in sorted(pairs_dir.glob("pairs-*.safetensors")):
        tensors = load_file(str(shard))
        n = tensors["x0"].shape[0]
        clips = torch.stack([clip_of(sources[offset + k][0]) for k in range(n)])
        tensors["x0"] = pipe.codec.encode(clips).float().contiguous()
        save_file(tensors, str(shard))
        offset += n


@pytest.fixture()
def grouped_pairs(micro_checkpoint, tmp_path):
    """Pairs of the micro checkpoint on two synthetic groups (two draws of whole groups, shards of 3)."""
    data = _group_data(tmp_path / "groups")
    pairs = generate_pairs(PairsConfig(teacher=micro_checkpoint, data=data, out=tmp_path / "pairs", num_pairs=6,
                                       shard_size=3, batch_size=3, teacher_steps=1, groups=True), progress=False)
    return micro_checkpoint, data, pairs


def test_pair_sources_are_recorded_and_made_again_for_older_pairs(grouped_pairs, tmp_path):
    from tesseract4d.model.predict import load_pipeline

    ckpt, data, pairs_dir = grouped_pairs
    pairs = ReflowPairs(pairs_dir)
    clips = _clip_data(load_pipeline(ckpt), data)
    recorded = pair_sources(pairs, clips)
    assert len(recorded) == 6 and all(start == 0 for _, start in recorded)
    by_id = {s.episode_id: s.instruction for s in clips.sources}
    assert [by_id[e] for e, _ in recorded] == pairs.instructions
    # Each draw is one whole group: its three episodes of one scene.
    assert {df.group_of_episode_id(e) for e, _ in recorded[:3]} == {df.group_of_episode_id(recorded[0][0])}
    assert len({e for e, _ in recorded[:3]}) == 3
    # Shards written before the sources were recorded: the same sources, drawn again from the shard's seed.
    for sidecar in pairs_dir.glob("pairs-*.json"):
        record = json.loads(sidecar.read_text())
        sidecar.write_text(json.dumps({"instructions": record["instructions"]}))
    assert pair_sources(ReflowPairs(pairs_dir), clips) == recorded
    # Other data than the pairs were made from is refused.
    other = write_grouped_dataset(tmp_path / "other", scenes=2)
    with pytest.raises(UserError, match="does not come from"):
        pair_sources(ReflowPairs(pairs_dir), _clip_data(load_pipeline(ckpt), other))


def test_a_right_teacher_keeps_every_pair_and_a_still_one_only_keep_still(grouped_pairs):
    from tesseract4d.model.predict import load_pipeline

    ckpt, data, pairs_dir = grouped_pairs
    truth = {s.episode_id: s.frames.float() for s in _clip_data(load_pipeline(ckpt), data).sources}

    _set_teacher_clips(pairs_dir, lambda episode_id: truth[episode_id])
    record = score_pairs(pairs_dir, ckpt, progress=False)
    assert (record["num_pairs"], record["judged"], record["right"]) == (6, 6, 6)
    assert record["kept"] == list(range(6))
    assert record["per_skill"] == {"keep_still": [2, 2], "push": [4, 4]}
    assert json.loads((pairs_dir / FOLLOWING).read_text()) == record

    # A teacher whose clips never move: the pushes are wrong, "keep still" right; only those are kept.
    _set_teacher_clips(pairs_dir, lambda episode_id: truth[episode_id][:1].expand_as(truth[episode_id]))
    record = score_pairs(pairs_dir, ckpt, progress=False)
    assert (record["judged"], record["right"]) == (6, 2)
    assert record["per_skill"] == {"keep_still": [2, 2], "push": [0, 4]}
    kept = ReflowPairs(pairs_dir, keep_following=True)
    assert kept.kept == record["kept"] and len(kept) == 2
    assert kept.instructions == ["keep still", "keep still"]
    everything = ReflowPairs(pairs_dir)
    for name in ("first", "noise", "x0"):
        assert torch.equal(getattr(kept, name), getattr(everything, name)[record["kept"]])
    # Each kept pair is its group's only one now; the groups stay apart.
    assert sorted(len(u) for u in kept.group_units()) == [1, 1]


def test_a_pair_cut_later_in_its_episode_is_kept_unjudged_with_its_skill(grouped_pairs, monkeypatch):
    """The check reads an episode from frame 0: a pair whose clip starts later is not judged, kept, and still
    counted under its skill (read from the file's attributes)."""
    import tesseract4d.model.reflow as reflow
    from tesseract4d.model.predict import load_pipeline

    ckpt, data, pairs_dir = grouped_pairs
    clips = _clip_data(load_pipeline(ckpt), data)
    truth = {s.episode_id: s.frames.float() for s in clips.sources}
    _set_teacher_clips(pairs_dir, lambda e: truth[e][:1].expand_as(truth[e]))  # never moves: pushes wrong
    sources = reflow.pair_sources(ReflowPairs(pairs_dir), clips)
    later = next(i for i, (e, _) in enumerate(sources) if not e.endswith("_k2"))  # a push (k2: keep still)
    shifted = [(e, 3 if i == later else s) for i, (e, s) in enumerate(sources)]
    monkeypatch.setattr(reflow, "pair_sources", lambda pairs, data: shifted)
    record = score_pairs(pairs_dir, ckpt, progress=False)
    assert (record["num_pairs"], record["judged"]) == (6, 5)
    assert record["per_pair"][later] == {"episode": sources[later][0], "skill": "push", "judged": False, "right": None}
    assert later in record["kept"] and record["right"] == 2


def test_distill_keep_following_scores_once_and_trains_on_the_kept(grouped_pairs, tmp_path, capsys):
    from tesseract4d.model.predict import load_pipeline

    ckpt, data, pairs_dir = grouped_pairs
    with pytest.raises(UserError, match="--keep-following"):
        ReflowPairs(pairs_dir, keep_following=True)  # not scored yet
    # A teacher right but for the green cube's push (episodes k1), which it leaves where it is.
    truth = {s.episode_id: s.frames.float() for s in _clip_data(load_pipeline(ckpt), data).sources}
    _set_teacher_clips(pairs_dir, lambda e: truth[e][:1].expand_as(truth[e]) if e.endswith("_k1") else truth[e])
    argv = ["distill", "--teacher", str(ckpt), "--pairs", str(pairs_dir), "--keep-following", "--counterfactual-swap",
            "0.5", "--batch-size", "3", "--max-steps", "2", "--val-every", "0", "--ckpt-every", "0", "--no-progress"]
    assert main(argv + ["--out", str(tmp_path / "run")]) == 0
    out = capsys.readouterr().out
    record = scores_of(pairs_dir)
    assert record is not None and (record["num_pairs"], record["judged"], record["right"]) == (6, 6, 4)
    assert "training on 4 of 6" in out and "each task keeps its share" in out
    assert json.loads((tmp_path / "run" / "train_config.json").read_text())["balance_tasks"] is True  # the default
    assert ReflowPairs(pairs_dir, keep_following=True).instructions.count(GROUP[1][0]) == 0
    student = load_pipeline(tmp_path / "run" / "final")
    assert student.config["distilled_from"]["num_pairs"] == len(record["kept"])
    assert student.config["distilled_from"]["pairs_scored"] == 6
    assert student.config["distilled_from"]["pairs_balanced_by_task"] is True
    # A second run reads the scores rather than scoring again; grown pairs are scored again.
    stamp = (pairs_dir / FOLLOWING).stat().st_mtime_ns
    assert main(argv + ["--out", str(tmp_path / "run2")]) == 0
    assert (pairs_dir / FOLLOWING).stat().st_mtime_ns == stamp
    generate_pairs(PairsConfig(teacher=ckpt, data=data, out=pairs_dir, num_pairs=9, shard_size=3, batch_size=3,
                               teacher_steps=1, groups=True), progress=False)
    assert scores_of(pairs_dir) is None
    with pytest.raises(UserError, match="scores 6 pairs"):
        ReflowPairs(pairs_dir, keep_following=True)
    assert main(argv + ["--out", str(tmp_path / "run3")]) == 0
    assert scores_of(pairs_dir)["num_pairs"] == 9


def test_scores_are_written_only_into_a_pairs_folder(grouped_pairs, tmp_path):
    """The scores go to PAIRS/following.json alone; a folder that is not a pairs folder (a dataset, its
    parent) is refused before anything is written."""
    ckpt, data, pairs_dir = grouped_pairs
    for folder in (data, tmp_path):
        before = sorted(p for p in folder.rglob("*"))
        with pytest.raises(UserError, match="not a reflow pairs folder"):
            score_pairs(folder, ckpt, progress=False)
        assert sorted(p for p in folder.rglob("*")) == before
    before = {p.name for p in pairs_dir.iterdir()}
    score_pairs(pairs_dir, ckpt, progress=False)
    assert {p.name for p in pairs_dir.iterdir()} == before | {FOLLOWING}


def test_task_balance_gives_every_task_its_share_of_the_folder():
    """Weighted by task_balance, each task's kept pairs weigh what all its pairs are of the folder, however
    unevenly the check kept them."""
    g = torch.Generator().manual_seed(0)
    for _ in range(50):
        n = int(torch.randint(2, 40, (1,), generator=g))
        tasks = [f"Task{int(t)}-v1" for t in torch.randint(3, (n,), generator=g)]
        kept = [i for i in range(n) if torch.rand(1, generator=g) < 0.6] or [0]
        w = task_balance(tasks, kept)
        assert len(w) == len(kept) and min(w) >= 1.0
        kept_tasks = {tasks[i] for i in kept}
        folder = sum(tasks.count(t) for t in kept_tasks)  # the folder's pairs of the tasks still kept
        for task in kept_tasks:
            weighed = sum(wi for wi, i in zip(w, kept) if tasks[i] == task)
            assert weighed / sum(w) == pytest.approx(tasks.count(task) / folder)
    assert task_balance(["A", "A", "B", "B"], [0, 1, 2, 3]) == [1.0] * 4  # nothing left out: uniform


def test_kept_groups_are_drawn_so_each_task_keeps_its_share(grouped_pairs):
    """Two groups of three pairs, one task each: every pair of the first kept, one of the second. Drawn
    uniformly by group, the first task's pairs are 3/4 of a batch; balanced, half of it, as in the folder."""
    _, _, pairs_dir = grouped_pairs
    group_of = ReflowPairs(pairs_dir).group_of
    leaders = sorted(set(group_of))
    assert len(leaders) == 2 and group_of.count(leaders[0]) == group_of.count(leaders[1]) == 3
    tasks = ["TaskA-v1" if leader == leaders[0] else "TaskB-v1" for leader in group_of]
    kept = [i for i, t in enumerate(tasks) if t == "TaskA-v1"] + [tasks.index("TaskB-v1")]
    write_following(pairs_dir, {"num_pairs": 6, "kept": kept,
                                "per_pair": [{"episode": f"{t}/seed_000000_k0"} for t in tasks]})
    for balance, share in ((False, 0.75), (True, 0.5)):
        pairs = ReflowPairs(pairs_dir, keep_following=True, balance_tasks=balance)
        g = torch.Generator().manual_seed(0)
        first_task = {tuple(pairs.noise[k].flatten()[:8].tolist()) for k in range(3)}  # kept pairs 0-2: TaskA's
        for sample in (pairs.sample_group_batch, pairs.sample_batch):
            noise = sample(4000, g)[1]
            drawn = [tuple(n.flatten()[:8].tolist()) in first_task for n in noise]
            assert sum(drawn) / len(drawn) == pytest.approx(share, abs=0.03), (sample.__name__, balance)
    write_following(pairs_dir, {"num_pairs": 6, "kept": kept})  # scores without the pairs' episodes
    with pytest.raises(UserError, match="names no episode"):
        ReflowPairs(pairs_dir, keep_following=True, balance_tasks=True)
