"""Few-step distillation by reflow: deterministic resumable pairs, the `distill` command, and a
student that follows its guided multi-step teacher in a few unguided steps."""

from __future__ import annotations

import dataclasses
import json
import shutil
from pathlib import Path

import pytest
import torch
from tesseract4d.testing.model_fixtures import MICRO
from tesseract4d.testing.synthetic_scene import write_grouped_dataset, write_synthetic_dataset

from tesseract4d.cli import main
from tesseract4d.errors import UserError
from tesseract4d.model.checkpoint import weights_digest
from tesseract4d.model.reflow import (
    PairsConfig, ReflowPairs, generate_pairs, model_space_psnr,
)
from tesseract4d.model.trainer import TrainConfig, Trainer

pytestmark = pytest.mark.usefixtures("micro_preset")

TEACHER_STEPS, TEACHER_GUIDANCE, STUDENT_STEPS = 8, 2.0, 2


@pytest.fixture(scope="module")
def teacher(tmp_path_factory) -> tuple[Path, Path]:
    """A micro teacher trained briefly on the synthetic scenes: (checkpoint, dataset)."""
    root = tmp_path_factory.mktemp("reflow")
    data = write_synthetic_dataset(root / "data", episodes=4)
    cfg = TrainConfig(data=data, out=root / "teacher", preset=MICRO.name, max_steps=150, batch_size=4,
                      val_every=0, ckpt_every=0, quiet=True)
    return Trainer(cfg).train(), data


def _pairs_cfg(teacher, data, out, n):
    return PairsConfig(teacher=teacher, data=data, out=out, num_pairs=n, shard_size=2, batch_size=2,
                       teacher_steps=TEACHER_STEPS, text_guidance=TEACHER_GUIDANCE)


@pytest.mark.slow
def test_pairs_are_deterministic_and_resume(teacher, tmp_path):
    ckpt, data = teacher
    whole = ReflowPairs(generate_pairs(_pairs_cfg(ckpt, data, tmp_path / "a", 4), progress=False))
    generate_pairs(_pairs_cfg(ckpt, data, tmp_path / "b", 2), progress=False)  # interrupted after one shard
    assert len(ReflowPairs(tmp_path / "b")) == 2
    resumed = ReflowPairs(generate_pairs(_pairs_cfg(ckpt, data, tmp_path / "b", 4), progress=False))
    assert len(whole) == len(resumed) == 4 and whole.instructions == resumed.instructions
    for name in ("first", "noise", "x0"):
        assert torch.equal(getattr(whole, name), getattr(resumed, name)), name
    assert whole.manifest["teacher_digest"] == weights_digest(ckpt)
    with pytest.raises(UserError, match="other settings"):
        generate_pairs(PairsConfig(teacher=ckpt, data=data, out=tmp_path / "a", num_pairs=4, shard_size=2,
                                   teacher_steps=3), progress=False)
    # The same weights guided only at high noise sample other clips: their pairs are other pairs.
    interval = shutil.copytree(ckpt, tmp_path / "interval")
    config = json.loads((interval / "tesseract4d_config.json").read_text())
    config["preset"]["guidance_min_sigma"] = 0.5
    (interval / "tesseract4d_config.json").write_text(json.dumps(config))
    with pytest.raises(UserError, match="guidance_min_sigma"):
        generate_pairs(_pairs_cfg(interval, data, tmp_path / "a", 4), progress=False)


