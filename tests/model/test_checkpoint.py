"""The checkpoint format (tesseract4d/model/checkpoint.py): versions, scheduler, transformer loading."""

from __future__ import annotations

import json
import shutil

import pytest
import torch

from tesseract4d.errors import UserError
from tesseract4d.model import checkpoint as ck
from tesseract4d.model.checkpoint import SHIPPED_CHECKPOINT, V2_CHECKPOINT
from tesseract4d.model.presets import preset_from_dict


@pytest.fixture
def v2_copy(tmp_path):
    """The v2 checkpoint copied into tmp_path (its files may then be edited)."""
    return shutil.copytree(V2_CHECKPOINT, tmp_path / "v2")


def _edit_config(folder, **changes):
    path = folder / ck.INFERENCE_CONFIG_FILE
    path.write_text(json.dumps({**json.loads(path.read_text()), **changes}))


@pytest.mark.parametrize("checkpoint", [SHIPPED_CHECKPOINT, V2_CHECKPOINT], ids=["default", "v2"])
def test_shipped_checkpoints_are_the_current_version_with_their_scheduler(checkpoint):
    cfg = ck.read_inference_config(checkpoint)
    assert cfg["format"] == ck.FORMAT and cfg["version"] == ck.FORMAT_VERSION
    scheduler = ck.load_scheduler(checkpoint, cfg)
    assert (checkpoint / ck.SCHEDULER_DIR / ck.SCHEDULER_CONFIG_FILE).is_file()
    assert scheduler.config.num_train_timesteps == 1000 and scheduler.config.shift == 1.0


def test_the_default_is_a_one_pass_per_step_student_of_v2():
    cfg = ck.read_inference_config(SHIPPED_CHECKPOINT)
    teacher = ck.read_inference_config(V2_CHECKPOINT)
    from tesseract4d.model.checkpoint import weights_digest

    assert cfg["distilled_from"]["teacher_digest"] == weights_digest(V2_CHECKPOINT)  # the shipped v2's student
    assert cfg["preset"]["text_guidance"] == cfg["preset"]["image_guidance"] == 1.0  # no guidance: one pass
    assert cfg["preset"]["num_steps"] <= 4 < teacher["preset"]["num_steps"]
    assert cfg["autoencoder"]["hash"] == teacher["autoencoder"]["hash"]  # the same autoencoder


def test_v2_skips_guidance_only_at_its_last_low_noise_steps():
    """v2 samples 10 guided steps but its last two (noise 0.11 and 0.001), where guidance changed none of
    the held-out measures (docs/research/sampling.md): 18 network passes per clip instead of 20."""
    from tesseract4d.model.pipeline import make_scheduler
    from tesseract4d.model.presets import preset_from_dict

    preset = preset_from_dict(ck.read_inference_config(V2_CHECKPOINT)["preset"])
    scheduler = make_scheduler()
    scheduler.set_timesteps(preset.num_steps)
    sigmas = [float(s) for s in scheduler.sigmas[:preset.num_steps]]
    assert preset.text_guidance > 1 and preset.num_steps == 10
    assert sum(s < preset.guidance_min_sigma for s in sigmas) == 2 and min(sigmas[:8]) > 0.2


def test_transformer_loads_with_from_pretrained_and_holds_the_saved_weights():
    from safetensors.torch import load_file

    cfg = ck.read_inference_config(V2_CHECKPOINT)
    preset = preset_from_dict(cfg["preset"])
    channels = {"latent": cfg["autoencoder"]["config"]["latent_channels"]}
    model = ck.load_transformer(V2_CHECKPOINT, preset, channels)
    saved = load_file(str(V2_CHECKPOINT / ck.TRANSFORMER_DIR / ck.WEIGHTS_FILE))
    loaded = model.state_dict()
    assert saved.keys() == loaded.keys() and all(torch.equal(saved[k].float(), loaded[k]) for k in saved)
    assert all(v.dtype == torch.float32 for v in loaded.values())  # float16 on disk, float32 in memory
    assert not model.training
    with pytest.raises(UserError, match="modality channels"):
        ck.load_transformer(V2_CHECKPOINT, preset, {"latent": channels["latent"] + 1})


def test_a_newer_version_or_another_format_fails_with_the_fix(v2_copy):
    _edit_config(v2_copy, version=ck.FORMAT_VERSION + 1)
    with pytest.raises(UserError, match=f"version {ck.FORMAT_VERSION + 1}.*update tesseract4d"):
        ck.read_inference_config(v2_copy)
    _edit_config(v2_copy, format="something-else", version=ck.FORMAT_VERSION)
    with pytest.raises(UserError, match=f"not a {ck.FORMAT} config"):
        ck.read_inference_config(v2_copy)
    (v2_copy / ck.INFERENCE_CONFIG_FILE).write_text("{")
    with pytest.raises(UserError, match="corrupt"):
        ck.read_inference_config(v2_copy)


def test_version_1_without_a_scheduler_samples_with_the_training_sampler(v2_copy):
    from tesseract4d.model.pipeline import make_scheduler

    shutil.rmtree(v2_copy / ck.SCHEDULER_DIR)
    _edit_config(v2_copy, version=1)
    cfg = ck.read_inference_config(v2_copy)
    assert dict(ck.load_scheduler(v2_copy, cfg).config) == dict(make_scheduler().config)
    _edit_config(v2_copy, version=2)
    with pytest.raises(UserError, match="scheduler_config.json is missing"):
        ck.load_scheduler(v2_copy, ck.read_inference_config(v2_copy))


