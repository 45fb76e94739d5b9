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
                              "20", "--out", str(out), "--resolution", "32", "--frames", "4", "--no-previews", "--quiet"],
                             cwd=REPO, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        deadline = time.time() + 60
        while not (out / df.INFO_FILE).is_file() and time.time() < deadline:
            time.sleep(0.05)
        assert first.poll() is None and (out / df.LOCK_FILE).read_text().strip() == str(first.pid)
        rc, _, err = run_cli(capsys, "datagen", "--tasks", "PushCube-v1", "--episodes", "20", "--out", out,
                             "--resolution", "32", "--frames", "4", "--no-previews", "--quiet")
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