@pytest.mark.slow
def test_distill_student_follows_teacher_in_few_steps(teacher, tmp_path, capsys):
    """The distill command's student loads as a pipeline whose preset samples in STUDENT_STEPS
    unguided steps, and its samples from new noise are closer to the guided TEACHER_STEPS-step
    teacher than the teacher's own STUDENT_STEPS-step samples."""
    from tesseract4d.model.predict import load_pipeline

    ckpt, data = teacher
    pairs, run = tmp_path / "pairs", tmp_path / "student"
    generate_pairs(PairsConfig(teacher=ckpt, data=data, out=pairs, num_pairs=32, shard_size=16, batch_size=16,
                               teacher_steps=TEACHER_STEPS, text_guidance=TEACHER_GUIDANCE), progress=False)
    argv = ["distill", "--teacher", str(ckpt), "--pairs", str(pairs), "--out", str(run), "--student-steps",
            str(STUDENT_STEPS), "--max-steps", "150", "--batch-size", "4", "--lr", "1e-3", "--val-every", "150",
            "--ckpt-every", "0", "--quiet"]
    assert main(argv) == 0
    student = load_pipeline(run / "final")
    p = student.preset
    assert (p.num_steps, p.text_guidance, p.image_guidance) == (STUDENT_STEPS, 1.0, 1.0)
    src = student.config["distilled_from"]
    assert src["teacher_digest"] == weights_digest(ckpt) and src["teacher_steps"] == TEACHER_STEPS
    assert src["text_guidance"] == TEACHER_GUIDANCE
    assert json.loads((run / "train_config.json").read_text())["teacher"] == str(ckpt)

    # New noise (not a training pair), the pairs' first frames and instructions.
    teacher_pipe = load_pipeline(ckpt)
    pairs_data = ReflowPairs(pairs)
    first, texts = pairs_data.first[:8].float(), pairs_data.instructions[:8]
    noise = torch.randn(teacher_pipe.latent_shape(8), generator=torch.Generator().manual_seed(123))
    target = teacher_pipe(first, texts, num_inference_steps=TEACHER_STEPS, text_guidance=TEACHER_GUIDANCE,
                          latents=noise, output_type="latent")
    few = teacher_pipe(first, texts, num_inference_steps=STUDENT_STEPS, text_guidance=TEACHER_GUIDANCE,
                       latents=noise, output_type="latent")
    distilled = student(first, texts, latents=noise, output_type="latent")  # its preset: 2 steps, 1 pass each
    psnr_student = model_space_psnr(student.codec, distilled, target)
    psnr_teacher_few = model_space_psnr(student.codec, few, target)
    print(f"student {STUDENT_STEPS} steps: {psnr_student:.2f} dB, teacher {STUDENT_STEPS} steps: "
          f"{psnr_teacher_few:.2f} dB (vs teacher {TEACHER_STEPS} guided steps)")
    assert psnr_student > psnr_teacher_few + 1.0 and psnr_student > 25.0, (psnr_student, psnr_teacher_few)


def test_pairs_from_several_dataset_folders(teacher, tmp_path):
    ckpt, data = teacher
    more = write_synthetic_dataset(tmp_path / "more", episodes=2, seed_start=100)
    argv = ["distill", "--pairs-only", "--teacher", str(ckpt), "--pairs", str(tmp_path / "p"), "--num-pairs", "4",
            "--teacher-steps", "2", "--pair-batch-size", "2", "--quiet", "--data", str(data), str(more)]
    assert main([*argv, "--teacher-guidance", "2.5"]) == 0
    pairs = ReflowPairs(tmp_path / "p")
    assert len(pairs) == 4 and pairs.manifest["data"] == [str(data), str(more)]
    assert pairs.manifest["text_guidance"] == 2.5
    assert main([*argv, "--teacher-guidance", "2.5"]) == 0  # complete: resumed as it is
    assert main(argv) == 2  # the teacher preset's guidance is another setting: refused
    # Reused without --data (a student trained on them), the pairs are checked against the teacher all the same.
    student = ["distill", "--teacher", str(ckpt), "--pairs", str(tmp_path / "p"), "--teacher-steps", "2",
               "--out", str(tmp_path / "student"), "--max-steps", "1", "--quiet", "--val-every", "0"]
    assert main([*student, "--teacher-guidance", "1.5"]) == 2 and not (tmp_path / "student").exists()  # not 2.5
    from tesseract4d.model.checkpoint_copies import write_sampler_copy

    interval = write_sampler_copy(ckpt, tmp_path / "interval", {"guidance_min_sigma": 0.5})
    assert main([*student[:2], str(interval), *student[3:]]) == 2  # its copy with a guidance interval: other pairs
    assert main(student) == 0  # the steps and guidance the pairs were made with are the student's record
    # the same episodes twice is refused before any pair is made
    assert main([*argv[:5], str(tmp_path / "q"), *argv[6:], str(data)]) == 2 and not (tmp_path / "q").exists()


def test_distill_errors(teacher, tmp_path):
    ckpt, data = teacher
    assert main(["distill", "--teacher", str(ckpt), "--pairs", str(tmp_path / "none"), "--out", str(tmp_path / "r")]) == 2
    assert main(["distill", "--teacher", str(ckpt), "--pairs", str(tmp_path / "p"), "--pairs-only"]) == 2
    # The pairs folder is never the run folder.
    generate_pairs(_pairs_cfg(ckpt, data, tmp_path / "p", 2), progress=False)
    assert main(["distill", "--teacher", str(ckpt), "--pairs", str(tmp_path / "p"), "--out", str(tmp_path / "p")]) == 2
    assert not (tmp_path / "r").exists()


