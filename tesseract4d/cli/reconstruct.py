"""Reconstruct a temporally consistent 4D point cloud from an RGB-D-N video (a dataset episode
or a prediction): depth refined to agree with the normals and across frames, per-frame coloured
points with normals and static/dynamic labels, a TSDF-fused static background and its mesh.

INPUT is an episode .h5 file, a dataset or prediction folder holding one episode, or
DIR/ENV_ID/SEED. DIR (--out) receives manifest.json (with the resolved config), recon4d.npz,
frames/frame_NNNN.ply, background.ply and background_mesh.ply/.glb, and the object layer: the first
frame's objects tracked as rigid bodies (trajectories.json, plain JSON; objects/<name>.ply). A
prediction names its objects with --objects-from (the episode it was predicted from: its segmentation),
else the colour object finder finds them.

Example:
  tesseract4d reconstruct data/train/episodes/PickCube-v1/seed_000000.h5 --out out/recon
  tesseract4d reconstruct out/pred --objects-from data/truth/episodes/PushCube-v1/seed_100000.h5 --out out/pred_recon
  tesseract4d view out/recon
"""

from __future__ import annotations

import argparse
from pathlib import Path

from reconstruction.reconstruct import ReconConfig
from tesseract4d.cli.argument_types import number, whole
from tesseract4d.cli.config_args import add_deprecated, add_moved_to_set, add_set_option
from tesseract4d.configs import with_overrides


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("input", help="episode .h5, dataset/prediction folder with one episode, or DIR/ENV_ID/SEED")
    parser.add_argument("--out", type=Path, required=True,
                        help="output folder: new, empty, or an earlier reconstruction (whose files are replaced)")
    parser.add_argument("--overwrite", action="store_true",
                        help="write into a folder holding other files (only this command's files are replaced)")
    parser.add_argument("--camera", help="camera of the episode to reconstruct (default: the first)")
    parser.add_argument("--no-ply", action="store_true", help="write only manifest.json + recon4d.npz (+ trajectories.json)")
    parser.add_argument("--objects-from", metavar="EPISODE",
                        help="episode whose first frame names the objects (segmentation, instructed object), e.g. the "
                             "one a prediction started from (default: the input's own segmentation, else found by "
                             "colour; `--set objects=false` skips the object layer)")
    parser.add_argument("--quiet", action="store_true", help="print nothing but errors")
    add_set_option(parser, ReconConfig)
    # The solver's weights and thresholds are `--set` options now; the old flags keep working for one release.
    for old, name, kind in (
        ("--voxel-size", "voxel_size_m", number(0, above=True)),
        ("--static-weight", "static_weight", number(0)),
        ("--dynamic-weight", "dynamic_weight", number(0)),
        ("--normal-weight", "normal_weight", number(0)),
        ("--reg-weight", "reg_weight", number(0, above=True, hint=" (it fixes the depth scale)")),
        ("--iterations", "iterations", whole(1)),
        ("--flow-threshold", "flow_threshold_px", number(0, above=True, hint=" pixels")),
    ):
        add_deprecated(parser, old, use=f"--set {name}=VALUE", set_field=name, config_class=ReconConfig, type=kind)
    add_moved_to_set(parser, ReconConfig, [("--no-refine", "refine", None, False), ("--no-mesh", "mesh", None, False)])


def config_from_args(args: argparse.Namespace) -> ReconConfig:
    return with_overrides(ReconConfig(), args.set_overrides)


def run(args: argparse.Namespace) -> int:
    from reconstruction.reconstruct import reconstruct_episode
    from tesseract4d.dataset_format import read_episode, resolve_episode
    from tesseract4d.outputs import OutputDir

    config = config_from_args(args)
    config.validate()
    path = resolve_episode(args.input)
    output = OutputDir(args.out, "reconstruct", inputs=[path, args.input], overwrite=args.overwrite)
    episode = read_episode(path, cameras=[args.camera] if args.camera else None, check=True)
    objects_from = read_episode(resolve_episode(args.objects_from), frames=slice(0, 1)) if args.objects_from else None
    recon = reconstruct_episode(episode, camera=args.camera, config=config, objects_from=objects_from)
    recon.metadata["episode_path"] = str(path)
    with output as stage:
        recon.save(stage, write_ply=not args.no_ply, staged=True)
    out = args.out
    if not args.quiet:
        m = recon.metadata
        timings = ", ".join(f"{k} {v:.2f}" for k, v in m["timings_s"].items())
        print(f"reconstructed {episode.episode_id} ({m['camera']}, {recon.num_frames} frames, "
              f"{sum(len(p) for p in recon.points_world)} points, {m['dynamic_share']:.1%} dynamic, "
              f"background {len(recon.background_points)} points / {len(recon.mesh_faces)} faces)")
        if "solver" in m:
            s = m["solver"]
            print(f"solve: {s['iterations']} iterations, relative residual {s['relative_residual']:.1e}")
        if recon.objects is not None:
            states = ", ".join(f"{t.name} {sum(s == 'tracked' for s in t.states())}/{recon.num_frames} tracked"
                               + (f", lost {t.states().count('lost')}" if "lost" in t.states() else "")
                               for t in recon.objects.tracks)
            print(f"objects ({recon.objects.source}; instructed: {recon.objects.instructed or '-'}): {states or 'none found'}")
        print(f"seconds: {timings}")
        print(f"wrote {out}")
    return 0
