"""Named training recipes: the options that trained the shipped models, as config field values.

`tesseract4d train --recipe v2 --data ... --out ...` starts from ``TRAIN["v2"]`` instead of a dozen
flags copied from a model card; flags and ``--set NAME=VALUE`` change a recipe, and
``--recipe-from CHECKPOINT`` reads the recipe a checkpoint records in its ``tesseract4d_config.json``.
A recipe holds training options only: the data, the output folder and the weights a run starts from
(``--init``, ``--autoencoder``, ``--teacher``) are the user's, named on the command line.

Each table maps a recipe name to field values of one trainer's config dataclass:
``TRAIN`` (`train`), ``AUTOENCODER`` (`train-autoencoder`), ``DISTILL`` (`distill`) and ``IDM``
(`train-idm`). ``tests/model/test_recipes.py`` checks them against what the shipped checkpoints record.
"""

from __future__ import annotations

# The shipped v2's last training stage (its card, "Training"): started from the previous v2 with
# `--init`, on the tabletop and cube-task groups, 1,800 steps of batch 32 on one GPU in bf16.
TRAIN: dict[str, dict] = {
    "v2": {
        "preset": "latent-128",
        "condition_noise": 0.1,
        "moving_weight": 2.0,
        "object_weight": 2.0,
        "scene_object_weight": 40.0,
        "time_logit_normal": 1.0,
        "group_batches": True,
        "counterfactual_swap": 0.5,
        "rephrase": 0.8,
        "text_noise": 0.5,
        "text_dropout": 0.1,
        "lr": 1e-4,
        "warmup_steps": 200,
        "batch_size": 32,
        "max_steps": 1800,
        "ema_decay": 0.999,
        "ckpt_every": 500,
        "val_every": 0,
    },
}

# The shipped autoencoder (v2's card, "Training" 1 and 4): trained from scratch, then its decoder
# alone fine-tuned on v2's latents with robot/object pixels x10 and RGB x2.
AUTOENCODER: dict[str, dict] = {
    "ae-f8c32": {
        "preset": "ae-f8c32",
        "max_steps": 20000,
        "batch_size": 8,
        "lr": 3e-4,
    },
    "ae-f8c32-decoder": {
        "decoder_only": True,
        "object_weight": 10.0,
        "rgb_weight": 2.0,
        "lr": 2e-4,
        "warmup_steps": 100,
        "max_steps": 9000,
        "batch_size": 8,
    },
}

# The shipped v2-2step (its card): the 720-pair student of v2, 1,800 steps of batch 4 at lr 3e-4 on
# whole counterfactual groups, with the swap and rephrasing of v2's recipe at half strength.
DISTILL: dict[str, dict] = {
    "v2-2step": {
        "student_steps": 2,
        "num_pairs": 720,
        "groups": True,
        "group_batches": True,
        "counterfactual_swap": 0.5,
        "rephrase": 0.5,
        "max_steps": 1800,
        "batch_size": 4,
        "lr": 3e-4,
    },
}

# The closed loop's IDM (docs/closed_loop.md, "The inverse dynamics model"): `train-idm --data data/idm_train128 --max-steps 3000`
# on 128² renders of every simulator step; `bc` is its behaviour-cloning twin without the future.
IDM: dict[str, dict] = {
    "idm": {"max_steps": 3000},
    "bc": {"max_steps": 3000, "use_future": False},
}