def test_distill_resumes_and_refuses_an_existing_run(teacher, tmp_path):
    ckpt, data = teacher
    argv = ["distill", "--teacher", str(ckpt), "--data", str(data), "--pairs", str(tmp_path / "p"), "--num-pairs", "4",
            "--teacher-steps", "2", "--out", str(tmp_path / "run"), "--batch-size", "2", "--val-every", "0",
            "--ckpt-every", "0", "--quiet"]
    assert main([*argv, "--max-steps", "2"]) == 0
    assert main([*argv, "--max-steps", "4"]) == 2  # a run is there: --resume or a new --out
    assert main([*argv, "--max-steps", "4", "--resume"]) == 0  # the pairs are complete: nothing resampled
    state = json.loads((tmp_path / "run" / "checkpoint-000004" / "trainer_state.json").read_text())
    assert state["step"] == 4 and state["inference_config"]["distilled_from"]["teacher_steps"] == 2
    assert json.loads((tmp_path / "run" / ".tesseract4d-output.json").read_text())["command"] == "distill"


def _files(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


def test_distill_never_writes_into_its_inputs(teacher, tmp_path, capsys):
    """--out and --pairs that are, lie inside or contain a --data folder, the --teacher (or, for --out,
    the --pairs) are refused before the teacher samples, and nothing is written (before: pairs and a
    student were written inside the dataset, exit 0)."""
    ckpt = shutil.copytree(teacher[0], tmp_path / "teacher")
    data = shutil.copytree(teacher[1], tmp_path / "data")
    quick = ["--num-pairs", "2", "--teacher-steps", "2", "--pair-batch-size", "2", "--max-steps", "1",
             "--batch-size", "2", "--val-every", "0", "--ckpt-every", "0", "--quiet"]
    cases = [
        (["--data", data, "--pairs", tmp_path / "p", "--out", data / "student"],
         f"--out {data / 'student'} lies inside the input {data}"),
        (["--data", data, "--pairs", data / "pairs", "--out", tmp_path / "run"],
         f"--pairs {data / 'pairs'} lies inside the input {data}"),
        (["--data", data, "--pairs", data / "pairs", "--pairs-only"], f"--pairs {data / 'pairs'} lies inside the input {data}"),
        (["--data", data, "--pairs", data, "--pairs-only"], f"--pairs {data} is the input {data}"),
        (["--data", data, "--pairs", tmp_path, "--pairs-only"], f"--pairs {tmp_path} contains the input {data}"),
        (["--data", data, "--pairs", ckpt / "pairs", "--pairs-only"], f"--pairs {ckpt / 'pairs'} lies inside the input {ckpt}"),
        (["--data", data, "--pairs", tmp_path / "p", "--out", tmp_path / "p" / "run"],
         f"--out {tmp_path / 'p' / 'run'} lies inside the input {tmp_path / 'p'}"),
    ]
    before = _files(tmp_path)
    for argv, said in cases:
        rc = main([str(a) for a in ["distill", "--teacher", ckpt, *argv, *quick]])
        err = capsys.readouterr().err
        assert rc == 2 and f"tesseract4d distill: error: {said}; write the output to a separate folder" in err, (argv, err)
        assert _files(tmp_path) == before, argv
        assert sorted(p.name for p in tmp_path.iterdir()) == ["data", "teacher"], argv


def test_distill_names_its_pairs_folder(teacher, tmp_path, capsys):
    """A --pairs folder holding someone's files, or a file, is refused as --pairs (it once said --out)."""
    ckpt, data = teacher
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "notes.txt").write_text("the user's own notes")
    argv = ["distill", "--pairs-only", "--teacher", str(ckpt), "--data", str(data), "--num-pairs", "2",
            "--teacher-steps", "2", "--quiet", "--pairs"]
    assert main([*argv, str(mine)]) == 2
    err = capsys.readouterr().err
    assert f"--pairs {mine} holds files that are not reflow pairs; choose a new or empty --pairs folder" in err, err
    assert [p.name for p in mine.iterdir()] == ["notes.txt"]
    assert main([*argv, str(mine / "notes.txt")]) == 2
    assert f"--pairs {mine / 'notes.txt'} is a file, not a folder" in capsys.readouterr().err
    generate_pairs(_pairs_cfg(ckpt, data, tmp_path / "p", 2), progress=False)
    assert main([*argv, str(tmp_path / "p"), "--teacher-guidance", "3"]) == 2  # made with guidance 2
    assert "choose a new --pairs folder for these settings" in capsys.readouterr().err


