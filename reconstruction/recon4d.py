"""``Recon4D``: the 4D reconstruction result, and its on-disk format (the contract between
reconstruction, evaluation and the viewer).

Folder layout written by :meth:`Recon4D.save`::

    DIR/manifest.json               format version, frame count, image size, fps, metadata, file list
    DIR/recon4d.npz                 every array below (what :meth:`Recon4D.load` reads)
    DIR/frames/frame_0000.ply ...   per-frame coloured points with normals (world frame)
    DIR/background.ply              fused static background points (if any)
    DIR/background_mesh.ply/.glb    fused static background mesh (if any); the PLY in the world frame,
                                    the GLB turned so the scene's up is glTF's +y
    DIR/trajectories.json           the object layer's tracks as plain JSON (if it has one; see objects.py)
    DIR/objects/<name>.ply          each object's rigid point set in its own frame (if it has an object layer)
    DIR/objects/frames/frame_0000.ply ...  every object placed at that frame, world frame

Format versions: 2 added the object layer (``objects``: arrays ``object_<k>_*`` and ``point_object``
in the npz, names and sources in the manifest). Version-1 folders still load, without objects.

All points and normals are in the world frame (metres); cameras use OpenCV axes.
Per-frame point sets have different sizes, so they are stored concatenated with offsets.
"""

from __future__ import annotations

import json
import os
import shutil
import uuid
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from reconstruction.objects import ObjectLayer, ObjectTrack
from tesseract4d.errors import UserError
from tesseract4d.geometry import rotation_to_y_up, scene_up_axis

RECON_FORMAT_VERSION = 2  # 2: the object layer
READABLE_VERSIONS = (1, 2)
TRAJECTORIES = "trajectories.json"
MANIFEST = "manifest.json"
ARRAYS = "recon4d.npz"


class ReconFormatError(UserError):
    """A folder that is not a (readable) tesseract4d reconstruction."""


