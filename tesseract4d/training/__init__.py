"""One training loop for every trainer of the project.

The diffusion trainer (``model/trainer.py``), its reflow student (``model/reflow.py``), the
autoencoder trainer (``model/autoencoder_trainer.py``) and the inverse dynamics trainer
(``policy/idm_trainer.py``) each supply their step and their export; this package owns what they
share, so a run behaves the same whichever command started it:

- ``config.py``: ``TrainingLoopConfig``, the loop's options (steps, minutes, checkpoint cadence, learning
  rate and warm-up, seed, quiet, resume), which every trainer's config extends;
- ``schedule.py``: the learning-rate schedule and ``--max-steps auto``;
- ``checkpoints.py``: checkpoint folders written whole and rotated, optimiser and RNG state without
  pickle, and resuming from the newest intact checkpoint;
- ``loop.py``: the loop itself: stop on Ctrl-C or SIGTERM after the current step (checkpoint and
  export kept, then exit 130 / 143), the non-finite-loss guard, logging.

It sits on the model floor and imports only the contracts below it.
"""