@pytest.mark.parametrize("extra, said", [
    (["--max-steps", "0"], "--max-steps must be a whole number >= 1 or 'auto', got 0"),
    (["--max-steps", "auto"], "--max-steps auto fits the learning-rate schedule to a time budget; pass --max-minutes"),
])
def test_distill_training_options_are_checked_before_the_pairs(teacher, tmp_path, capsys, extra, said):
    """A student run that cannot start is refused before the teacher spends its time on the pairs."""
    ckpt, data = teacher
    rc = main(["distill", "--teacher", str(ckpt), "--data", str(data), "--pairs", str(tmp_path / "p"), "--num-pairs",
               "2", "--teacher-steps", "2", "--out", str(tmp_path / "run"), "--quiet", *extra])
    assert rc == 2 and said in capsys.readouterr().err
    assert not (tmp_path / "p").exists() and not (tmp_path / "run").exists()


def test_group_pairs_share_first_frame_and_noise(teacher, tmp_path):
    """--group-pairs draws whole counterfactual groups: a group's pairs share the first frame and the
    noise and differ by the words; the shards resume to the same pairs; data without groups is refused."""
    ckpt, data = teacher
    groups = write_grouped_dataset(tmp_path / "groups", scenes=3, singles=1)

    def cfg(out, n):
        return PairsConfig(teacher=ckpt, data=groups, out=out, num_pairs=n, shard_size=4, batch_size=2,
                           teacher_steps=2, groups=True)

    whole = ReflowPairs(generate_pairs(cfg(tmp_path / "a", 8), progress=False))
    assert whole.grouped and whole.manifest["groups"] is True
    units = whole.group_units()
    assert sorted(i for u in units for i in u) == list(range(8))
    for unit in units:
        for i in unit[1:]:
            assert torch.equal(whole.noise[i], whole.noise[unit[0]])
            assert torch.equal(whole.first[i], whole.first[unit[0]])
            assert whole.instructions[i] != whole.instructions[unit[0]]
    assert any(len(u) == 2 for u in units)
    generate_pairs(cfg(tmp_path / "b", 4), progress=False)  # interrupted after one shard
    resumed = ReflowPairs(generate_pairs(cfg(tmp_path / "b", 8), progress=False))
    assert resumed.group_of == whole.group_of and torch.equal(resumed.noise, whole.noise)
    with pytest.raises(UserError, match="other settings"):  # the same folder without groups
        generate_pairs(dataclasses.replace(cfg(tmp_path / "a", 8), groups=False), progress=False)
    with pytest.raises(UserError, match="counterfactual groups"):
        generate_pairs(dataclasses.replace(cfg(tmp_path / "c", 4), data=data), progress=False)
    assert not (tmp_path / "c").exists()
    plain = ReflowPairs(generate_pairs(_pairs_cfg(ckpt, data, tmp_path / "d", 2), progress=False))
    with pytest.raises(UserError, match="--set groups=true"):
        plain.group_units()


def test_group_batch_of_pairs_is_whole_groups(teacher, tmp_path):
    ckpt, _ = teacher
    groups = write_grouped_dataset(tmp_path / "groups", scenes=3, singles=1)
    pairs = ReflowPairs(generate_pairs(PairsConfig(teacher=ckpt, data=groups, out=tmp_path / "p", num_pairs=8,
                                                   shard_size=8, batch_size=4, teacher_steps=1, groups=True),
                                       progress=False))
    g = torch.Generator().manual_seed(0)
    for _ in range(20):
        first, noise, x0, texts, leaders = pairs.sample_group_batch(4, g)
        assert len(texts) == first.shape[0] == noise.shape[0] == x0.shape[0] == len(leaders) == 4
        for k, leader in enumerate(leaders):
            assert leaders[leader] == leader and torch.equal(noise[k], noise[leader])
            assert torch.equal(first[k], first[leader])


