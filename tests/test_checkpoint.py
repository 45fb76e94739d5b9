"""The checkpoint format (tesseract4d/model/checkpoint.py): versions, scheduler, transformer loading."""

from __future__ import annotations

import json
import shutil

import pytest
import torch

from tesseract4d.errors import UserError
from tesseract4d.model import checkpoint as ck
from tesseract4d.model.checkpoint import TINY_CHECKPOINT
from tesseract4d.model.presets import preset_from_dict


@pytest.fixture
def tiny_copy(tmp_path):
    """The tiny checkpoint copied into tmp_path (its files may then be edited)."""
    return shutil.copytree(TINY_CHECKPOINT, tmp_path / "tiny")


def _edit_config(folder, **changes):
    path = folder / ck.INFERENCE_CONFIG_FILE
    path.write_text(json.dumps({**json.loads(path.read_text()), **changes}))


def test_tiny_checkpoint_is_the_current_version_with_its_scheduler():
    cfg = ck.read_inference_config(TINY_CHECKPOINT)
    assert cfg["format"] == ck.FORMAT and cfg["version"] == ck.FORMAT_VERSION
    scheduler = ck.load_scheduler(TINY_CHECKPOINT, cfg)
    assert (TINY_CHECKPOINT / ck.SCHEDULER_DIR / ck.SCHEDULER_CONFIG_FILE).is_file()
    assert scheduler.config.num_train_timesteps == 1000 and scheduler.config.shift == 1.0


def test_transformer_loads_with_from_pretrained_and_holds_the_saved_weights():
    from safetensors.torch import load_file

    cfg = ck.read_inference_config(TINY_CHECKPOINT)
    preset = preset_from_dict(cfg["preset"])
    model = ck.load_transformer(TINY_CHECKPOINT, preset, {"rgb": 3, "depth": 1, "normal": 3})
    saved = load_file(str(TINY_CHECKPOINT / ck.TRANSFORMER_DIR / ck.WEIGHTS_FILE))
    loaded = model.state_dict()
    assert saved.keys() == loaded.keys() and all(torch.equal(saved[k].float(), loaded[k]) for k in saved)
    assert all(v.dtype == torch.float32 for v in loaded.values())  # float16 on disk, float32 in memory
    assert not model.training
    with pytest.raises(UserError, match="modality channels"):
        ck.load_transformer(TINY_CHECKPOINT, preset, {"rgb": 4, "depth": 4, "normal": 4})


def test_a_newer_version_or_another_format_fails_with_the_fix(tiny_copy):
    _edit_config(tiny_copy, version=ck.FORMAT_VERSION + 1)
    with pytest.raises(UserError, match=f"version {ck.FORMAT_VERSION + 1}.*update tesseract4d"):
        ck.read_inference_config(tiny_copy)
    _edit_config(tiny_copy, format="something-else", version=ck.FORMAT_VERSION)
    with pytest.raises(UserError, match=f"not a {ck.FORMAT} config"):
        ck.read_inference_config(tiny_copy)
    (tiny_copy / ck.INFERENCE_CONFIG_FILE).write_text("{")
    with pytest.raises(UserError, match="corrupt"):
        ck.read_inference_config(tiny_copy)


def test_version_1_without_a_scheduler_samples_with_the_training_sampler(tiny_copy):
    from tesseract4d.model.pipeline import make_scheduler

    shutil.rmtree(tiny_copy / ck.SCHEDULER_DIR)
    _edit_config(tiny_copy, version=1)
    cfg = ck.read_inference_config(tiny_copy)
    assert dict(ck.load_scheduler(tiny_copy, cfg).config) == dict(make_scheduler().config)
    _edit_config(tiny_copy, version=2)
    with pytest.raises(UserError, match="scheduler_config.json is missing"):
        ck.load_scheduler(tiny_copy, ck.read_inference_config(tiny_copy))