@dataclass
class Recon4D:
    """A temporally consistent 4D point cloud. T frames of H x W images."""

    points_world: list[np.ndarray]  # T x (N_t, 3) float32
    colors: list[np.ndarray]  # T x (N_t, 3) uint8
    normals_world: list[np.ndarray]  # T x (N_t, 3) float32, unit
    dynamic: list[np.ndarray]  # T x (N_t,) bool, True = moving part of the scene
    rgb: np.ndarray  # (T, H, W, 3) uint8 source frames (for frustums and side panels)
    depth_m: np.ndarray  # (T, H, W) float32 depth used for the points (refined or raw), 0 = none
    normal_cam: np.ndarray  # (T, H, W, 3) float32 normals, OpenCV camera frame
    K: np.ndarray  # (T, 3, 3)
    T_world_cam: np.ndarray  # (T, 4, 4) camera -> world
    fps: float = 10.0
    background_points: np.ndarray = field(default_factory=lambda: np.zeros((0, 3), np.float32))
    background_colors: np.ndarray = field(default_factory=lambda: np.zeros((0, 3), np.uint8))
    background_normals: np.ndarray = field(default_factory=lambda: np.zeros((0, 3), np.float32))
    mesh_vertices: np.ndarray = field(default_factory=lambda: np.zeros((0, 3), np.float32))
    mesh_faces: np.ndarray = field(default_factory=lambda: np.zeros((0, 3), np.int32))
    mesh_colors: np.ndarray = field(default_factory=lambda: np.zeros((0, 3), np.uint8))
    metadata: dict = field(default_factory=dict)
    objects: ObjectLayer | None = None  # the scene's objects as tracked rigid point sets (None: not made)

    @property
    def num_frames(self) -> int:
        return len(self.points_world)

    def validate(self) -> None:
        T = self.num_frames
        if T == 0:
            raise ReconFormatError("a reconstruction needs at least one frame")
        for name in ("colors", "normals_world", "dynamic"):
            seq = getattr(self, name)
            if len(seq) != T:
                raise ReconFormatError(f"{name} has {len(seq)} frames, points_world has {T}")
            for t, (p, a) in enumerate(zip(self.points_world, seq)):
                if len(a) != len(p):
                    raise ReconFormatError(f"frame {t}: {name} has {len(a)} rows, points_world has {len(p)}")
        for name in ("rgb", "depth_m", "normal_cam", "K", "T_world_cam"):
            if len(getattr(self, name)) != T:
                raise ReconFormatError(f"{name} has {len(getattr(self, name))} frames, expected {T}")
        if self.objects is not None:
            for tr in self.objects.tracks:
                for name in ("T_world_object", "visibility", "confidence", "state"):
                    if len(getattr(tr, name)) != T:
                        raise ReconFormatError(f"object {tr.name!r}: {name} has {len(getattr(tr, name))} frames, expected {T}")
            labels = self.objects.point_object
            if labels and (len(labels) != T or any(len(a) != len(p) for a, p in zip(labels, self.points_world))):
                raise ReconFormatError("the object layer's point labels do not match the per-frame points")

    # ------------------------------------------------------------------ save / load

    def save(self, out_dir: str | os.PathLike, write_ply: bool = True, staged: bool = False) -> Path:
        """Write the folder atomically (to a temporary sibling, then rename); returns it.

        ``staged``: ``out_dir`` lies inside a staging folder of the caller's own (a command's
        ``OutputDir``), which is renamed into place as a whole: write straight into it."""
        self.validate()
        out = Path(out_dir)
        if out.exists() and (not out.is_dir() or any(out.iterdir())):
            raise ReconFormatError(f"{out} exists and is not empty; a reconstruction is written only to a new or empty "
                                   f"folder (the command line's --overwrite replaces its own earlier output)")
        if staged:
            out.mkdir(parents=True, exist_ok=True)
            self._write_files(out, write_ply)
            return out
        tmp = out.with_name(f".{out.name}.{uuid.uuid4().hex}.partial")
        tmp.mkdir(parents=True)
        try:
            self._write_files(tmp, write_ply)
            os.replace(tmp, out)  # onto nothing or an empty folder
        except BaseException:
            shutil.rmtree(tmp, ignore_errors=True)
            raise
        return out

    def _write_files(self, folder: Path, write_ply: bool) -> None:
        """The arrays, the PLY files and the manifest (last) into the empty folder ``folder``."""
        offsets = np.cumsum([0] + [len(p) for p in self.points_world]).astype(np.int64)
        cat = lambda seq, dt, w: (np.concatenate(seq).astype(dt) if offsets[-1] else np.zeros((0,) + w, dt))  # noqa: E731
        np.savez_compressed(
            folder / ARRAYS,
            offsets=offsets,
            points_world=cat(self.points_world, np.float32, (3,)),
            colors=cat(self.colors, np.uint8, (3,)),
            normals_world=cat(self.normals_world, np.float32, (3,)),
            dynamic=cat(self.dynamic, bool, ()),
            rgb=self.rgb.astype(np.uint8),
            depth_m=self.depth_m.astype(np.float32),
            normal_cam=self.normal_cam.astype(np.float32),
            K=self.K.astype(np.float64),
            T_world_cam=self.T_world_cam.astype(np.float64),
            background_points=self.background_points.astype(np.float32),
            background_colors=self.background_colors.astype(np.uint8),
            background_normals=self.background_normals.astype(np.float32),
            mesh_vertices=self.mesh_vertices.astype(np.float32),
            mesh_faces=self.mesh_faces.astype(np.int32),
            mesh_colors=self.mesh_colors.astype(np.uint8),
            **self._object_arrays(cat),
        )
        files = [ARRAYS]
        if self.objects is not None:
            (folder / TRAJECTORIES).write_text(self.objects.trajectories_json(self.fps, self.metadata.get("instruction")))
            files.append(TRAJECTORIES)
        if write_ply:
            (folder / "frames").mkdir()
            for t in range(self.num_frames):
                name = f"frames/frame_{t:04d}.ply"
                write_point_ply(folder / name, self.points_world[t], self.colors[t], self.normals_world[t])
                files.append(name)
            if len(self.background_points):
                write_point_ply(folder / "background.ply", self.background_points, self.background_colors, self.background_normals)
                files.append("background.ply")
            if len(self.mesh_faces):
                import trimesh

                mesh = trimesh.Trimesh(self.mesh_vertices, self.mesh_faces, vertex_colors=self.mesh_colors, process=False)
                mesh.export(folder / "background_mesh.ply")  # the world frame, as the point clouds
                # glTF's +y is up: the scene's up axis (ManiSkill's +z) turned to it.
                y_up = np.eye(4)
                y_up[:3, :3] = rotation_to_y_up(scene_up_axis(self.T_world_cam[0]))
                mesh.apply_transform(y_up)
                mesh.export(folder / "background_mesh.glb")
                files += ["background_mesh.ply", "background_mesh.glb"]
            if self.objects is not None and len(self.objects):
                files += self._write_object_plys(folder)
        manifest = {
            "format": "tesseract4d-recon4d",
            "format_version": RECON_FORMAT_VERSION,
            "num_frames": self.num_frames,
            "image_size": list(self.rgb.shape[1:3]),
            "fps": self.fps,
            "points_per_frame": [int(len(p)) for p in self.points_world],
            "background_points": int(len(self.background_points)),
            "mesh_faces": int(len(self.mesh_faces)),
            "files": files,
            "metadata": self.metadata,
        }
        if self.objects is not None:
            manifest["objects"] = {
                "source": self.objects.source, "instructed": self.objects.instructed,
                "names": [t.name for t in self.objects.tracks],
                "colour_names": [t.colour_name for t in self.objects.tracks],
                "colors": [[int(c) for c in t.color] for t in self.objects.tracks],
                "point_labels": bool(self.objects.point_object),
            }
        (folder / MANIFEST).write_text(json.dumps(manifest, indent=2, default=str))

    def _object_arrays(self, cat) -> dict:
        """The object layer's arrays for the npz (none without one)."""
        if self.objects is None:
            return {}
        out = {}
        for k, tr in enumerate(self.objects.tracks):
            out.update({
                f"object_{k}_points": tr.points_object.astype(np.float32), f"object_{k}_colors": tr.colors.astype(np.uint8),
                f"object_{k}_normals": tr.normals_object.astype(np.float32),
                f"object_{k}_T_world_object": tr.T_world_object.astype(np.float64),
                f"object_{k}_visibility": tr.visibility.astype(np.float32),
                f"object_{k}_confidence": tr.confidence.astype(np.float32), f"object_{k}_state": tr.state.astype(np.int8),
            })
        if self.objects.point_object:
            out["point_object"] = cat(self.objects.point_object, np.int16, ())
        return out

    def _write_object_plys(self, folder: Path) -> list[str]:
        """Each object's point set in its own frame, and every object placed per frame (world)."""
        (folder / "objects" / "frames").mkdir(parents=True)
        files, used = [], set()
        for tr in self.objects.tracks:
            stem = "".join(c if c.isalnum() or c in "-_" else "_" for c in tr.name) or "object"
            while stem in used:
                stem += "_"
            used.add(stem)
            write_point_ply(folder / "objects" / f"{stem}.ply", tr.points_object, tr.colors, tr.normals_object)
            files.append(f"objects/{stem}.ply")
        for t in range(self.num_frames):
            tracks = self.objects.tracks
            pts = np.concatenate([tr.points_world(t) for tr in tracks])
            cols = np.concatenate([tr.colors for tr in tracks])
            nrm = np.concatenate([tr.normals_object @ tr.T_world_object[t, :3, :3].T for tr in tracks])
            write_point_ply(folder / "objects" / "frames" / f"frame_{t:04d}.ply", pts, cols, nrm)
            files.append(f"objects/frames/frame_{t:04d}.ply")
        return files

    @staticmethod
    def _load_objects(z, manifest: dict, offsets: np.ndarray) -> ObjectLayer | None:
        info = manifest.get("objects")
        if info is None:
            return None
        tracks = []
        for k, name in enumerate(info["names"]):
            tracks.append(ObjectTrack(
                name=name, color=np.asarray(info["colors"][k], np.uint8), colour_name=info["colour_names"][k],
                points_object=z[f"object_{k}_points"], colors=z[f"object_{k}_colors"], normals_object=z[f"object_{k}_normals"],
                T_world_object=z[f"object_{k}_T_world_object"], visibility=z[f"object_{k}_visibility"],
                confidence=z[f"object_{k}_confidence"], state=z[f"object_{k}_state"],
            ))
        labels = []
        if info.get("point_labels"):
            a = z["point_object"]
            labels = [a[offsets[i]:offsets[i + 1]] for i in range(len(offsets) - 1)]
        return ObjectLayer(tracks=tracks, source=info.get("source", ""), instructed=info.get("instructed"), point_object=labels)

    @classmethod
    def load(cls, path: str | os.PathLike) -> "Recon4D":
        path = Path(path)
        manifest_path = path / MANIFEST
        if not manifest_path.is_file():
            raise ReconFormatError(f"{path} is not a reconstruction folder (no {MANIFEST}); write one with `tesseract4d reconstruct`.")
        try:
            manifest = json.loads(manifest_path.read_text())
        except json.JSONDecodeError as e:
            raise ReconFormatError(f"{manifest_path} is corrupt ({e}); re-run `tesseract4d reconstruct`.") from e
        if manifest.get("format_version") not in READABLE_VERSIONS:
            raise ReconFormatError(
                f"{path} is reconstruction format {manifest.get('format_version')}; this tesseract4d reads "
                f"{', '.join(map(str, READABLE_VERSIONS))}. Re-run `tesseract4d reconstruct` on the source video."
            )
        if not (path / ARRAYS).is_file():
            raise ReconFormatError(f"{path} has a {MANIFEST} but no {ARRAYS}: the reconstruction is incomplete; "
                                   f"re-run `tesseract4d reconstruct`.")
        try:
            z = np.load(path / ARRAYS)
            off = z["offsets"]
            split = lambda a: [a[off[i]:off[i + 1]] for i in range(len(off) - 1)]  # noqa: E731
            return cls(
                points_world=split(z["points_world"]),
                colors=split(z["colors"]),
                normals_world=split(z["normals_world"]),
                dynamic=split(z["dynamic"]),
                rgb=z["rgb"], depth_m=z["depth_m"], normal_cam=z["normal_cam"],
                K=z["K"], T_world_cam=z["T_world_cam"], fps=float(manifest.get("fps", 10.0)),
                background_points=z["background_points"], background_colors=z["background_colors"],
                background_normals=z["background_normals"], mesh_vertices=z["mesh_vertices"],
                mesh_faces=z["mesh_faces"], mesh_colors=z["mesh_colors"],
                metadata=manifest.get("metadata", {}),
                objects=cls._load_objects(z, manifest, off),
            )
        except (OSError, KeyError, ValueError, IndexError, TypeError) as e:
            raise ReconFormatError(f"{path / ARRAYS} is corrupt or truncated ({e}); re-run `tesseract4d reconstruct`.") from e


