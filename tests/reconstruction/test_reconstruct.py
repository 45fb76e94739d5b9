"""4D reconstruction: refinement beats plain back-projection on corrupted depth, the Recon4D
contract is filled and round-trips, the CLIs work, bad input fails with a clear error."""

from __future__ import annotations

import copy
import json

import numpy as np
import pytest

from tesseract4d.evaluation.episode import evaluate_episode
from reconstruction.recon4d import Recon4D
from reconstruction.reconstruct import STAGES, ReconConfig, reconstruct_episode
from tesseract4d.errors import UserError
from tesseract4d.geometry import depth_to_world_points
from tesseract4d.testing.synthetic_scene import analytic_episode, flickering_depth, look_at_pose

FRAMES, SIZE = 16, 64
NOISE_REL = 0.01  # per-pixel depth noise (fraction of depth)
WOBBLE_SCALE, WOBBLE_SHIFT_M = 0.03, 0.02  # per-frame depth scale / shift flicker amplitudes


def corrupt(episode, seed: int = 0):
    return flickering_depth(episode, NOISE_REL, WOBBLE_SCALE, WOBBLE_SHIFT_M, seed=seed)


def static_depth_variance(depth_m: np.ndarray, gt_depth_m: np.ndarray) -> float:
    """Mean over ground-truth-static pixels of the depth variance over time (m^2)."""
    static = np.all(np.abs(gt_depth_m - gt_depth_m[:1]) < 1e-6, axis=0) & (gt_depth_m[0] > 0)
    return float(np.mean(np.var(depth_m[:, static], axis=0)))


def compare(gt, noisy, label: str) -> dict:
    cam = next(iter(gt.cameras))
    raw = reconstruct_episode(noisy, config=ReconConfig(refine=False, fuse_background=False))
    refined = reconstruct_episode(noisy)
    r_raw, r_ref = evaluate_episode(raw, gt)["mean"], evaluate_episode(refined, gt)["mean"]
    gt_depth = gt.cameras[cam].depth_m
    out = {
        "chamfer_raw": r_raw["chamfer_l1_m"], "chamfer_refined": r_ref["chamfer_l1_m"],
        "chamfer_moving_raw": r_raw["chamfer_l1_m_moving"], "chamfer_moving_refined": r_ref["chamfer_l1_m_moving"],
        "var_raw": static_depth_variance(raw.depth_m, gt_depth), "var_refined": static_depth_variance(refined.depth_m, gt_depth),
        "seconds": sum(refined.metadata["timings_s"].values()), "refined": refined,
    }
    out["improvement"] = 1 - out["chamfer_refined"] / out["chamfer_raw"]
    print(f"\n{label}: Chamfer L1 {1000 * out['chamfer_raw']:.2f} mm -> {1000 * out['chamfer_refined']:.2f} mm "
          f"({100 * out['improvement']:.0f} % better; moving region {1000 * out['chamfer_moving_raw']:.2f} -> "
          f"{1000 * out['chamfer_moving_refined']:.2f} mm), static depth variance {out['var_raw']:.2e} -> "
          f"{out['var_refined']:.2e} m^2, AbsRel {r_raw['depth_abs_rel']:.4f} -> {r_ref['depth_abs_rel']:.4f}, "
          f"{out['seconds']:.2f} s")
    return out


@pytest.fixture(scope="module")
def scene():
    return analytic_episode(num_frames=FRAMES, height=SIZE, width=SIZE)


@pytest.fixture(scope="module")
def result(scene):
    return compare(scene, corrupt(scene), f"analytic scene {FRAMES}x{SIZE}^2, {NOISE_REL:.0%} noise + wobble")


def test_refinement_is_closer_to_truth_and_flickers_less(result):
    assert result["improvement"] >= 0.30
    assert result["var_refined"] < 0.1 * result["var_raw"]
    assert result["chamfer_moving_refined"] < result["chamfer_moving_raw"]


