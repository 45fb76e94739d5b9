"""Bad input, one test per case: every user mistake is one line with exit code 2 (or 1 for a
failed `dataset check`), names what is wrong, and changes nothing outside the command's own output.

Each test builds a sandbox inside its own ``tmp_path`` (copies of a micro checkpoint, a synthetic
dataset, foreign files), hashes every file in it before and after the command, and compares.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import h5py
import pytest
from tesseract4d.testing.model_fixtures import MICRO
from tesseract4d.testing.synthetic_scene import synthetic_episode, write_synthetic_dataset

from tesseract4d import cli
from tesseract4d import dataset_format as df
from tesseract4d.outputs import MARKER

REPO = Path(__file__).resolve().parents[2]
ENV = "Synthetic-v0"


# --------------------------------------------------------------------------- fixtures


@pytest.fixture(scope="module")
def micro_registered(micro_preset):
    """The micro preset, registered for the whole run by conftest's micro_preset (a registration of
    this module's own would remove it from the modules that run after this one)."""
    return micro_preset


@pytest.fixture(scope="module")
def built(micro_registered, tmp_path_factory) -> dict[str, Path]:
    """A synthetic dataset, a micro training run (2 checkpoints) and its exported checkpoint."""
    from tesseract4d.model.trainer import TrainConfig, Trainer

    root = tmp_path_factory.mktemp("bad_input")
    data = write_synthetic_dataset(root / "data", episodes=2)
    run = root / "run"
    final = Trainer(TrainConfig(data=data, out=run, preset=MICRO.name, max_steps=2, val_every=0, ckpt_every=1,
                                quiet=True)).train()
    return {"data": data, "run": run, "checkpoint": final}


@pytest.fixture
def sandbox(built, tmp_path, monkeypatch) -> Path:
    """tmp_path/sb with copies of data/, run/, ckpt/ and a foreign file; the working directory."""
    sb = tmp_path / "sb"
    shutil.copytree(built["data"], sb / "data")
    shutil.copytree(built["run"], sb / "run")
    shutil.copytree(built["checkpoint"], sb / "ckpt")
    (sb / "notes.txt").write_text("the user's own notes")
    monkeypatch.chdir(sb)
    return sb


def snapshot(root: Path) -> dict[str, str]:
    """Every file and folder under root: relative path -> sha256 (folders: 'dir')."""
    out = {}
    for p in sorted(root.rglob("*")):
        rel = p.relative_to(root).as_posix()
        out[rel] = "dir" if p.is_dir() else hashlib.sha256(p.read_bytes()).hexdigest()
    return out


def changed(before: dict[str, str], after: dict[str, str]) -> set[str]:
    return {k for k in set(before) | set(after) if before.get(k) != after.get(k)}


def run_cli(capsys, *argv) -> tuple[int, str, str]:
    rc = cli.main([str(a) for a in argv])
    cap = capsys.readouterr()
    return rc, cap.out, cap.err


def assert_one_line_error(rc: int, err: str, *words: str, code: int = 2) -> None:
    assert rc == code, err
    assert "Traceback" not in err
    lines = [line for line in err.splitlines() if line.startswith("tesseract4d ")]
    assert len(lines) == 1, err
    for w in words:
        assert w in lines[0], (w, lines[0])


def episode_file(sb: Path, seed: int = 0) -> Path:
    return df.episode_path(sb / "data", ENV, seed)


# --------------------------------------------------------------------------- output folders


def test_reconstruct_out_holding_foreign_files_is_refused(sandbox, capsys):
    (sandbox / "out").mkdir()
    (sandbox / "out" / "thesis.tex").write_text("months of work")
    before = snapshot(sandbox)
    rc, _, err = run_cli(capsys, "reconstruct", "data/Synthetic-v0/0", "--out", "out", "--no-refine", "--no-mesh")
    assert_one_line_error(rc, err, "out", "--overwrite")
    assert changed(before, snapshot(sandbox)) == set()


@pytest.mark.parametrize("argv", [
    ["rollout", "--tasks", "PushCube-v1", "--arms", "motion_planner", "--episodes", "1", "--out", "out"],
    ["train-idm", "--data", "data", "--out", "out", "--steps", "1"],
], ids=["rollout", "train-idm"])
def test_policy_commands_refuse_an_out_holding_foreign_files(sandbox, capsys, argv):
    (sandbox / "out").mkdir()
    (sandbox / "out" / "report.json").write_text("the user's own report")
    before = snapshot(sandbox)
    rc, _, err = run_cli(capsys, *argv)
    assert_one_line_error(rc, err, "out", "did not write")
    assert changed(before, snapshot(sandbox)) == set()


def test_reconstruct_out_dotdot_from_a_nested_directory_is_refused(sandbox, capsys, monkeypatch):
    nested = sandbox / "work" / "inner"
    nested.mkdir(parents=True)
    monkeypatch.chdir(nested)
    before = snapshot(sandbox)
    rc, _, err = run_cli(capsys, "reconstruct", sandbox / "data" / ENV / "0", "--out", "..", "--no-refine", "--no-mesh")
    assert_one_line_error(rc, err, "--overwrite")
    assert changed(before, snapshot(sandbox)) == set()


@pytest.mark.parametrize("out", ["data", "data/episodes", "data/Synthetic-v0/0", "."])
def test_reconstruct_out_overlapping_the_input_is_refused(sandbox, capsys, out):
    before = snapshot(sandbox)
    rc, _, err = run_cli(capsys, "reconstruct", "data/Synthetic-v0/0", "--out", out, "--no-refine", "--no-mesh")
    assert_one_line_error(rc, err, "input", "separate folder")
    assert changed(before, snapshot(sandbox)) == set()