def test_a_checkpoint_can_share_the_autoencoder_of_the_one_beside_it(tmp_path):
    """The shipped student reads v2's autoencoder (its config names ../v2/autoencoder) and samples exactly
    as a self-contained copy of it; copies written elsewhere (set-sampler, swap-decoder) carry the
    autoencoder again; a shared checkpoint moved away from its sibling is refused with the fix."""
    from tesseract4d.model.checkpoint_copies import replace_decoder, write_sampler_copy
    from tesseract4d.model.latent_checkpoint import AUTOENCODER_DIR, checkpoint_autoencoder
    from tesseract4d.model.predict import load_pipeline

    pair = tmp_path / "pair"
    v2 = shutil.copytree(V2_CHECKPOINT, pair / "v2")
    shared = shutil.copytree(SHIPPED_CHECKPOINT, pair / SHIPPED_CHECKPOINT.name)
    entry = ck.read_inference_config(shared)["autoencoder"]
    assert entry["dir"] == "../v2/autoencoder" and not (shared / AUTOENCODER_DIR).exists()
    assert checkpoint_autoencoder(SHIPPED_CHECKPOINT, entry).resolve() == (V2_CHECKPOINT / AUTOENCODER_DIR).resolve()
    steps = ck.read_inference_config(shared)["preset"]["num_steps"]
    own = write_sampler_copy(shared, tmp_path / "own", {"num_steps": steps})  # the same sampler, self-contained
    assert (own / AUTOENCODER_DIR / "model.safetensors").is_file()
    first = torch.rand(1, 7, 128, 128, generator=torch.Generator().manual_seed(0)) * 2 - 1

    def sample(folder):
        return load_pipeline(folder, precision="fp32")(first, ["push the purple cube to the left"],
                                                       generator=torch.Generator().manual_seed(1))

    assert torch.equal(sample(shared), sample(own))
    swapped = replace_decoder(shared, v2 / AUTOENCODER_DIR, tmp_path / "swapped")
    for copy in (own, swapped):
        entry = ck.read_inference_config(copy)["autoencoder"]
        assert entry["dir"] == AUTOENCODER_DIR and "shared_with" not in entry
        assert (copy / AUTOENCODER_DIR / "model.safetensors").read_bytes() == (v2 / AUTOENCODER_DIR /
                                                                               "model.safetensors").read_bytes()
    lonely = shutil.copytree(shared, tmp_path / "lonely")
    with pytest.raises(UserError, match="side by side"):
        load_pipeline(lonely)


def test_shipped_checkpoints_record_no_removed_option():
    """v2 no longer carries autoguidance's guide network; neither shipped config names an option this
    version removed (docs/research/removed_features.md)."""
    from tesseract4d.model.presets import REMOVED_FIELDS
    from tesseract4d.model.recipe import REMOVED_LEVERS

    assert not (V2_CHECKPOINT / ck.REMOVED_GUIDE_DIR).exists()
    for checkpoint in (V2_CHECKPOINT, SHIPPED_CHECKPOINT):
        cfg = ck.read_inference_config(checkpoint)
        assert "guide" not in cfg and not set(REMOVED_FIELDS) & set(cfg["preset"])
        assert not set(REMOVED_LEVERS) & set(cfg["recipe"])
        assert "decoder_layers_per_block" not in cfg["autoencoder"]["config"]


def test_a_checkpoint_recording_removed_options_at_their_no_op_values_loads_and_samples_as_before(v2_copy, tmp_path):
    """A checkpoint written before the removals records autoguidance 0 (and its interval), an unused guide
    folder, prediction x0, time shift 1, difference weight 1 and a null decoder depth: it loads and
    samples bit for bit as the shipped one; set-sampler's copy of it leaves the guide folder and the
    removed settings out. Any other value of a removed option is refused with a message that names it."""
    from tesseract4d.model.checkpoint_copies import write_sampler_copy
    from tesseract4d.model.predict import load_pipeline

    cfg = ck.read_inference_config(v2_copy)
    old = {**cfg, "preset": {**cfg["preset"], "autoguidance": 0.0, "autoguidance_min_sigma": 0.5},
           "recipe": {**cfg["recipe"], "prediction": "x0", "time_shift": 1.0, "difference_weight": 1.0},
           "autoencoder": {**cfg["autoencoder"],
                           "config": {**cfg["autoencoder"]["config"], "decoder_layers_per_block": None}},
           "guide": {"source": "an old guide", "bits": 8}}
    (v2_copy / ck.INFERENCE_CONFIG_FILE).write_text(json.dumps(old))
    shutil.copytree(v2_copy / ck.TRANSFORMER_DIR, v2_copy / ck.REMOVED_GUIDE_DIR)  # an unused guide, as v2 had
    first = torch.rand(1, 7, 128, 128, generator=torch.Generator().manual_seed(0)) * 2 - 1

    def sample(folder):
        return load_pipeline(folder, precision="fp32")(first, ["push the purple cube to the left"], num_inference_steps=2,
                                                       generator=torch.Generator().manual_seed(1))

    assert torch.equal(sample(v2_copy), sample(V2_CHECKPOINT))
    copy = write_sampler_copy(v2_copy, tmp_path / "copy", {"draws": 1})
    written = ck.read_inference_config(copy)
    assert not (copy / ck.REMOVED_GUIDE_DIR).exists() and "guide" not in written
    assert "autoguidance" not in written["preset"] and "autoguidance_min_sigma" not in written["preset"]
    for changes, match in ((dict(preset={**old["preset"], "autoguidance": 1.0}), "autoguidance 1.0"),
                           (dict(recipe={**old["recipe"], "prediction": "velocity"}), "predicts 'velocity'")):
        _edit_config(v2_copy, **{**old, **changes})
        with pytest.raises(UserError, match=match):
            load_pipeline(v2_copy)
