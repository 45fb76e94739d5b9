"""Named training recipes (tesseract4d/recipes.py): the shipped models' training options as config
values, equal to what their checkpoints record; `--recipe NAME` and `--recipe-from CHECKPOINT` build
the same config; `train --recipe v2 --max-steps 2` trains."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import pytest

from tesseract4d import recipes
from tesseract4d.cli import build_parser, main
from tesseract4d.cli.config_args import config_from_args, recipe_from_args

ROOT = Path(__file__).resolve().parents[2]
V2 = ROOT / "tesseract4d" / "checkpoints" / "v2"
V2_2STEP = ROOT / "tesseract4d" / "checkpoints" / "v2-2step"


def _saved(checkpoint: Path) -> dict:
    return json.loads((checkpoint / "tesseract4d_config.json").read_text())


def _config(words, argv):
    parser, module = build_parser(words)
    args = parser.parse_args(argv)
    return module, args


def test_every_recipe_names_fields_of_its_config():
    from tesseract4d.cli.distill import DistillConfig
    from tesseract4d.configs import settable_fields
    from tesseract4d.model.autoencoder_trainer import AutoencoderTrainConfig
    from tesseract4d.model.trainer import TrainConfig
    from tesseract4d.policy.idm_trainer import IDMTrainConfig

    for table, cls in ((recipes.TRAIN, TrainConfig), (recipes.AUTOENCODER, AutoencoderTrainConfig),
                       (recipes.DISTILL, DistillConfig), (recipes.IDM, IDMTrainConfig)):
        for name, values in table.items():
            assert set(values) <= set(settable_fields(cls)), (name, set(values) - set(settable_fields(cls)))


def test_v2_recipe_is_what_the_shipped_v2_records():
    saved = _saved(V2)
    recipe = recipes.TRAIN["v2"]
    for key, value in saved["recipe"].items():
        if key in recipe or value not in (0.0, 1.0, False):  # every lever v2 used is in the recipe
            assert recipe[key] == value, key
    training = saved["training"]
    assert (recipe["batch_size"], recipe["lr"], recipe["ema_decay"], recipe["max_steps"]) == (
        training["batch_size"], training["lr"], training["ema_decay"], training["steps"])
    assert recipe["preset"] == saved["preset"]["name"]


def test_train_recipe_v2_and_recipe_from_v2_build_the_same_training():
    from tesseract4d.model.trainer import TrainConfig

    module, args = _config(("train",), ["--recipe", "v2", "--data", "d", "--out", "o"])
    by_name = config_from_args(TrainConfig, args, args.flag_fields,
                               recipe=recipe_from_args(args, module.RECIPES, module.read_recipe))
    _, args = _config(("train",), ["--recipe-from", str(V2), "--data", "d", "--out", "o"])
    from_checkpoint = config_from_args(TrainConfig, args, args.flag_fields,
                                       recipe=recipe_from_args(args, module.RECIPES, module.read_recipe))
    recorded = module.read_recipe(V2)
    assert recorded and {k: getattr(from_checkpoint, k) for k in recorded} == {k: getattr(by_name, k) for k in recorded}
    assert by_name.data == [Path("d")] and by_name.scene_object_weight == 40.0 and by_name.max_steps == 1800
    # flags and --set change a recipe
    _, args = _config(("train",), ["--recipe", "v2", "--out", "o", "--set", "lr=3e-4", "--max-steps", "2"])
    changed = config_from_args(TrainConfig, args, args.flag_fields, recipe=recipes.TRAIN["v2"])
    assert (changed.lr, changed.max_steps, changed.rephrase) == (3e-4, 2, 0.8)


def test_v2_2step_recipe_is_what_the_shipped_student_records():
    saved = _saved(V2_2STEP)
    recipe = recipes.DISTILL["v2-2step"]
    made = saved["distilled_from"]
    assert (recipe["student_steps"], recipe["num_pairs"], recipe["groups"]) == (
        made["student_steps"], made["num_pairs"], made["pair_groups"])
    training = saved["training"]
    assert (recipe["batch_size"], recipe["lr"], recipe["max_steps"]) == (training["batch_size"], training["lr"],
                                                                          training["steps"])
    for key in ("group_batches", "counterfactual_swap", "rephrase"):
        assert recipe[key] == saved["recipe"][key], key
    module, args = _config(("distill",), ["--recipe-from", str(V2_2STEP), "--teacher", "t", "--pairs", "p",
                                          "--out", "o"])
    recorded = module.read_recipe(V2_2STEP)
    cfg = config_from_args(module.DistillConfig, args, args.flag_fields, recipe=recorded).shared()
    _, args = _config(("distill",), ["--recipe", "v2-2step", "--teacher", "t", "--pairs", "p", "--out", "o"])
    named = config_from_args(module.DistillConfig, args, args.flag_fields, recipe=recipes.DISTILL["v2-2step"]).shared()
    assert (cfg.student.student_steps, cfg.pairs.num_pairs, cfg.pairs.groups, cfg.student.max_steps) == (
        named.student.student_steps, named.pairs.num_pairs, named.pairs.groups, named.student.max_steps)
    assert named.pairs.teacher == named.student.teacher == Path("t") and named.pairs.out == Path("p")


def test_autoencoder_recipe_is_the_shipped_autoencoders_architecture():
    saved = json.loads((V2 / "autoencoder" / "config.json").read_text())
    assert recipes.AUTOENCODER["ae-f8c32"]["preset"] == saved["name"]
    module, args = _config(("train-autoencoder",), ["--recipe-from", str(V2 / "autoencoder"), "--data", "d",
                                                    "--out", "o"])
    assert module.read_recipe(V2 / "autoencoder")["preset"] == saved["name"]
    _, args = _config(("train-autoencoder",), ["--recipe", "ae-f8c32-decoder", "--data", "d", "--out", "o",
                                               "--init", str(V2 / "autoencoder")])
    cfg = config_from_args(module.AutoencoderTrainConfig, args, args.flag_fields,
                           recipe=recipes.AUTOENCODER["ae-f8c32-decoder"])
    assert cfg.decoder_only and cfg.object_weight == 10.0 and cfg.init == V2 / "autoencoder"


def test_idm_recipes():
    from tesseract4d.policy.idm_trainer import IDMTrainConfig

    module, args = _config(("train-idm",), ["--recipe", "bc", "--data", "d", "--out", "o"])
    cfg = config_from_args(IDMTrainConfig, args, args.flag_fields, recipe=recipes.IDM["bc"])
    assert (cfg.max_steps, cfg.use_future) == (3000, False)
    _, args = _config(("train-idm",), ["--recipe", "idm", "--data", "d", "--out", "o", "--max-steps", "5"])
    assert config_from_args(IDMTrainConfig, args, args.flag_fields, recipe=recipes.IDM["idm"]).max_steps == 5


@pytest.mark.slow
def test_train_recipe_v2_runs_two_steps(tmp_path, capsys):
    """`train --recipe v2 --max-steps 2` on a tiny grouped 128² dataset with the shipped autoencoder (the
    recipe's batch of 32 made 2 here to keep the test short; the CPU time, not the recipe, is the limit)."""
    from tesseract4d.testing.synthetic_scene import write_grouped_dataset

    data = write_grouped_dataset(tmp_path / "data", scenes=2, frames=16, size=128)
    rc = main(["train", "--recipe", "v2", "--data", str(data), "--autoencoder", str(V2 / "autoencoder"),
               "--out", str(tmp_path / "run"), "--max-steps", "2", "--set", "batch_size=2", "--quiet"])
    assert rc == 0, capsys.readouterr().err
    saved = json.loads((tmp_path / "run" / "train_config.json").read_text())
    assert {k: saved[k] for k in recipes.TRAIN["v2"] if k not in ("max_steps", "batch_size")} == {
        k: v for k, v in recipes.TRAIN["v2"].items() if k not in ("max_steps", "batch_size")}
    final = json.loads((tmp_path / "run" / "final" / "tesseract4d_config.json").read_text())
    assert final["training"]["steps"] == 2 and final["recipe"]["scene_object_weight"] == 40.0