def test_recon4d_is_complete(result, scene, tmp_path):
    recon: Recon4D = result["refined"]
    recon.validate()
    assert recon.num_frames == FRAMES and recon.rgb.shape == (FRAMES, SIZE, SIZE, 3)
    valid = scene.cameras["base_camera"].depth_m > 0
    assert [len(p) for p in recon.points_world] == list(valid.sum(axis=(1, 2)))
    assert all(np.allclose(np.linalg.norm(n, axis=-1), 1, atol=1e-3) for n in recon.normals_world)
    share = np.mean(np.concatenate(recon.dynamic))
    assert 0.01 < share < 0.3, share  # the box moves, the table does not
    assert len(recon.background_points) > 1000 and len(recon.background_colors) == len(recon.background_points)
    assert np.allclose(np.linalg.norm(recon.background_normals, axis=-1), 1, atol=1e-2)
    # The background is the table: its points lie near z = 0.
    assert np.median(np.abs(recon.background_points[:, 2])) < 0.01
    assert len(recon.mesh_faces) > 1000 and recon.mesh_faces.max() < len(recon.mesh_vertices)
    assert len(recon.mesh_colors) == len(recon.mesh_vertices)
    meta = recon.metadata
    assert meta["config"]["static_weight"] == 200 and set(meta["timings_s"]) == set(STAGES)
    assert meta["solver"]["converged"]

    out = recon.save(tmp_path / "recon")
    for name in ("manifest.json", "recon4d.npz", "frames/frame_0000.ply", "background.ply", "background_mesh.glb"):
        assert (out / name).is_file(), name
    # The GLB is glTF's +y up: the table (world z = 0, normals +z) becomes the plane y = 0 facing +y.
    import trimesh

    glb = trimesh.load(out / "background_mesh.glb", force="mesh")
    assert len(glb.faces) == len(recon.mesh_faces)
    assert np.median(np.abs(glb.vertices[:, 1])) < 0.01 and np.median(glb.face_normals[:, 1]) > 0.9
    np.testing.assert_allclose(np.sort(glb.vertices[:, 0]), np.sort(recon.mesh_vertices[:, 0]), atol=1e-6)
    back = Recon4D.load(out)
    assert back.num_frames == FRAMES
    np.testing.assert_array_equal(back.dynamic[3], recon.dynamic[3])
    np.testing.assert_allclose(back.depth_m, recon.depth_m)
    assert json.loads((out / "manifest.json").read_text())["metadata"]["config"]["refine"] is True
    # Inside a command's own staging folder it writes straight into the folder: nothing beside it.
    staged = recon.save(tmp_path / "stage" / "recon", write_ply=False, staged=True)
    assert [p.name for p in (tmp_path / "stage").iterdir()] == ["recon"]
    assert Recon4D.load(staged).num_frames == FRAMES


def test_no_refine_is_plain_back_projection(scene):
    calls = []
    recon = reconstruct_episode(scene, config=ReconConfig(refine=False, fuse_background=False),
                                progress=lambda done, total: calls.append((done, total)))
    cam = scene.cameras["base_camera"]
    np.testing.assert_array_equal(recon.depth_m, cam.depth_m)
    np.testing.assert_allclose(recon.points_world[5], depth_to_world_points(cam.depth_m[5], cam.K[5], cam.T_world_cam[5])[0], atol=1e-6)
    assert calls[-1] == (len(STAGES), len(STAGES)) and len(calls) == len(STAGES)


def test_a_chained_episodes_schedule_is_kept_for_the_viewer(scene, tmp_path):
    import dataclasses

    from tesseract4d.instruction_schedule import SCHEDULE_KEY, Segment

    schedule = [Segment("push it", 0, 4).to_dict(), Segment("lift it", 4, len(scene.frame_steps) - 1).to_dict()]
    chained = dataclasses.replace(scene, metadata={**scene.metadata, SCHEDULE_KEY: schedule})
    recon = reconstruct_episode(chained, config=ReconConfig(refine=False, fuse_background=False))
    assert Recon4D.load(recon.save(tmp_path / "recon", write_ply=False)).metadata[SCHEDULE_KEY] == schedule
    assert SCHEDULE_KEY not in reconstruct_episode(scene, config=ReconConfig(refine=False, fuse_background=False)).metadata


