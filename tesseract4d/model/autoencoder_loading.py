"""Which network a saved autoencoder folder rebuilds into: the plain RGB-D-N autoencoder, or the one
whose decoder also reads the given first frame (model/first_frame_decoder.py), as its config says."""

from __future__ import annotations

import os
from pathlib import Path

from tesseract4d.model.autoencoder import RGBDNAutoencoder, load_weights, read_autoencoder_config
from tesseract4d.model.first_frame_decoder import FirstFrameAutoencoder


def load_autoencoder(folder: str | os.PathLike) -> RGBDNAutoencoder:
    """Rebuild a saved autoencoder (eval mode, fp32)."""
    folder = Path(folder)
    config = read_autoencoder_config(folder)
    if config.first_frame_injection is not None:
        model = FirstFrameAutoencoder(config)
    else:
        model = RGBDNAutoencoder(config)
    model.load_state_dict(load_weights(folder))
    return model.eval().requires_grad_(False)
