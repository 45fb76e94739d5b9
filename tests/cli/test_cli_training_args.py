"""The training commands' numbers and folders (distill, train-idm, train-autoencoder, encode-latents):
a value no run can use ends at parse time (argparse's exit 2 and the rule), before any work and
before anything is written, instead of a traceback, a half-made run folder or an untrained model."""

from __future__ import annotations

from pathlib import Path

import pytest

from tesseract4d import cli


def _refused_at_parse_time(argv: list[str], said: str, capsys) -> None:
    with pytest.raises(SystemExit) as ended:
        cli.main(argv)
    err = capsys.readouterr().err
    assert ended.value.code == 2 and said in err, err
    assert "Traceback" not in err


DISTILL = ["distill", "--teacher", "ckpt", "--data", "data", "--pairs", "pairs", "--out", "student"]


@pytest.mark.parametrize("argv, said", [
    (["--pair-batch-size", "0"], "argument --pair-batch-size: must be a whole number >= 1, got '0'"),
    (["--num-pairs", "0"], "argument --num-pairs: must be a whole number >= 1"),
    (["--teacher-steps", "0"], "argument --teacher-steps: must be a whole number >= 1"),
    (["--teacher-guidance", "-1"], "argument --teacher-guidance: must be a finite number > 0 (1: no guidance), got '-1'"),
    (["--teacher-guidance", "0"], "argument --teacher-guidance: must be a finite number > 0"),
    (["--student-steps", "0"], "argument --student-steps: must be a whole number >= 1, got '0'"),
    (["--batch-size", "0"], "argument --batch-size: must be a whole number >= 1"),
    (["--lr", "0"], "argument --lr: must be a finite number > 0"),
    (["--lr", "nan"], "argument --lr: must be a finite number > 0"),
    (["--max-minutes", "-1"], "argument --max-minutes: must be a finite number >= 0"),
    (["--val-every", "-1"], "argument --val-every: must be a whole number >= 0 (0 = never)"),
    (["--ckpt-every", "-1"], "argument --ckpt-every: must be a whole number >= 0 (0 = only at the end)"),
    (["--counterfactual-swap", "-0.5"], "argument --counterfactual-swap: must be a finite number >= 0"),
    (["--rephrase", "nan"], "argument --rephrase: must be a finite number >= 0"),
    (["--seed", "-1"], "argument --seed: must be a whole number in 0..4294967295"),
])
def test_distill_numbers_are_refused_before_the_teacher_samples(tmp_path, monkeypatch, capsys, argv, said):
    """Before, --student-steps 0 was refused only after every pair was made, --pair-batch-size 0 named
    a --shard-size flag distill does not have, and --teacher-guidance -1 was sampled."""
    monkeypatch.chdir(tmp_path)
    _refused_at_parse_time([*DISTILL, *argv], said, capsys)
    assert list(tmp_path.iterdir()) == []


TRAIN_IDM = ["train-idm", "--data", "data", "--out", "run"]


@pytest.mark.parametrize("argv, said", [
    (["--num-points", "0"], "argument --num-points: must be a whole number >= 1, got '0'"),
    (["--chunk-len", "0"], "argument --chunk-len: must be a whole number >= 1, got '0'"),
    (["--gap-scales", "abc"], "argument --gap-scales: must be a finite number > 0, got 'abc' (each of the "
                              "comma-separated scales, e.g. 0.5,1,2)"),
    (["--gap-scales", "1,-2"], "argument --gap-scales: must be a finite number > 0, got '-2'"),
    (["--gap-scales", ","], "argument --gap-scales: must be comma-separated numbers > 0 such as 0.5,1,2, got ','"),
    (["--steps", "0"], "argument --steps: must be a whole number >= 1, got '0'"),
    (["--steps", "-1"], "argument --steps: must be a whole number >= 1, got '-1'"),
    (["--batch-size", "0"], "argument --batch-size: must be a whole number >= 1, got '0'"),
    (["--lr", "-0.001"], "argument --lr: must be a finite number > 0"),
    (["--noise-frac", "-0.1"], "argument --noise-frac: must be a finite number >= 0"),
    (["--noise-m", "inf"], "argument --noise-m: must be a finite number >= 0"),
    (["--max-episodes-per-task", "-1"], "argument --max-episodes-per-task: must be a whole number >= 0 (0 = all)"),
    (["--predicted-share", "0"], "argument --predicted-share: must be a finite number > 0"),
    (["--predicted-starts", "0"], "argument --predicted-starts: must be a whole number >= 1"),
    (["--predicted-steps", "0"], "argument --predicted-steps: must be a whole number >= 1"),
    (["--ckpt-every", "-5"], "argument --ckpt-every: must be a whole number >= 0 (0 = only at the end)"),
    (["--max-minutes", "nan"], "argument --max-minutes: must be a finite number >= 0"),
    (["--seed", "-1"], "argument --seed: must be a whole number in 0..4294967295"),
])
def test_train_idm_numbers_are_refused_before_any_work(tmp_path, monkeypatch, capsys, argv, said):
    """Before: --num-points 0 and --gap-scales abc were tracebacks, --chunk-len 0 one after training
    (with a half-made run folder), --steps 0 wrote an untrained final/ model and --batch-size 0 trained
    on empty batches."""
    monkeypatch.chdir(tmp_path)
    _refused_at_parse_time([*TRAIN_IDM, *argv], said, capsys)
    assert list(tmp_path.iterdir()) == []


