"""Finding the scene's objects in an RGB frame without a segmentation (tesseract4d/object_finder.py):
on a drawn table scene, on scenery that is not an object, and on rendered ManiSkill first frames
against their own segmentation."""

from __future__ import annotations

import numpy as np
import pytest

from tesseract4d.object_finder import MAX_OBJECT_SHARE, find_objects

WOOD = np.array([160, 80, 45])
CUBES = {"red": (200, 30, 30), "blue": (40, 60, 200), "green": (60, 160, 60), "yellow": (210, 200, 40),
         "purple": (140, 60, 190)}


def table_scene(size: int = 128, seed: int = 0):
    """A grained wooden table under a grey floor strip, a grey robot block standing on it and five
    shaded 8-px cubes: (rgb (size, size, 3) uint8, {colour name: its cube's mask})."""
    rng = np.random.default_rng(seed)
    s = size / 128
    rgb = np.empty((size, size, 3), np.int32)
    grain = rng.integers(-14, 15, size)  # streaks along the rows, as the wood's grain
    rgb[:] = WOOD + grain[:, None, None] + rng.integers(-4, 5, (size, size, 1))
    rgb[: int(20 * s)] = (120, 121, 126)  # the floor beyond the table's edge
    rgb[int(10 * s):int(50 * s), int(40 * s):int(70 * s)] = (200, 200, 204)  # the robot
    masks = {}
    for k, (name, colour) in enumerate(CUBES.items()):
        y, x, c = int((60 + 12 * (k % 3)) * s), int((15 + 22 * k) * s), max(2, int(8 * s))
        rgb[y:y + c, x:x + c] = np.array(colour) * 0.75  # the shaded side
        rgb[y:y + c // 2, x:x + c] = colour  # the lit top
        mask = np.zeros((size, size), bool)
        mask[y:y + c, x:x + c] = True
        masks[name] = mask
    return np.clip(rgb, 0, 255).astype(np.uint8), masks


def iou(a: np.ndarray, b: np.ndarray) -> float:
    return float((a & b).sum() / (a | b).sum())


def test_every_cube_on_a_grained_table_is_found_and_nothing_else():
    rgb, masks = table_scene()
    found = find_objects(rgb)
    assert len(found) == len(CUBES)
    for name, mask in masks.items():
        assert max(iou(mask, f) for f in found) == 1.0, name
    # The same scene as floats, and at 64² (the window scales with the image): the same objects.
    assert all(np.array_equal(a, b) for a, b in zip(find_objects(rgb.astype(np.float32)), found))
    small, small_masks = table_scene(64)
    found64 = find_objects(small)
    assert len(found64) == len(CUBES)
    assert all(max(iou(m, f) for f in found64) == 1.0 for m in small_masks.values())


def test_scenery_is_not_an_object():
    rgb, masks = table_scene()
    for mask in masks.values():
        rgb[mask] = WOOD  # the table, its grain, the floor's edge and the robot alone
    assert find_objects(rgb) == []
    # A saturated region larger than MAX_OBJECT_SHARE of the image (a mat, a wall) is scenery.
    side = int(np.ceil(np.sqrt(MAX_OBJECT_SHARE * 128 * 128))) + 2
    rgb[60:60 + side, 60:60 + side] = (40, 60, 200)
    assert find_objects(rgb) == []
    rgb[60:60 + side, 60:60 + side] = (40, 60, 200)
    rgb[100:108, 100:108] = (40, 160, 60)  # beside it, a green cube is still found
    assert len(found := find_objects(rgb)) == 1 and found[0][100:108, 100:108].all() and found[0].sum() == 64
    # Grey objects are not followed: the robot's white and the floor's grey are grey too.
    grey = np.full((128, 128, 3), 90, np.uint8)
    grey[40:48, 40:48] = 220
    assert find_objects(grey) == []
    with pytest.raises(ValueError, match=r"\(H, W, 3\)"):
        find_objects(grey[..., 0])


@pytest.mark.sim
def test_the_objects_of_rendered_first_frames_are_found_as_their_segmentation_names_them(tmp_path):
    """A tabletop scene with a red cylinder on the wooden table (the hardest colour) and PushCube
    with its red-and-white goal target: every scene object whose colours the segmentation-based
    reading keeps is found (one found group holds its distinctive pixels; the cylinder's dark side, as
    unlike the table as it is like it, may be left out), and nothing found lies off the scene's objects."""
    from tesseract4d import cli
    from tesseract4d import dataset_format as df
    from tesseract4d.model.draw_choice import AROUND_PX
    from tesseract4d.object_colours import MIN_OBJECT_PIXELS, distinctive
    from tesseract4d.segments import scene_object_ids

    out = tmp_path / "scenes"
    assert cli.main(["datagen", "--tasks", "Tesseract4dTabletop-v1,PushCube-v1", "--episodes", "1", "--seed-start",
                     "100003", "--instruction-split", "heldout", "--resolution", "128", "--frames", "2", "--out",
                     str(out), "--set", "previews=false", "--quiet"]) == 0
    paths = df.list_episode_files(out)
    assert len(paths) == 2
    for path in paths:
        cam = df.read_episode(path, frames=slice(0, 1)).cameras["close"]
        rgb, seg = cam.rgb[0], cam.segmentation[0]
        objects = [seg == i for i in scene_object_ids(cam.seg_id_to_name)]
        own = []  # each object's distinctive pixels, for the objects the segmentation-based reading follows
        for mask in objects:
            pixels = np.zeros_like(mask)
            pixels[mask] = distinctive(rgb, mask, AROUND_PX)
            if pixels.sum() >= MIN_OBJECT_PIXELS:
                own.append(pixels)
        found = find_objects(rgb)
        assert own, path
        for pixels in own:
            assert max((f & pixels).sum() for f in found) >= 0.9 * pixels.sum(), path
        on_objects = np.any(objects, axis=0)
        assert all((f & on_objects).sum() >= 0.8 * f.sum() for f in found), path