def test_reconstruct_overwrite_replaces_only_its_own_files(sandbox, capsys):
    out = sandbox / "out"
    out.mkdir()
    (out / "thesis.tex").write_text("months of work")
    rc, _, err = run_cli(capsys, "reconstruct", "data/Synthetic-v0/0", "--out", out, "--no-refine", "--no-mesh",
                         "--overwrite", "--quiet")
    assert rc == 0, err
    assert (out / "thesis.tex").read_text() == "months of work"
    assert (out / "recon4d.npz").is_file() and (out / MARKER).is_file()
    # A rerun replaces the earlier reconstruction (its files) and still keeps the foreign one.
    (out / "frames" / "frame_0000.ply").unlink()
    before = snapshot(sandbox)
    rc, _, err = run_cli(capsys, "reconstruct", "data/Synthetic-v0/0", "--out", out, "--no-refine", "--no-mesh", "--quiet")
    assert rc == 0, err
    assert (out / "thesis.tex").read_text() == "months of work" and (out / "frames" / "frame_0000.ply").is_file()
    assert {p.split("/")[0] for p in changed(before, snapshot(sandbox))} == {"out"}
    assert not [p for p in sandbox.iterdir() if ".tmp-" in p.name or ".old-" in p.name]


def test_reconstruct_rerun_into_its_own_output_swaps_it_whole(sandbox, capsys):
    rc, _, err = run_cli(capsys, "reconstruct", "data/Synthetic-v0/0", "--out", "out", "--no-refine", "--no-mesh", "--quiet")
    assert rc == 0, err
    before = snapshot(sandbox)
    rc, _, err = run_cli(capsys, "reconstruct", "data/Synthetic-v0/1", "--out", "out", "--no-refine", "--no-mesh", "--quiet")
    assert rc == 0, err
    assert {p.split("/")[0] for p in changed(before, snapshot(sandbox))} == {"out"}
    assert json.loads((sandbox / "out" / "manifest.json").read_text())["metadata"]["episode_path"].endswith("seed_000001.h5")


def test_predict_into_the_dataset_it_reads_is_refused(sandbox, capsys):
    before = snapshot(sandbox)
    rc, _, err = run_cli(capsys, "predict", "--checkpoint", "ckpt", "--episode", "data/Synthetic-v0/0", "--out", "data",
                         "--steps", "1")
    assert_one_line_error(rc, err, "data", "input")
    assert changed(before, snapshot(sandbox)) == set()


def test_predict_into_another_dataset_is_refused(sandbox, capsys):
    (sandbox / "other").mkdir()
    df.write_episode_dataset(sandbox / "other", synthetic_episode(5))
    before = snapshot(sandbox)
    rc, _, err = run_cli(capsys, "predict", "--checkpoint", "ckpt", "--episode", "data/Synthetic-v0/0", "--out", "other",
                         "--steps", "1")
    assert_one_line_error(rc, err, "other", "--overwrite")
    assert changed(before, snapshot(sandbox)) == set()


def test_predict_writes_a_new_folder_and_warns_about_a_long_instruction(sandbox, capsys):
    before = snapshot(sandbox)
    rc, _, err = run_cli(capsys, "predict", "--checkpoint", "ckpt", "--episode", "data/Synthetic-v0/0", "--out", "pred",
                         "--steps", "1", "--instruction", "push the square to the right " * 200)
    assert rc == 0, err
    assert "tokens; the text encoder keeps the first 8" in err
    assert {p.split("/")[0] for p in changed(before, snapshot(sandbox))} == {"pred"}
    assert (sandbox / "pred" / MARKER).is_file() and (sandbox / "pred" / "predict_config.json").is_file()
    # As readable as a plain mkdir/open would make them (staging folders start private).
    mask = os.umask(0)
    os.umask(mask)
    assert (sandbox / "pred").stat().st_mode & 0o777 == 0o777 & ~mask


def test_single_file_outputs_are_created_with_the_users_umask(sandbox, capsys):
    rc, _, err = run_cli(capsys, "view", "data/Synthetic-v0/0", "--export", "scene.html")
    assert rc == 0, err
    mask = os.umask(0)
    os.umask(mask)
    assert (sandbox / "scene.html").stat().st_mode & 0o777 == 0o666 & ~mask


@pytest.mark.parametrize("field,value", [("env_id", "../../../escaped"), ("env_id", "a/b"), ("env_id", ".."),
                                         ("camera", "../cam")])
def test_names_from_a_crafted_episode_never_become_paths(sandbox, capsys, field, value):
    path = episode_file(sandbox)
    with h5py.File(path, "r+") as f:
        if field == "env_id":
            f.attrs["env_id"] = value
        else:
            f["cameras"].move("close", value.replace("/", "\\"))  # h5 names cannot hold '/'
    before = snapshot(sandbox)
    rc, _, err = run_cli(capsys, "predict", "--checkpoint", "ckpt", "--episode", path, "--out", "pred", "--steps", "1")
    assert_one_line_error(rc, err, "env_id" if field == "env_id" else "camera name", str(path))
    assert changed(before, snapshot(sandbox)) == set()
    assert not (sandbox.parent / "escaped").exists() and not (sandbox.parent.parent / "escaped").exists()
    rc, out, _ = run_cli(capsys, "dataset", "check", "data")
    assert rc == 1 and f"BAD  data/episodes/{ENV}/{path.name}" in out and "1 bad" in out


def test_export_keeps_files_it_did_not_write(sandbox, capsys):
    to = sandbox / "published"
    to.mkdir()
    (to / "MODEL_CARD.md").write_text("# my model card")
    before = snapshot(sandbox)
    rc, _, err = run_cli(capsys, "checkpoint", "export", "run", "--to", to)
    assert_one_line_error(rc, err, "published", "--overwrite")
    assert changed(before, snapshot(sandbox)) == set()
    rc, _, err = run_cli(capsys, "checkpoint", "export", "run", "--to", to, "--overwrite")
    assert rc == 0, err
    assert (to / "MODEL_CARD.md").read_text() == "# my model card"
    assert (to / "transformer" / "diffusion_pytorch_model.safetensors").is_file()
    # Exporting again replaces the export's own files only.
    rc, _, err = run_cli(capsys, "checkpoint", "export", "run", "--to", to)
    assert rc == 0, err
    assert (to / "MODEL_CARD.md").read_text() == "# my model card"


@pytest.mark.parametrize("case", ["export-to-file", "train-out-file"])
def test_output_that_is_a_file(sandbox, capsys, case):
    before = snapshot(sandbox)
    if case == "export-to-file":
        rc, _, err = run_cli(capsys, "checkpoint", "export", "run", "--to", "notes.txt")
    else:
        rc, _, err = run_cli(capsys, "train", "--set", f"preset={MICRO.name}", "--data", "data", "--out", "notes.txt",
                             "--max-steps", "1", "--quiet")
    assert_one_line_error(rc, err, "notes.txt", "is a file")
    assert changed(before, snapshot(sandbox)) == set()