def test_train_idm_help_example_keeps_its_line_continuation(capsys):
    with pytest.raises(SystemExit) as ended:
        cli.main(["train-idm", "--help"])
    out = capsys.readouterr().out
    assert ended.value.code == 0
    assert "--max-steps 3000 \\\n      --predicted-futures tesseract4d/checkpoints/v2-2step" in out, out


TRAIN_AE = ["train-autoencoder", "--data", "data", "--out", "run"]


@pytest.mark.parametrize("argv, said", [
    (["--batch-size", "0"], "argument --batch-size: must be a whole number >= 1, got '0'"),
    (["--lr", "0"], "argument --lr: must be a finite number > 0"),
    (["--warmup-steps", "-1"], "argument --warmup-steps: must be a whole number >= 0"),
    (["--frame-stride", "0"], "argument --frame-stride: must be a whole number >= 1"),
    (["--object-weight", "-1"], "argument --object-weight: must be a finite number >= 0"),
    (["--rgb-weight", "nan"], "argument --rgb-weight: must be a finite number >= 0"),
    (["--depth-weight", "-3"], "argument --depth-weight: must be a finite number >= 0"),
    (["--normal-weight", "inf"], "argument --normal-weight: must be a finite number >= 0"),
    (["--kl-weight", "-0.0001"], "argument --kl-weight: must be a finite number >= 0"),
    (["--ckpt-every", "-1"], "argument --ckpt-every: must be a whole number >= 0 (0 = only at the end)"),
    (["--heldout-frames", "0"], "argument --heldout-frames: must be a whole number >= 1"),
    (["--max-minutes", "-2"], "argument --max-minutes: must be a finite number >= 0"),
    (["--seed", "-1"], "argument --seed: must be a whole number in 0..4294967295"),
])
def test_train_autoencoder_numbers_are_refused_before_any_work(tmp_path, monkeypatch, capsys, argv, said):
    """Before: --batch-size 0 was a RuntimeError traceback; negative loss weights trained."""
    monkeypatch.chdir(tmp_path)
    _refused_at_parse_time([*TRAIN_AE, *argv], said, capsys)
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("cache, said", [
    ("notes.txt", "--cache notes.txt is a file; --cache must be a folder"),
    ("notes.txt/cache", "--cache notes.txt/cache lies under the file notes.txt; --cache must be a folder"),
])
def test_encode_latents_cache_that_is_a_file_is_refused(tmp_path, monkeypatch, capsys, cache, said):
    """Before: a NotADirectoryError traceback."""
    from tesseract4d.testing.synthetic_scene import write_segmented_dataset

    from tesseract4d.model.autoencoder import RGBDNAutoencoder, get_autoencoder_preset, save_autoencoder

    data = write_segmented_dataset(tmp_path / "data", episodes=1)
    ae = save_autoencoder(RGBDNAutoencoder(get_autoencoder_preset("ae-test")), tmp_path / "ae")
    (tmp_path / "notes.txt").write_text("the user's own notes")
    monkeypatch.chdir(tmp_path)
    rc = cli.main(["encode-latents", "--data", str(data), "--autoencoder", str(ae), "--cache", cache, "--quiet"])
    err = capsys.readouterr().err
    assert rc == 2 and "Traceback" not in err
    assert f"tesseract4d encode-latents: error: {said}" in err, err
    assert (tmp_path / "notes.txt").read_text() == "the user's own notes"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ae", "data", "notes.txt"]
    assert not (Path(data) / "latent_cache").exists()