def test_clean_depth_stays_close(scene):
    """Refining exact depth must not damage it much (the normals agree with it)."""
    report = evaluate_episode(reconstruct_episode(scene, config=ReconConfig(fuse_background=False)), scene)["mean"]
    print(f"\nclean input: refined Chamfer {1000 * report['chamfer_l1_m']:.2f} mm, AbsRel {report['depth_abs_rel']:.4f}")
    assert report["chamfer_l1_m"] < 0.003 and report["depth_abs_rel"] < 0.005


# ----------------------------------------------------------------------------- bad input


def broken(scene, **changes):
    ep = copy.deepcopy(scene)
    for key, value in changes.items():
        setattr(ep.cameras["base_camera"], key, value(getattr(ep.cameras["base_camera"], key)))
    return ep


def test_mismatched_frame_counts(scene):
    with pytest.raises(UserError, match="depth_m must be"):
        reconstruct_episode(broken(scene, depth_m=lambda d: d[:-1]))
    ep = copy.deepcopy(scene)
    ep.frame_steps = ep.frame_steps[:-2]
    with pytest.raises(UserError, match="frame_steps"):
        reconstruct_episode(ep)


def test_missing_or_broken_intrinsics(scene):
    with pytest.raises(UserError, match="intrinsics"):
        reconstruct_episode(broken(scene, K=lambda K: None))
    with pytest.raises(UserError, match="intrinsics"):
        reconstruct_episode(broken(scene, K=lambda K: np.zeros_like(K)))
    with pytest.raises(UserError, match="no camera"):
        reconstruct_episode(scene, camera="wrist")


def test_nan_and_zero_depth(scene):
    def holes(d):
        d = d.copy()
        d[:, :8, :] = np.nan
        d[:, 8:12, :] = 0
        return d

    recon = reconstruct_episode(broken(scene, depth_m=holes), config=ReconConfig(fuse_background=False))
    assert all(np.all(np.isfinite(p)) for p in recon.points_world)
    assert np.all(recon.depth_m[:, :12] == 0) and np.all(np.isfinite(recon.depth_m))
    with pytest.raises(UserError, match="no pixel has a valid depth"):
        reconstruct_episode(broken(scene, depth_m=lambda d: np.zeros_like(d)))
    with pytest.raises(UserError, match="no pixel has a valid depth"):
        reconstruct_episode(broken(scene, depth_m=lambda d: np.full_like(d, np.nan)))


def test_missing_normals_and_empty_masks(scene):
    # No normals at all: no normal rows; point normals come from the depth instead.
    recon = reconstruct_episode(broken(scene, normal_cam=lambda n: np.zeros_like(n)), config=ReconConfig(fuse_background=False))
    assert all(np.allclose(np.linalg.norm(n, axis=-1), 1, atol=1e-3) for n in recon.normals_world[1:])
    # A static clip: empty dynamic masks, everything fused into the background.
    still = broken(scene, rgb=lambda x: np.repeat(x[:1], len(x), 0), depth_m=lambda d: np.repeat(d[:1], len(d), 0),
                   normal_cam=lambda n: np.repeat(n[:1], len(n), 0))
    recon = reconstruct_episode(still)
    assert not np.concatenate(recon.dynamic).any() and recon.metadata["temporal_rows_dynamic"] == 0
    assert len(recon.background_points) > 0


def test_bad_config():
    with pytest.raises(UserError, match="reg_weight"):
        reconstruct_episode(analytic_episode(2, 16, 16), config=ReconConfig(reg_weight=0))
    with pytest.raises(UserError, match="voxel"):
        reconstruct_episode(analytic_episode(2, 16, 16), config=ReconConfig(voxel_size_m=-1))


# ----------------------------------------------------------------------------- CLIs