def test_evaluate_json_does_not_replace_a_foreign_file(sandbox, capsys):
    before = snapshot(sandbox)
    rc, _, err = run_cli(capsys, "evaluate", "data/Synthetic-v0/0", "--gt", "data/Synthetic-v0/0", "--json", "notes.txt")
    assert_one_line_error(rc, err, "notes.txt", "--overwrite")
    assert changed(before, snapshot(sandbox)) == set()
    rc, _, err = run_cli(capsys, "evaluate", "data/Synthetic-v0/0", "--gt", "data/Synthetic-v0/1", "--json", "r.json")
    assert rc == 0, err
    rc, _, err = run_cli(capsys, "evaluate", "data/Synthetic-v0/0", "--gt", "data/Synthetic-v0/1", "--json", "r.json")
    assert rc == 0, err  # its own earlier report is replaced


def test_view_export_does_not_replace_a_foreign_file(sandbox, capsys):
    before = snapshot(sandbox)
    rc, _, err = run_cli(capsys, "view", "data/Synthetic-v0/0", "--export", "notes.txt")
    assert_one_line_error(rc, err, "notes.txt", "--overwrite")
    rc, _, err = run_cli(capsys, "view", "data/Synthetic-v0/0", "--export", episode_file(sandbox))
    assert_one_line_error(rc, err, "is the input")
    assert changed(before, snapshot(sandbox)) == set()


# --------------------------------------------------------------------------- datagen


@pytest.mark.parametrize("args,words", [
    (["--out", "notes.txt"], ["notes.txt", "is a file"]),
    (["--out", "run"], ["run", "already holds"]),
    (["--out", "new", "--resolution", "100000"], ["100000", "at most"]),
    (["--out", "new", "--episodes", "0"], ["--episodes"]),
    (["--out", "new", "--seed-start", "-5"], ["--seed-start", "-5"]),
    (["--out", "new", "--instructions-per-scene", "0"], ["--instructions-per-scene"]),
])
def test_datagen_refuses_bad_outputs_and_options(sandbox, capsys, args, words):
    before = snapshot(sandbox)
    rc, _, err = run_cli(capsys, "datagen", "--tasks", "PushCube-v1", "--episodes", "1", *args)
    assert_one_line_error(rc, err, *words)
    assert changed(before, snapshot(sandbox)) == set()


def test_second_datagen_on_a_locked_folder_refuses(sandbox, capsys):
    holder = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        lock = sandbox / "data" / df.LOCK_FILE
        lock.write_text(f"{holder.pid}\n")
        before = snapshot(sandbox)
        rc, _, err = run_cli(capsys, "datagen", "--tasks", "PushCube-v1", "--episodes", "1", "--out", "data")
        assert_one_line_error(rc, err, "another datagen", str(holder.pid))
        assert changed(before, snapshot(sandbox)) == set()
    finally:
        holder.kill()
        holder.wait()


