"""scripts/text_table.py: the text encoder carried as a table of its outputs, and a command run with it."""

from __future__ import annotations

import json

import pytest
import torch
from project_scripts import load_script
from synthetic_scene import write_segmented_dataset

from tesseract4d.model.autoencoder import RGBDNAutoencoder, get_autoencoder_preset, save_autoencoder
from tesseract4d.model.latent_cache import CACHE_FILE, default_cache_dir, ensure_latent_cache
from tesseract4d.model.presets import PRESETS

from test_latent_model import MICRO_LATENT


@pytest.fixture
def cached(tmp_path, monkeypatch):
    monkeypatch.setitem(PRESETS, MICRO_LATENT.name, MICRO_LATENT)
    data = write_segmented_dataset(tmp_path / "data", episodes=2)
    torch.manual_seed(0)
    save_autoencoder(RGBDNAutoencoder(get_autoencoder_preset("ae-test")), tmp_path / "ae")
    ensure_latent_cache(data, tmp_path / "ae")
    return data, tmp_path / "ae"


def test_the_table_encodes_as_the_encoder_and_a_command_trains_with_it(cached, tmp_path):
    import tesseract4d.model.build as build
    from tesseract4d.model.build import build_text_encoder
    from tesseract4d.model.predict import load_pipeline

    tool = load_script("text_table")
    data, ae = cached
    table = tool.make([data], tmp_path / "table", preset=MICRO_LATENT.name)
    texts = tool.wordings([data])
    assert texts == ["push the square to the left", "push the square to the right"]  # no train template writes them
    episodes_only = write_segmented_dataset(tmp_path / "episodes_only", episodes=2)  # no latent cache (distill's data)
    assert tool.wordings([episodes_only]) == texts
    carried = tool.TableEncoder(table).encode(texts)
    own = build_text_encoder(MICRO_LATENT).encode(texts)
    assert carried.shape == own.shape and float((carried - own).abs().max()) < 3e-3
    assert torch.equal((carried != 0).any(-1), (own != 0).any(-1))  # the same tokens, the same padding
    with pytest.raises(SystemExit, match="not in the text table"):
        tool.TableEncoder(table).encode(["stay still"])
    original = build.build_text_encoder
    assert tool.main(["run", str(table), "train", "--preset", MICRO_LATENT.name, "--data", str(data), "--autoencoder",
                      str(ae), "--out", str(tmp_path / "run"), "--max-steps", "1", "--val-every", "0", "--ckpt-every", "0",
                      "--no-progress"]) == 0
    assert build.build_text_encoder is original  # the encoder is the project's again after the command
    assert load_pipeline(tmp_path / "run" / "final").config["text_encoder"]["kind"] == "minilm"


def test_a_run_whose_data_has_other_wordings_stops_before_training(cached, tmp_path):
    tool = load_script("text_table")
    data, ae = cached
    table = tool.make([data], tmp_path / "table", preset=MICRO_LATENT.name)
    cache = default_cache_dir(data, "close") / CACHE_FILE
    meta = json.loads(cache.read_text())
    meta["episodes"][0]["instruction"] = "stay still"  # as if the data had another sentence
    cache.write_text(json.dumps(meta))
    with pytest.raises(SystemExit, match="not in the table"):
        tool.main(["run", str(table), "train", "--preset", MICRO_LATENT.name, "--data", str(data), "--autoencoder",
                   str(ae), "--out", str(tmp_path / "run"), "--max-steps", "1"])
    assert not (tmp_path / "run").exists()