def test_reconstruct_and_evaluate_cli(scene, tmp_path, capsys):
    from tesseract4d.cli import main
    from tesseract4d.dataset_format import write_episode

    gt_path = write_episode(tmp_path / "gt", scene)
    noisy = corrupt(scene, seed=1)
    noisy.source = "prediction"
    pred_path = write_episode(tmp_path / "pred", noisy)
    out = tmp_path / "recon"
    assert main(["reconstruct", str(pred_path), "--out", str(out), "--set", "iterations=200",
                 "--set", "voxel_size_m=0.02"]) == 0
    assert "wrote" in capsys.readouterr().out
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["metadata"]["config"]["iterations"] == 200 and manifest["metadata"]["voxel_size_m"] == 0.02
    report_path = tmp_path / "report.json"
    assert main(["evaluate", str(out), "--gt", str(gt_path), "--json", str(report_path)]) == 0
    printed = capsys.readouterr().out
    assert "chamfer_l1_m" in printed and "moving" in printed
    refined = json.loads(report_path.read_text())
    assert main(["evaluate", str(tmp_path / "pred"), "--gt", str(gt_path), "--set", "per_frame=false"]) == 0
    capsys.readouterr()
    assert main(["reconstruct", str(pred_path), "--out", str(tmp_path / "raw"), "--set", "refine=false",
                 "--no-ply"]) == 0
    assert not (tmp_path / "raw" / "frames").exists()
    assert refined["mean"]["chamfer_l1_m"] < 0.7 * evaluate_episode(noisy, scene)["mean"]["chamfer_l1_m"]
    # Errors are one line with the fix, exit code 2.
    assert main(["reconstruct", str(tmp_path / "missing.h5"), "--out", str(tmp_path / "x")]) == 2
    assert main(["evaluate", str(out), "--gt", str(tmp_path / "missing.h5")]) == 2
    assert main(["reconstruct", str(pred_path), "--out", str(tmp_path / "x"), "--camera", "wrist"]) == 2
    assert "error" in capsys.readouterr().err


def test_a_predictions_given_first_frame_is_not_scored(scene):
    """A prediction's frame 0 is the first frame it was given (a perfect copy): its means start at
    frame 1, for the episode and for its reconstruction; a recording's are over every frame."""
    from reconstruction.backproject import recon_from_episode

    pred = corrupt(scene, seed=3)
    for cam, gt_cam in zip(pred.cameras.values(), scene.cameras.values()):
        cam.rgb[0], cam.depth_m[0], cam.normal_cam[0] = gt_cam.rgb[0], gt_cam.depth_m[0], gt_cam.normal_cam[0]
    pred.source = "prediction"
    report = evaluate_episode(pred, scene)
    err = [r["depth_abs_rel"] for r in report["per_frame"]]  # the corruption is in the depth
    assert report["first_scored_frame"] == 1 and err[0] == 0.0 and min(err[1:]) > 0  # the given frame keeps its row
    assert report["mean"]["depth_abs_rel"] == pytest.approx(np.mean(err[1:]))
    assert evaluate_episode(recon_from_episode(pred), scene)["first_scored_frame"] == 1
    recording = copy.deepcopy(pred)
    recording.source = "sim"
    whole = evaluate_episode(recording, scene)
    assert whole["first_scored_frame"] == 0 and whole["mean"]["depth_abs_rel"] == pytest.approx(np.mean(err))
    assert evaluate_episode(pred, scene, first_scored_frame=0)["mean"]["depth_abs_rel"] == pytest.approx(np.mean(err))


# ----------------------------------------------------------------------------- simulator


@pytest.fixture(scope="module")
def pickcube(sim_dataset):
    """One real PickCube-v1 episode rendered by ManiSkill (the run's simulator dataset, conftest.py),
    its close camera."""
    from tesseract4d.dataset_format import list_episode_files, read_episode

    return read_episode(list_episode_files(sim_dataset)[0], cameras=["close"])


@pytest.mark.sim
def test_refinement_on_real_maniskill_episode(pickcube):
    out = compare(pickcube, corrupt(pickcube), f"PickCube-v1 {FRAMES}x{SIZE}^2, {NOISE_REL:.0%} noise + wobble")
    assert out["improvement"] >= 0.30
    assert out["var_refined"] < 0.1 * out["var_raw"]


