"""scripts/latent_cache_8bit.py: latent caches packed small for another machine and unpacked there
into dataset folders the latent model trains from."""

from __future__ import annotations

import torch
from project_scripts import load_script
from synthetic_scene import write_segmented_dataset

from tesseract4d.model.autoencoder import RGBDNAutoencoder, get_autoencoder_preset, save_autoencoder
from tesseract4d.model.latent_cache import ensure_latent_cache


def test_pack_unpack_round_trip_trains_from_the_unpacked_cache(tmp_path):
    tool = load_script("latent_cache_8bit")
    data = write_segmented_dataset(tmp_path / "data", episodes=3, frames=8)
    torch.manual_seed(0)
    save_autoencoder(RGBDNAutoencoder(get_autoencoder_preset("ae-test")), tmp_path / "ae")
    cache, _ = ensure_latent_cache(data, tmp_path / "ae")
    written = tool.pack([data], tmp_path / "packed", chunk_mb=0.0005)  # several chunks of 500 bytes
    assert len(written) > 2 and all(p.stat().st_size <= 500 for p in written[1:])
    (folder,) = tool.unpack(tmp_path / "packed", tmp_path / "there")
    moved, built = ensure_latent_cache(folder, tmp_path / "ae")  # no episodes there: the cache as it is
    assert not built and len(moved.episodes) == len(cache.episodes) == 3
    for a, b in zip(moved.episodes, cache.episodes):
        assert a.instruction == b.instruction and torch.equal(a.objects, b.objects)
        assert torch.equal(a.scene_objects, b.scene_objects)
        assert float((a.latents.float() - b.latents.float()).abs().max()) <= tool.SCALE / 2 + 1e-3