@pytest.mark.sim
def test_two_datagen_processes_on_one_folder(tmp_path, capsys):
    out = tmp_path / "ds"
    first = subprocess.Popen([sys.executable, "-m", "tesseract4d.cli", "datagen", "--tasks", "PushCube-v1", "--episodes",
                              "20", "--out", str(out), "--resolution", "32", "--frames", "4", "--set", "previews=false", "--quiet"],
                             cwd=REPO, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        deadline = time.time() + 60
        while not (out / df.INFO_FILE).is_file() and time.time() < deadline:
            time.sleep(0.05)
        assert first.poll() is None and (out / df.LOCK_FILE).read_text().strip() == str(first.pid)
        rc, _, err = run_cli(capsys, "datagen", "--tasks", "PushCube-v1", "--episodes", "20", "--out", out,
                             "--resolution", "32", "--frames", "4", "--set", "previews=false", "--quiet")
        assert_one_line_error(rc, err, "another datagen", f"pid {first.pid}")
        assert first.poll() is None  # the first run goes on
    finally:
        first.kill()
        first.wait()


# --------------------------------------------------------------------------- training


@pytest.mark.parametrize("args,words", [
    (["--batch-size", "0"], ["--batch-size"]),
    (["--batch-size", "-3"], ["--batch-size"]),
    (["--lr", "nan"], ["--lr", "finite"]),
    (["--lr", "inf"], ["--lr", "finite"]),
    (["--lr", "0"], ["--lr"]),
    (["--loss-weights", "rgb=nan,depth=1,normal=1"], ["rgb=nan", "finite"]),
    (["--loss-weights", "rgb=-1,depth=1,normal=1"], ["rgb=-1", ">= 0"]),
    (["--loss-weights", "rgb=0,depth=0,normal=0"], ["not all be zero"]),
    (["--loss-weights", "colour=1"], ["colour"]),
    (["--max-steps", "0"], ["--max-steps"]),
    (["--max-steps", "-1"], ["--max-steps"]),
    (["--max-steps", "auto"], ["--max-steps auto", "--max-minutes"]),
    (["--max-steps", "auto", "--max-minutes", "5", "--stop-at-step", "3"], ["--stop-at-step"]),
    (["--warmup-steps", "-1"], ["--warmup-steps"]),
    (["--max-minutes", "nan"], ["--max-minutes"]),
])
def test_train_numeric_options_are_checked_before_anything_is_written(sandbox, capsys, args, words):
    before = snapshot(sandbox)
    rc, _, err = run_cli(capsys, "train", "--set", f"preset={MICRO.name}", "--data", "data", "--out", "newrun", "--quiet",
                         "--max-steps", "1", *args)
    assert_one_line_error(rc, err, *words)
    assert changed(before, snapshot(sandbox)) == set()


def test_train_loss_weights_that_are_no_weights_end_at_parse_time(sandbox, capsys):
    before = snapshot(sandbox)
    for argv in (["--loss-weights", "rgb"], ["--set", "loss_weights=rgb"]):
        with pytest.raises(SystemExit) as ended:
            run_cli(capsys, "train", "--set", f"preset={MICRO.name}", "--data", "data", "--out", "newrun", *argv)
        assert ended.value.code == 2 and "loss" in capsys.readouterr().err
    assert changed(before, snapshot(sandbox)) == set()


def test_train_with_missing_data_leaves_no_run_folder(sandbox, capsys):
    before = snapshot(sandbox)
    rc, _, err = run_cli(capsys, "train", "--set", f"preset={MICRO.name}", "--data", "nowhere", "--out", "newrun", "--quiet")
    assert_one_line_error(rc, err, "nowhere")
    assert changed(before, snapshot(sandbox)) == set()


def test_train_out_inside_the_data_is_refused(sandbox, capsys):
    before = snapshot(sandbox)
    rc, _, err = run_cli(capsys, "train", "--set", f"preset={MICRO.name}", "--data", "data", "--out", "data/run", "--quiet")
    assert_one_line_error(rc, err, "input")
    assert changed(before, snapshot(sandbox)) == set()


def test_resume_without_a_checkpoint_errors(sandbox, capsys):
    (sandbox / "empty_run").mkdir()
    before = snapshot(sandbox)
    rc, _, err = run_cli(capsys, "train", "--set", f"preset={MICRO.name}", "--data", "data", "--out", "empty_run", "--resume",
                         "--quiet")
    assert_one_line_error(rc, err, "no checkpoint", "drop --resume")
    assert changed(before, snapshot(sandbox)) == set()


def test_resume_falls_back_to_the_newest_intact_checkpoint(sandbox, capsys):
    latest = sandbox / "run" / "checkpoint-000002" / "transformer" / "diffusion_pytorch_model.safetensors"
    latest.write_bytes(latest.read_bytes()[:1000])  # truncated, as by a full disk
    rc, out, err = run_cli(capsys, "train", "--set", f"preset={MICRO.name}", "--data", "data", "--out", "run", "--resume",
                           "--max-steps", "3", "--ckpt-every", "0", "--set", "val_every=0", "--quiet")
    assert rc == 0, err
    assert "checkpoint-000002" in out and "damaged" in out and "resuming from checkpoint-000001 (step 1)" in out
    state = json.loads((sandbox / "run" / "checkpoint-000003" / "trainer_state.json").read_text())
    assert state["step"] == 3


def test_diverging_training_stops_with_the_step_and_keeps_the_checkpoints(sandbox, capsys):
    rc, _, err = run_cli(capsys, "train", "--set", f"preset={MICRO.name}", "--data", "data", "--out", "run", "--resume",
                         "--max-steps", "50", "--set", "lr=1e30", "--set", "warmup_steps=0", "--ckpt-every", "1",
                         "--set", "val_every=0", "--quiet")
    assert_one_line_error(rc, err, "diverged at step", "last good checkpoint")
    step = int(err.split("diverged at step ")[1].split(":")[0])
    ckpts = sorted(p.name for p in (sandbox / "run").glob("checkpoint-*"))
    assert ckpts[-1] == f"checkpoint-{step - 1:06d}"  # nothing saved from the bad step
    from safetensors.torch import load_file

    weights = load_file(str(sandbox / "run" / ckpts[-1] / "transformer" / "diffusion_pytorch_model.safetensors"))
    assert all(bool(w.isfinite().all()) for w in weights.values())


# --------------------------------------------------------------------------- predict


@pytest.mark.parametrize("device,words", [("bogus", ["bogus", "not a torch device"]),
                                          ("cuda", ["CUDA is not available"]), ("cuda:7", ["cuda:7"])])
def test_predict_device(sandbox, capsys, device, words):
    import torch

    if device.startswith("cuda") and torch.cuda.is_available() and device == "cuda":
        pytest.skip("this machine has CUDA; the case is a machine without it")
    before = snapshot(sandbox)
    rc, _, err = run_cli(capsys, "predict", "--checkpoint", "ckpt", "--episode", "data/Synthetic-v0/0", "--out", "pred",
                         "--device", device)
    assert_one_line_error(rc, err, *words)
    assert changed(before, snapshot(sandbox)) == set()


@pytest.mark.parametrize("damage", ["config-other-preset", "config-missing-key", "inference-config-missing-key",
                                    "weights-truncated"])
def test_damaged_checkpoint(sandbox, capsys, damage):
    ckpt = sandbox / "ckpt"
    cfg = ckpt / "transformer" / "config.json"
    if damage == "config-other-preset":
        d = json.loads(cfg.read_text())
        d["backbone_config"]["num_layers"] = 5
        cfg.write_text(json.dumps(d))
        words = ["num_layers"]
    elif damage == "config-missing-key":
        d = json.loads(cfg.read_text())
        del d["backbone_config"]
        cfg.write_text(json.dumps(d))
        words = ["backbone_config"]
    elif damage == "inference-config-missing-key":
        d = json.loads((ckpt / "tesseract4d_config.json").read_text())
        del d["model_space"]
        (ckpt / "tesseract4d_config.json").write_text(json.dumps(d))
        words = ["model_space"]
    else:
        w = ckpt / "transformer" / "diffusion_pytorch_model.safetensors"
        w.write_bytes(w.read_bytes()[:500])
        words = ["corrupt or truncated"]
    before = snapshot(sandbox)
    rc, _, err = run_cli(capsys, "predict", "--checkpoint", "ckpt", "--episode", "data/Synthetic-v0/0", "--out", "pred",
                         "--steps", "1")
    assert_one_line_error(rc, err, *words)
    assert changed(before, snapshot(sandbox)) == set()


# --------------------------------------------------------------------------- damaged shards


def _damage(path: Path, how: str) -> None:
    if how == "truncated":
        data = path.read_bytes()
        path.write_bytes(data[: len(data) // 2])
    elif how in ("byte-flipped", "pose-bit-flipped"):
        data = bytearray(path.read_bytes())
        with h5py.File(path, "r") as f:
            name = "cameras/close/depth_m" if how == "byte-flipped" else "cameras/close/T_world_cam"
            offset = f[name].id.get_chunk_info(0).byte_offset
        if how == "byte-flipped":
            for k in range(16):  # inside the first (compressed) depth chunk
                data[offset + 8 + k] ^= 0xFF
        else:
            data[offset + 3] ^= 0x10  # one bit of a stored (uncompressed) camera pose
        path.write_bytes(bytes(data))
    else:
        with h5py.File(path, "r+") as f:
            del f["cameras/close/depth_m"]


COMMANDS = {
    "dataset check": lambda sb, p: ["dataset", "check", "data"],
    "train": lambda sb, p: ["train", "--set", f"preset={MICRO.name}", "--data", "data", "--out", "newrun", "--max-steps", "1",
                            "--quiet"],
    "predict": lambda sb, p: ["predict", "--checkpoint", "ckpt", "--episode", p, "--out", "pred", "--steps", "1"],
    "view": lambda sb, p: ["view", p, "--export", "scene.html"],
    "evaluate": lambda sb, p: ["evaluate", p, "--gt", "data/Synthetic-v0/1"],
}


@pytest.mark.parametrize("how", ["truncated", "byte-flipped", "pose-bit-flipped", "array-deleted"])
@pytest.mark.parametrize("command", list(COMMANDS))
def test_damaged_shard_is_named(sandbox, capsys, how, command):
    path = episode_file(sandbox)
    _damage(path, how)
    before = snapshot(sandbox)
    rc, out, err = run_cli(capsys, *COMMANDS[command](sandbox, path))
    if command == "dataset check":
        assert rc == 1 and f"BAD  data/episodes/{ENV}/{path.name}" in out and "1 bad" in out, out + err
    else:
        assert_one_line_error(rc, err, str(Path(path).name))
    assert changed(before, snapshot(sandbox)) == set()


# --------------------------------------------------------------------------- predict's inputs


def _user_files(sb: Path, size: int) -> dict[str, Path]:
    """A first frame as a user's own files: rgb.png, depth.npy (1 m), K.txt, all ``size``²."""
    import imageio.v2 as imageio
    import numpy as np

    imageio.imwrite(sb / "rgb.png", np.full((size, size, 3), 120, np.uint8))
    np.save(sb / "depth.npy", np.ones((size, size), np.float32))
    np.savetxt(sb / "K.txt", [[40.0, 0, size / 2], [0, 40.0, size / 2], [0, 0, 1]])
    return {"--rgb": sb / "rgb.png", "--depth": sb / "depth.npy", "--K": sb / "K.txt"}


@pytest.mark.parametrize("damage,words", [
    ("K-text", ["K.txt", "cannot read K", "3 rows of 3 numbers"]),
    ("K-json-dict", ["K.json", "cannot read K"]),
    ("K-zero-focal", ["K.txt", "focal lengths"]),
    ("rgb-not-an-image", ["--rgb", "notes.txt", "is not an image file"]),
    ("depth-negative", ["depth.npy", "depth must be finite metres >= 0"]),
    ("depth-nan", ["depth.npy", "depth must be finite metres >= 0"]),
    ("normal-shape", ["--normal", "normal.npy", "expected finite (H, W, 3)"]),
])
def test_predict_from_unreadable_user_files_says_what_each_takes(sandbox, capsys, damage, words):
    """Each of a user's first-frame files that cannot be a first frame is refused in one line naming
    the file and the form it takes, before the model samples anything."""
    import numpy as np

    files = _user_files(sandbox, MICRO.width)
    extra = []
    if damage == "K-text":
        files["--K"].write_text("hello\n")
    elif damage == "K-json-dict":
        files["--K"] = sandbox / "K.json"
        files["--K"].write_text(json.dumps({"fx": 1}))
    elif damage == "K-zero-focal":
        np.savetxt(files["--K"], np.diag([0.0, 40.0, 1.0]))
    elif damage == "rgb-not-an-image":
        files["--rgb"] = sandbox / "notes.txt"
    elif damage == "depth-negative":
        np.save(files["--depth"], -np.ones((MICRO.height, MICRO.width), np.float32))
    elif damage == "depth-nan":
        np.save(files["--depth"], np.full((MICRO.height, MICRO.width), np.nan, np.float32))
    else:
        np.save(sandbox / "normal.npy", np.zeros((4, 4, 3), np.float32))
        extra = ["--normal", "normal.npy"]
    before = snapshot(sandbox)
    rc, _, err = run_cli(capsys, "predict", "--checkpoint", "ckpt", *[x for kv in files.items() for x in kv], *extra,
                         "--instruction", "push", "--out", "pred", "--steps", "1")
    assert_one_line_error(rc, err, *words)
    assert changed(before, snapshot(sandbox)) == set()


@pytest.mark.parametrize("argv,said", [
    (["--steps", "0"], "argument --steps: must be a whole number >= 1, got '0'"),
    (["--num-frames", "0"], "argument --num-frames: must be a whole number >= 1"),
    (["--num-samples", "0"], "argument --num-samples: must be a whole number >= 1"),
    (["--draws", "0"], "argument --draws: must be a whole number >= 1 (1: a single draw)"),
    (["--text-guidance", "-1"], "argument --text-guidance: must be a finite number > 0 (1: no guidance)"),
    (["--image-guidance", "0"], "argument --image-guidance: must be a finite number > 0"),
    (["--sample-seed", "-1"], "argument --sample-seed: must be a whole number in 0..4294967295"),
])
def test_predict_numbers_are_refused_before_any_work(sandbox, capsys, argv, said):
    """A number no sampler can use ends at once (argparse's exit 2), not as the preset's value in disguise
    (``--steps 0`` once sampled the preset's steps) or a traceback after sampling."""
    before = snapshot(sandbox)
    with pytest.raises(SystemExit) as ended:
        cli.main(["predict", "--checkpoint", "ckpt", "--episode", "data/Synthetic-v0/0", "--out", "pred", *argv])
    assert ended.value.code == 2 and said in capsys.readouterr().err
    assert changed(before, snapshot(sandbox)) == set()


def test_predict_task_seed_outside_the_simulators_range_is_refused(sandbox, capsys):
    with pytest.raises(SystemExit) as ended:
        cli.main(["predict", "--task", "PushCube-v1", "--seed", "-1", "--out", "pred"])
    assert ended.value.code == 2 and "argument --seed: must be a whole number in 0..4294967295" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        cli.main(["demo", "--headless", "--seed", "-1"])
    assert "argument --seed: must be a whole number in 0..4294967295" in capsys.readouterr().err


def test_what_is_not_an_episode_or_a_checkpoint_is_named_with_the_fix(sandbox, capsys):
    """A user's text file is not called a damaged episode; a folder of several episodes names the form
    of one (a group's future included); a file is not 'not found' as a checkpoint."""
    rc, _, err = run_cli(capsys, "predict", "--checkpoint", "ckpt", "--episode", "notes.txt", "--out", "pred")
    assert_one_line_error(rc, err, "notes.txt is not an episode file (not HDF5)")
    assert "Delete" not in err
    rc, _, err = run_cli(capsys, "predict", "--checkpoint", "ckpt", "--episode", "data", "--out", "pred")
    assert_one_line_error(rc, err, "holds 2 episodes", "<seed>_k<K>", f"data/{ENV}/0")
    rc, _, err = run_cli(capsys, "predict", "--checkpoint", "notes.txt", "--episode", "data/Synthetic-v0/0",
                         "--out", "pred")
    assert_one_line_error(rc, err, "checkpoint notes.txt is a file, not a folder")


def test_the_samples_of_predict_are_named_to_the_commands_after_it(sandbox, capsys):
    """`predict --num-samples 2` writes a folder per sample; reconstruct, evaluate and view on the parent
    name the samples' folders instead of saying it holds no episodes."""
    rc, out, err = run_cli(capsys, "predict", "--checkpoint", "ckpt", "--episode", "data/Synthetic-v0/0", "--out", "pred",
                           "--steps", "1", "--num-samples", "2")
    assert rc == 0, err
    assert "pred/sample_00" in out.splitlines()[-1]
    for argv in (["reconstruct", "pred", "--out", "recon"], ["view", "pred", "--export", "scene.html"],
                 ["evaluate", "pred", "--gt", "data/Synthetic-v0/0"]):
        rc, _, err = run_cli(capsys, *argv)
        assert_one_line_error(rc, err, "holds 2 samples of `tesseract4d predict --num-samples`", "pred/sample_00")


def test_view_export_refuses_the_options_only_the_served_viewer_uses(sandbox, capsys):
    before = snapshot(sandbox)
    for extra, flag in ((["--compare", "data/Synthetic-v0/1"], "--compare"), (["--metrics", "notes.txt"], "--metrics"),
                        (["--compare", "data/Synthetic-v0/1", "--labels", "a", "b"], "--compare, --labels")):
        rc, _, err = run_cli(capsys, "view", "data/Synthetic-v0/0", "--export", "scene.html", *extra)
        assert_one_line_error(rc, err, "--export records PATH alone", flag)
    assert changed(before, snapshot(sandbox)) == set()


# --------------------------------------------------------------------------- viewer


def _start_viewer(sb: Path, *extra: str) -> tuple[subprocess.Popen, str, str]:
    proc = subprocess.Popen([sys.executable, "-m", "tesseract4d.cli", "view", str(episode_file(sb)), "--port", "0", *extra],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=sb,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    line = proc.stdout.readline()
    assert line.startswith("viewer: http://"), line + proc.stderr.read()
    return proc, line.split()[1], line


@pytest.mark.parametrize("stop", [signal.SIGINT, signal.SIGTERM])
def test_viewer_survives_malformed_requests_and_stops_cleanly(sandbox, stop):
    import urllib.request

    proc, url, _ = _start_viewer(sandbox)
    try:
        host, port = url.split("//")[1].rstrip("/").rsplit(":", 1)
        garbage = [b"\x00\xff\xfe garbage\r\n\r\n", b"GET / HTTP/9.9\r\nHost: x\r\n\r\n",
                   b"GET / HTTP/1.1\r\nUpgrade: websocket\r\nConnection: Upgrade\r\nSec-WebSocket-Key: !!\r\n"
                   b"Sec-WebSocket-Version: 13\r\n\r\n\x81\xff" + os.urandom(64),
                   b"GET /" + b"a" * 70000 + b" HTTP/1.1\r\n\r\n"]
        for payload in garbage:
            with socket.create_connection((host, int(port)), timeout=5) as s:
                try:
                    s.sendall(payload)
                    s.recv(1024)
                except OSError:
                    pass
        with urllib.request.urlopen(url, timeout=10) as page:  # still serving
            assert b"<html" in page.read().lower()
    finally:
        proc.send_signal(stop)
        rc = proc.wait(timeout=60)
    err = proc.stderr.read()
    assert rc == (130 if stop == signal.SIGINT else 143), err
    assert "Traceback" not in err and ("interrupted" if stop == signal.SIGINT else "terminated") in err


def test_a_viewer_stopped_as_soon_as_it_prints_its_url_stops_cleanly(sandbox):
    """A supervisor may stop the viewer the moment it reports its URL: SIGTERM then is the same clean stop."""
    proc, _, _ = _start_viewer(sandbox)
    proc.send_signal(signal.SIGTERM)
    rc = proc.wait(timeout=60)
    err = proc.stderr.read()
    assert rc == 143 and "Traceback" not in err and "terminated" in err, (rc, err)


def test_viewer_on_all_interfaces_warns(sandbox):
    proc, _, _ = _start_viewer(sandbox, "--host", "0.0.0.0")
    try:
        time.sleep(0.5)
    finally:
        proc.send_signal(signal.SIGTERM)
        proc.wait(timeout=60)
    err = proc.stderr.read()
    assert "reachable from the network" in err and "0.0.0.0" in err



# --------------------------------------------------------------------------- links below an output


def test_reconstruct_never_writes_or_deletes_through_a_linked_subfolder(sandbox, capsys):
    """`out/frames -> elsewhere/`: a rerun (with or without --no-ply) is refused before any work, and
    the linked folder's files stay as they were."""
    rc, _, err = run_cli(capsys, "reconstruct", "data/Synthetic-v0/0", "--out", "out", "--no-refine", "--no-mesh", "--quiet")
    assert rc == 0, err
    elsewhere = sandbox / "elsewhere"
    elsewhere.mkdir()
    for p in (sandbox / "out" / "frames").iterdir():
        (elsewhere / p.name).write_text(f"the user's own {p.name}")
    shutil.rmtree(sandbox / "out" / "frames")
    (sandbox / "out" / "frames").symlink_to(elsewhere, target_is_directory=True)
    before = snapshot(sandbox / "elsewhere")
    for extra in ([], ["--no-ply"], ["--overwrite"]):
        rc, _, err = run_cli(capsys, "reconstruct", "data/Synthetic-v0/1", "--out", "out", "--no-refine", "--no-mesh",
                             "--quiet", *extra)
        assert_one_line_error(rc, err, "out/frames", "symbolic link")
        assert snapshot(sandbox / "elsewhere") == before
        assert (sandbox / "out" / "frames").is_symlink()


def test_output_policy_refuses_a_link_made_below_the_output_while_the_command_runs(tmp_path):
    from tesseract4d.errors import UserError
    from tesseract4d.outputs import OutputDir

    out, elsewhere = tmp_path / "out", tmp_path / "elsewhere"
    elsewhere.mkdir()
    (elsewhere / "a.txt").write_text("foreign")
    with OutputDir(out, "demo") as stage:
        (stage / "sub").mkdir()
        (stage / "sub" / "a.txt").write_text("ours")
    with pytest.raises(UserError, match="symbolic link"):
        with OutputDir(out, "demo") as stage:  # passes the start; the link appears before the commit
            shutil.rmtree(out / "sub")
            (out / "sub").symlink_to(elsewhere, target_is_directory=True)
            (stage / "b.txt").write_text("ours")
    assert (elsewhere / "a.txt").read_text() == "foreign" and not (elsewhere / "b.txt").exists()


def test_a_crafted_marker_cannot_name_files_outside_the_output(tmp_path):
    from tesseract4d.errors import UserError
    from tesseract4d.outputs import OutputDir

    victim = tmp_path / "victim.txt"
    victim.write_text("keep me")
    out = tmp_path / "out"
    out.mkdir()
    (out / "mine.txt").write_text("a foreign file, so the commit goes file by file")
    (out / MARKER).write_text(json.dumps({"command": "demo", "version": 1, "files": ["../victim.txt"]}))
    with pytest.raises(UserError, match="not a file inside it"):
        with OutputDir(out, "demo") as stage:
            (stage / "new.txt").write_text("x")
    assert victim.read_text() == "keep me"


# --------------------------------------------------------------------------- two runs on one output


def test_a_second_run_on_an_output_being_written_refuses_and_names_the_first(sandbox, capsys):
    """While one run stages `out`, another run writing it refuses (naming the first's pid); neither
    calls the other's files foreign nor its live stage "killed"."""
    script = ("import sys, time\nfrom tesseract4d.outputs import OutputDir\n"
              "with OutputDir('out', 'reconstruct') as stage:\n"
              "    (stage / 'recon4d.npz').write_text('first')\n    print('staged', flush=True)\n"
              "    sys.stdin.readline()\n")
    first = subprocess.Popen([sys.executable, "-c", script], cwd=sandbox, stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                             text=True, env=dict(os.environ, PYTHONPATH=f"{REPO}{os.pathsep}{os.environ.get('PYTHONPATH', '')}"))
    try:
        assert first.stdout.readline().strip() == "staged"
        rc, _, err = run_cli(capsys, "reconstruct", "data/Synthetic-v0/0", "--out", "out", "--no-refine", "--no-mesh",
                             "--quiet")
        assert_one_line_error(rc, err, "out", "another run", f"pid {first.pid}")
        assert "killed" not in err
    finally:
        first.communicate("\n", timeout=60)
    assert first.returncode == 0
    assert (sandbox / "out" / "recon4d.npz").read_text() == "first"
    assert not list(sandbox.glob(".out.*"))  # no stage left behind
    rc, _, err = run_cli(capsys, "reconstruct", "data/Synthetic-v0/0", "--out", "out", "--no-refine", "--no-mesh", "--quiet")
    assert rc == 0, err  # the next run takes over


def test_a_killed_runs_stage_does_not_block_the_next_run(sandbox, capsys):
    """A run killed outright holds no lock any more: the next run names its stage as a killed run's
    leftover and writes the output."""
    script = ("import os\nfrom tesseract4d.outputs import OutputDir\n"
              "with OutputDir('out', 'reconstruct') as stage:\n    os.kill(os.getpid(), 9)\n")
    proc = subprocess.run([sys.executable, "-c", script], cwd=sandbox,
                          env=dict(os.environ, PYTHONPATH=f"{REPO}{os.pathsep}{os.environ.get('PYTHONPATH', '')}"))
    assert proc.returncode == -9
    (left,) = sandbox.glob(".out.tmp-*")
    rc, _, err = run_cli(capsys, "reconstruct", "data/Synthetic-v0/0", "--out", "out", "--no-refine", "--no-mesh", "--quiet")
    assert rc == 0, err
    assert f"{left.name} is a staging folder" in err and "killed" in err and left.is_dir()


# --------------------------------------------------------------------------- episode content


def _set_array(path: Path, name: str, edit) -> None:
    """Rewrite one array of an episode file in place (h5py recomputes its checksums)."""
    import numpy as np

    with h5py.File(path, "r+") as f:
        data = f[name][()]
        data = edit(np.array(data))
        f[name][...] = data


BAD_CONTENT = {
    "depth-negative": ("cameras/close/depth_m", lambda a: a * 0 - 0.5, ["depth_m", ">= 0"]),
    "normal-short": ("cameras/close/normal_cam", lambda a: a * 0.5, ["normal_cam", "unit", "0.500"]),
    "normal-nan": ("cameras/close/normal_cam", lambda a: a * float("nan"), ["normal_cam", "NaN"]),
    "K-zero": ("cameras/close/K", lambda a: a * 0, ["K", "positive focal lengths"]),
    "pose-not-rigid": ("cameras/close/T_world_cam", lambda a: a * 2, ["T_world_cam", "rigid"]),
}


def _bad_episode(sb: Path, how: str) -> Path:
    path = episode_file(sb)
    if how == "segmentation-unknown-id":
        with h5py.File(path, "r+") as f:
            g = f["cameras/close"]
            g.create_dataset("segmentation", data=g["depth_m"][()].astype("int32") * 0 + 99)
            g.attrs["seg_id_to_name"] = json.dumps({"0": "background", "17": "ground"})
    else:
        name, edit, _ = BAD_CONTENT[how]
        _set_array(path, name, edit)
    return path


CONTENT_WORDS = {**{k: v[2] for k, v in BAD_CONTENT.items()}, "segmentation-unknown-id": ["segmentation ids [99]"]}


@pytest.mark.parametrize("how", list(CONTENT_WORDS))
def test_dataset_check_validates_content(sandbox, capsys, how):
    path = _bad_episode(sandbox, how)
    rc, out, err = run_cli(capsys, "dataset", "check", "data")
    assert rc == 1, out + err
    bad = [line for line in out.splitlines() if line.startswith("BAD")]
    assert len(bad) == 1 and path.name in bad[0], out
    for w in CONTENT_WORDS[how]:
        assert w in bad[0], (w, bad[0])
    assert "1 ok, 1 bad" in out


@pytest.mark.parametrize("how", ["K-zero", "normal-nan", "depth-negative"])
@pytest.mark.parametrize("command", ["predict", "reconstruct", "train"])
def test_commands_that_read_episodes_refuse_bad_content(sandbox, capsys, how, command):
    """predict --episode, reconstruct and train apply `dataset check`'s validation when they read, so a
    NaN normal never reaches a training step and K = 0 never reaches a prediction."""
    path = _bad_episode(sandbox, how)
    argv = {"predict": ["predict", "--checkpoint", "ckpt", "--episode", "data/Synthetic-v0/0", "--out", "pred", "--steps", "1"],
            "reconstruct": ["reconstruct", "data/Synthetic-v0/0", "--out", "recon", "--no-refine", "--no-mesh", "--quiet"],
            "train": ["train", "--preset", MICRO.name, "--data", "data", "--out", "newrun", "--quiet", "--max-steps",
                      "1", "--val-every", "0"]}[command]
    before = snapshot(sandbox)
    rc, _, err = run_cli(capsys, *argv)
    assert_one_line_error(rc, err, path.name, "dataset check", *CONTENT_WORDS[how][:1])
    assert changed(before, snapshot(sandbox)) == set()


def test_a_wrongly_shaped_rgb_is_named_as_rgb():
    import numpy as np

    ep = synthetic_episode(0)
    cam = ep.cameras["close"]
    cam.rgb = np.zeros((cam.rgb.shape[0], cam.rgb.shape[1], cam.rgb.shape[2] + 1, 3), np.uint8)
    with pytest.raises(df.DatasetFormatError, match=r"close: rgb must have shape \(8, 32, 32, 3\)"):
        ep.validate()
    ep = synthetic_episode(0)
    ep.cameras["close"].normal_cam = ep.cameras["close"].normal_cam[:, :-1]
    with pytest.raises(df.DatasetFormatError, match="normal_cam must have shape"):
        ep.validate()


# --------------------------------------------------------------------------- autoencoder file


def test_a_truncated_autoencoder_is_called_corrupt_not_another_one(tmp_path):
    import torch

    from tesseract4d.errors import UserError
    from tesseract4d.model.autoencoder import (
        RGBDNAutoencoder, autoencoder_hash, get_autoencoder_preset, save_autoencoder,
    )
    from tesseract4d.model.latent_checkpoint import AUTOENCODER_DIR, checkpoint_autoencoder

    torch.manual_seed(0)
    folder = tmp_path / "ckpt" / AUTOENCODER_DIR
    save_autoencoder(RGBDNAutoencoder(get_autoencoder_preset("ae-test")), folder)
    entry = {"hash": autoencoder_hash(folder), "dir": AUTOENCODER_DIR}
    assert checkpoint_autoencoder(tmp_path / "ckpt", entry) == folder
    weights = folder / "model.safetensors"
    whole = weights.read_bytes()
    for cut in (len(whole) - 1, len(whole) // 2, 100, 4):
        weights.write_bytes(whole[:cut])
        with pytest.raises(UserError, match="corrupt or truncated") as e:
            checkpoint_autoencoder(tmp_path / "ckpt", entry)
        assert "trained on" not in str(e.value) and "model.safetensors" in str(e.value)


# --------------------------------------------------------------------------- instructions


INVALID_UTF8 = b"push the \xff\xfe cube".decode("utf-8", "surrogateescape")  # what Python makes of such argv bytes


def test_predict_refuses_an_instruction_that_is_not_utf8(sandbox, capsys):
    before = snapshot(sandbox)
    rc, _, err = run_cli(capsys, "predict", "--checkpoint", "ckpt", "--episode", "data/Synthetic-v0/0", "--out", "pred",
                         "--steps", "1", "--instruction", INVALID_UTF8)
    assert_one_line_error(rc, err, "--instruction", "not valid UTF-8")
    assert changed(before, snapshot(sandbox)) == set()


def test_predict_refuses_invalid_utf8_from_a_real_shell(sandbox):
    """The bytes as a shell passes them, in a process of its own: one line, exit 2."""
    proc = subprocess.run([sys.executable, "-m", "tesseract4d.cli", "predict", "--checkpoint", "ckpt", "--episode",
                           "data/Synthetic-v0/0", "--out", "pred", "--steps", "1", "--instruction",
                           b"push the \xff cube"], cwd=sandbox, capture_output=True, timeout=300,
                          env=dict(os.environ, PYTHONPATH=f"{REPO}{os.pathsep}{os.environ.get('PYTHONPATH', '')}"))
    err = proc.stderr.decode(errors="replace")
    assert proc.returncode == 2 and "not valid UTF-8" in err and "Traceback" not in err, err
    assert not (sandbox / "pred").exists()


@pytest.mark.parametrize("flag", ["--instruction", "--contrast-instruction"])
def test_demo_refuses_an_instruction_that_is_not_utf8_before_rendering(tmp_path, capsys, flag):
    t0 = time.monotonic()
    rc, _, err = run_cli(capsys, "demo", "--out", tmp_path / "demo", flag, INVALID_UTF8)
    assert_one_line_error(rc, err, flag, "not valid UTF-8")
    assert time.monotonic() - t0 < 10 and not (tmp_path / "demo").exists()  # refused before the scene is rendered