# ----------------------------------------------------------------------------- moving camera


def orbiting_table(frames: int = FRAMES, size: int = SIZE):
    """A static checkered table (plane z = 0) seen by a camera that orbits it: all image motion
    is the camera's own."""
    from tesseract4d.dataset_format import CameraFrames, Episode

    f = 0.5 * size / np.tan(np.deg2rad(30))
    K = np.array([[f, 0, size / 2], [0, f, size / 2], [0, 0, 1]])
    u, v = np.meshgrid(np.arange(size) + 0.5, np.arange(size) + 0.5)
    rays_cam = np.stack([(u - K[0, 2]) / f, (v - K[1, 2]) / f, np.ones_like(u)], -1)
    rgb = np.zeros((frames, size, size, 3), np.uint8)
    depth = np.zeros((frames, size, size), np.float32)
    normal = np.zeros((frames, size, size, 3), np.float32)
    poses = []
    for t in range(frames):
        angle = -0.8 + 0.03 * t
        T = look_at_pose(np.array([0.9 * np.cos(angle), 0.9 * np.sin(angle), 0.6]), np.zeros(3))
        rays = rays_cam @ T[:3, :3].T
        s = -T[2, 3] / rays[..., 2]  # camera z-depth of the hit on z = 0
        p = T[:3, 3] + s[..., None] * rays
        checker = ((np.floor(p[..., 0] / 0.1) + np.floor(p[..., 1] / 0.1)) % 2).astype(bool)
        hit = (s > 0) & (np.abs(p[..., 0]) < 1) & (np.abs(p[..., 1]) < 1)
        depth[t] = np.where(hit, s, 0)
        rgb[t] = np.where(hit[..., None], np.where(checker[..., None], [200, 200, 190], [90, 90, 80]), 0)
        normal[t] = np.where(hit[..., None], np.array([0.0, 0.0, 1.0]) @ T[:3, :3], 0)
        poses.append(T)
    cam = CameraFrames(rgb=rgb, depth_m=depth, normal_cam=normal, K=np.repeat(K[None], frames, 0), T_world_cam=np.stack(poses))
    return Episode(env_id="Orbit-v0", seed=0, instruction="", cameras={"base_camera": cam}, frame_steps=np.arange(frames, dtype=np.int32))


def test_moving_camera_static_scene():
    gt = orbiting_table()
    out = compare(gt, corrupt(gt), "orbiting camera, static table, 1% noise + wobble")
    recon = out["refined"]
    assert np.mean(np.concatenate(recon.dynamic)) < 0.05  # the camera's own motion is not "dynamic"
    assert recon.metadata["temporal_rows_static"] > 0.5 * recon.depth_m[1:].size
    assert out["improvement"] >= 0.30


def test_fusion_takes_frames_with_only_a_few_valid_pixels():
    # Open3D finds TSDF blocks only at every 4th pixel; a frame whose valid pixels all lie between
    # those (a prediction with almost no depth in range) must still fuse, not abort.
    from reconstruction.fusion import fuse_tsdf

    T, H, W = 4, 32, 32  # the surface is extracted where 3 frames agree
    K = np.tile(np.array([[32.0, 0, 16], [0, 32.0, 16], [0, 0, 1]]), (T, 1, 1))
    poses = np.tile(np.eye(4), (T, 1, 1))
    rgb = np.full((T, H, W, 3), 200, np.uint8)
    depth = np.full((T, H, W), 1.0, np.float32)
    depth[3] = 0.0
    depth[3, 1, 1] = 0.9  # a single valid pixel off Open3D's sampling lattice
    full = fuse_tsdf(depth, rgb, K, poses, np.ones((T, H, W), bool), voxel_size_m=0.02)
    assert len(full.points) > 0 and np.all(np.isfinite(full.points))
    lone = depth.copy()
    lone[:3] = lone[3]
    only_lone = fuse_tsdf(lone, rgb, K, poses, np.ones((T, H, W), bool), voxel_size_m=0.02)
    assert np.all(np.isfinite(only_lone.points)) and only_lone.points.shape[1] == 3
