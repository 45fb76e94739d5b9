"""Counterfactual group batches (``train --group-batches``): whole groups per batch sharing one noise
and one diffusion time, the loss weight on the cells where a group's futures differ, and the
counterfactual swap (model/recipe.py, model/clips.py). Pure functions; the trainer's use of them is
in test_latent_model.py."""

from __future__ import annotations

from types import SimpleNamespace

import pytest
import torch

from tesseract4d.dataset_format import group_of_episode_id
from tesseract4d.model.clips import draw_group_batch, group_units
from tesseract4d.model.recipe import (DISAGREE_SHARE, SWAP_MIN_T, cell_weights, disagreement_mask,
                                      share_within_groups, swap_sources)

IDS = ["Tab-v1/seed_000000_k0", "Tab-v1/seed_000000_k1", "Tab-v1/seed_000000_k2", "Tab-v1/seed_000000_k3",
       "Push-v1/seed_000004", "Tab-v1/seed_000002_k0", "Tab-v1/seed_000002_k1"]


def test_group_of_an_episode_id():
    assert group_of_episode_id("Tab-v1/seed_000003_k2") == "Tab-v1/seed_000003"
    assert group_of_episode_id("Tab-v1/seed_1000000_k11") == "Tab-v1/seed_1000000"
    assert group_of_episode_id("Push-v1/seed_000003") is None
    assert group_units(IDS) == [[0, 1, 2, 3], [4], [5, 6]]


@pytest.mark.parametrize("seed", range(20))
def test_a_group_batch_holds_whole_groups_with_one_start_each(seed):
    units = group_units(IDS)
    lengths = [16, 16, 16, 16, 20, 18, 19]
    g = torch.Generator().manual_seed(seed)
    indices, starts, leaders = draw_group_batch(units, lengths, 16, 4, g)
    assert len(indices) == len(starts) == len(leaders) == 4
    unit_of = {i: u for u, members in enumerate(units) for i in members}
    for k, (i, leader) in enumerate(zip(indices, leaders)):
        assert leader <= k and leaders[leader] == leader  # a leader is its group's first clip
        assert unit_of[indices[leader]] == unit_of[i] and starts[leader] == starts[k]
        assert 0 <= starts[k] <= lengths[i] - 16
    for leader in set(leaders):
        members = [indices[k] for k in range(4) if leaders[k] == leader]
        unit = units[unit_of[members[0]]]
        assert len(set(members)) == len(members)  # no episode twice within a group
        # Whole: the group is complete unless it was cut at the end of the batch.
        assert len(members) == len(unit) or leader + len(members) == 4


def test_group_batches_draw_every_episode_about_equally_often():
    units = group_units(IDS)
    g = torch.Generator().manual_seed(0)
    counts = torch.zeros(len(IDS))
    for _ in range(3000):
        indices, _, _ = draw_group_batch(units, [16] * len(IDS), 16, 4, g)
        counts[indices] += 1
    share = counts / counts.sum()
    # One clip per draw of its group: an episode alone is drawn as often as one in a group of four
    # (the last group of a batch is cut to fit, which costs big groups' members a little).
    assert share.min() > 0.8 / len(IDS) and share.max() < 1.2 / len(IDS)


def test_shared_noise_and_times_follow_the_leaders():
    leaders = [0, 0, 2, 2]
    noise = torch.randn(4, 3, 2, 2)
    shared = share_within_groups(noise, leaders)
    assert torch.equal(shared[1], noise[0]) and torch.equal(shared[3], noise[2]) and torch.equal(shared[2], noise[2])
    assert share_within_groups(noise, None) is noise


def test_the_disagreement_mask_marks_where_a_groups_futures_differ():
    x0 = torch.zeros(4, 4, 2, 10, 10)
    x0[0, 2:, :, 3:5, 3:5] = 1.0  # group (0, 1): clip 0 moves a patch that clip 1 keeps still
    x0[2:4] = torch.randn(2, 4, 2, 10, 10)  # group (2, 3): random futures
    still = disagreement_mask(x0[:2])
    assert still.shape == (1, 4, 1, 10, 10)
    assert still[0, 2:, 0, 3:5, 3:5].all() and still.sum() == 2 * 4  # exactly the differing cells
    assert disagreement_mask(x0[2:4]).mean().item() == pytest.approx(DISAGREE_SHARE, abs=0.01)


def test_scene_object_weight_adds_to_the_robot_and_object_weight_on_the_objects_alone():
    cfg = SimpleNamespace(moving_weight=1.0, object_weight=2.0, scene_object_weight=8.0)
    x0 = torch.zeros(1, 3, 2, 6, 6)  # a still clip: no moving cells
    objects = torch.zeros(1, 3, 2, 6, 6)
    objects[:, :, 0, 0, :3] = 1.0  # the robot: three cells
    objects[:, :, 0, 4, 4] = objects[:, :, 1, 4, 4] = 0.5  # a cube covering half a cell
    w = cell_weights(x0, objects, cfg)
    assert w.shape == (1, 3, 1, 6, 6)
    assert w[0, 1, 0, 0, 1] == 2.0  # robot: the object weight only
    assert w[0, 1, 0, 4, 4] == pytest.approx(1.0 + 1.0 * 0.5 + 7.0 * 0.5)  # cube: both, by its share
    assert w[0, 1, 0, 2, 2] == 1.0  # table
    cfg.scene_object_weight = 1.0
    assert cell_weights(x0, objects, cfg)[0, 1, 0, 4, 4] == pytest.approx(1.5)
    cfg.object_weight = 1.0
    assert cell_weights(x0, objects, cfg) is None  # every weight 1: no weighting at all


def test_counterfactual_swap_shows_a_sibling_only_at_high_noise():
    leaders = [0, 0, 0, 3, 4, 4]  # a group of three, one alone, a pair
    high = torch.full((6,), 0.9)
    never = swap_sources(leaders, high, 0.0, torch.Generator().manual_seed(0))
    assert never == list(range(6))
    for seed in range(10):
        shown = swap_sources(leaders, high, 1.0, torch.Generator().manual_seed(seed))
        for k, j in enumerate(shown):
            if k == 3:
                assert j == 3  # no sibling: itself
            else:
                assert j != k and leaders[j] == leaders[k]
    low = torch.full((6,), SWAP_MIN_T - 0.01)
    assert swap_sources(leaders, low, 1.0, torch.Generator().manual_seed(0)) == list(range(6))
    # The random stream does not depend on the outcome (a resumed run draws the same numbers).
    a, b = torch.Generator().manual_seed(3), torch.Generator().manual_seed(3)
    swap_sources(leaders, high, 1.0, a)
    swap_sources(leaders, low, 0.0, b)
    assert torch.equal(torch.rand(3, generator=a), torch.rand(3, generator=b))
