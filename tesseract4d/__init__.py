"""tesseract4d: a 4D embodied world model (RGB-D-N video diffusion + 4D reconstruction + viewer).

Importing this package is cheap: heavy dependencies (torch, diffusers, mani_skill, open3d,
viser) are imported inside the functions that need them.
"""

__version__ = "0.1.0"