def test_distill_with_counterfactual_swap(teacher, tmp_path, monkeypatch):
    """The student trains in batches of whole groups, shown a sibling's noisy sample at t >= SWAP_MIN_T
    (its target its own teacher clip), and records the recipe; pairs drawn one by one are refused."""
    from tesseract4d.model.predict import load_pipeline
    from tesseract4d.model.recipe import SWAP_MIN_T
    from tesseract4d.model.reflow import ReflowTrainer

    ckpt, data = teacher
    groups = write_grouped_dataset(tmp_path / "groups", scenes=3)
    seen, batches = [], []
    original, draw = ReflowTrainer.denoising_loss, ReflowPairs.sample_group_batch

    def spy(self, x0, first, text, t, noise, objects=None, *, shown=None):
        seen.append((t.clone(), batches[-1], list(shown) if shown is not None else None))
        return original(self, x0, first, text, t, noise, objects, shown=shown)

    def spy_batch(self, *args, **kwargs):
        out = draw(self, *args, **kwargs)
        batches.append(list(out[-1]))  # each pair's group leader (its batch position)
        return out

    monkeypatch.setattr(ReflowTrainer, "denoising_loss", spy)
    monkeypatch.setattr(ReflowPairs, "sample_group_batch", spy_batch)
    argv = ["distill", "--teacher", str(ckpt), "--data", str(groups), "--pairs", str(tmp_path / "p"), "--group-pairs",
            "--num-pairs", "8", "--teacher-steps", "2", "--out", str(tmp_path / "run"), "--batch-size", "4",
            "--max-steps", "12", "--val-every", "0", "--ckpt-every", "0", "--quiet", "--counterfactual-swap", "1",
            "--rephrase", "1"]  # (no train template writes the synthetic instructions: they keep their words)
    assert main(argv) == 0
    assert len(seen) == 12
    swapped = 0
    for t, leaders, shown in seen:
        for k, leader in enumerate(leaders):
            assert float(t[k]) == float(t[leader])  # one diffusion time per group
            siblings = [j for j, other in enumerate(leaders) if other == leader and j != k]
            if float(t[k]) >= SWAP_MIN_T and siblings:
                assert shown[k] in siblings  # probability 1: always a sibling's sample
                swapped += 1
            else:
                assert shown[k] == k
    assert swapped > 0
    student = load_pipeline(tmp_path / "run" / "final")
    assert student.config["recipe"]["counterfactual_swap"] == 1.0 and student.config["recipe"]["group_batches"]
    assert student.config["recipe"]["rephrase"] == 1.0
    assert student.config["distilled_from"]["pair_groups"] is True
    # Pairs drawn one by one cannot be swapped within a group.
    plain = tmp_path / "plain"
    generate_pairs(_pairs_cfg(ckpt, data, plain, 2), progress=False)
    assert main(["distill", "--teacher", str(ckpt), "--pairs", str(plain), "--out", str(tmp_path / "r2"),
                 "--counterfactual-swap", "0.5", "--quiet"]) == 2
    assert not (tmp_path / "r2").exists()


def test_pairs_made_with_a_removed_teacher_option_are_refused(teacher, tmp_path):
    """Pairs folders written before autoguidance and teacher draws were removed record them: at their
    no-op values (autoguidance 0, one draw) they resume and are reused as before; pairs an autoguided
    teacher or several draws made are refused, naming the setting."""
    from tesseract4d.model.reflow import MANIFEST, check_pairs_of_teacher

    ckpt, data = teacher
    folder = generate_pairs(_pairs_cfg(ckpt, data, tmp_path / "pairs", 2), progress=False)
    manifest = json.loads((folder / MANIFEST).read_text())
    old = {**manifest, "autoguidance": 0.0, "autoguidance_min_sigma": 0.0, "guide_digest": None, "teacher_draws": 1}
    (folder / MANIFEST).write_text(json.dumps(old))
    check_pairs_of_teacher(folder, ckpt)
    assert len(ReflowPairs(generate_pairs(_pairs_cfg(ckpt, data, folder, 4), progress=False))) == 4
    for key, value in (("autoguidance", 1.0), ("teacher_draws", 2)):
        (folder / MANIFEST).write_text(json.dumps({**old, key: value}))
        with pytest.raises(UserError, match=key):
            check_pairs_of_teacher(folder, ckpt)
        with pytest.raises(UserError, match=key):
            generate_pairs(_pairs_cfg(ckpt, data, folder, 6), progress=False)
