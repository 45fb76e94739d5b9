"""Networks and codecs of the RGB-D-N video diffusion model (see presets.py for their configurations)."""