def write_point_ply(path: str | os.PathLike, points: np.ndarray, colors: np.ndarray | None = None, normals: np.ndarray | None = None) -> None:
    """Binary little-endian PLY with float xyz, optional float normals and uchar RGB."""
    points = np.asarray(points, np.float32).reshape(-1, 3)
    fields = [("x", "<f4"), ("y", "<f4"), ("z", "<f4")]
    if normals is not None:
        fields += [("nx", "<f4"), ("ny", "<f4"), ("nz", "<f4")]
    if colors is not None:
        fields += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
    data = np.empty(len(points), dtype=fields)
    data["x"], data["y"], data["z"] = points.T
    if normals is not None:
        n = np.asarray(normals, np.float32).reshape(-1, 3)
        data["nx"], data["ny"], data["nz"] = n.T
    if colors is not None:
        c = np.asarray(colors, np.uint8).reshape(-1, 3)
        data["red"], data["green"], data["blue"] = c.T
    ply_type = {"<f4": "float", "u1": "uchar"}
    header = ["ply", "format binary_little_endian 1.0", f"element vertex {len(points)}"]
    header += [f"property {ply_type[t]} {n}" for n, t in fields]
    header.append("end_header")
    with open(path, "wb") as f:
        f.write(("\n".join(header) + "\n").encode("ascii"))
        f.write(data.tobytes())
