"""Fusion of the static background: a truncated signed distance field (Open3D tensor
``VoxelBlockGrid``) integrated over every frame's static pixels, then its surface as a
coloured point cloud with normals and as a triangle mesh.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from tesseract4d.geometry import depth_to_world_points, invert_pose

# The automatic voxel is this many pixel footprints at the median depth (a footprint is the
# width one pixel covers on a fronto-parallel surface).
AUTO_VOXEL_PIXELS = 1.5
# Voxel blocks of 8^3; the hash map grows on demand, this is only the initial capacity.
BLOCK_RESOLUTION = 8
INITIAL_BLOCKS = 10_000


@dataclass
class FusedSurface:
    """Fused static surface, world frame (metres)."""

    points: np.ndarray = field(default_factory=lambda: np.zeros((0, 3), np.float32))  # (N, 3)
    colors: np.ndarray = field(default_factory=lambda: np.zeros((0, 3), np.uint8))  # (N, 3)
    normals: np.ndarray = field(default_factory=lambda: np.zeros((0, 3), np.float32))  # (N, 3) unit
    mesh_vertices: np.ndarray = field(default_factory=lambda: np.zeros((0, 3), np.float32))  # (V, 3)
    mesh_faces: np.ndarray = field(default_factory=lambda: np.zeros((0, 3), np.int32))  # (F, 3)
    mesh_colors: np.ndarray = field(default_factory=lambda: np.zeros((0, 3), np.uint8))  # (V, 3)


def auto_voxel_size(depth_m: np.ndarray, K: np.ndarray) -> float:
    """Voxel edge (m) matched to the image resolution: AUTO_VOXEL_PIXELS pixel footprints at the
    median valid depth. depth_m (T, H, W), K (T, 3, 3)."""
    valid = np.isfinite(depth_m) & (depth_m > 0)
    if not valid.any():
        return 0.01
    median_depth = float(np.median(depth_m[valid]))
    focal = float(np.mean(K[:, [0, 1], [0, 1]]))
    return AUTO_VOXEL_PIXELS * median_depth / focal


def _to_uint8(colors01: np.ndarray) -> np.ndarray:
    return np.clip(np.rint(np.asarray(colors01) * 255.0), 0, 255).astype(np.uint8)


def fuse_tsdf(
    depth_m: np.ndarray,
    rgb: np.ndarray,
    K: np.ndarray,
    T_world_cam: np.ndarray,
    include: np.ndarray,
    voxel_size_m: float,
    trunc_voxels: float = 4.0,
    mesh: bool = True,
) -> FusedSurface:
    """Integrate the ``include`` pixels of every frame into a TSDF and extract its surface.

    depth_m (T, H, W) metres (0 = none), rgb (T, H, W, 3) uint8, K (T, 3, 3),
    T_world_cam (T, 4, 4), include (T, H, W) bool. Returns an empty surface when no pixel is
    included.
    """
    import open3d as o3d
    import open3d.core as o3c

    depth = np.where(include & np.isfinite(depth_m) & (depth_m > 0), depth_m, 0.0).astype(np.float32)
    if not (depth > 0).any():
        return FusedSurface()
    depth_max = float(depth.max()) * 1.01 + trunc_voxels * voxel_size_m
    device = o3c.Device("CPU:0")
    grid = o3d.t.geometry.VoxelBlockGrid(
        attr_names=("tsdf", "weight", "color"),
        attr_dtypes=(o3c.float32, o3c.float32, o3c.float32),
        attr_channels=((1), (1), (3)),
        voxel_size=float(voxel_size_m),
        block_resolution=BLOCK_RESOLUTION,
        block_count=INITIAL_BLOCKS,
        device=device,
    )
    for t in range(depth.shape[0]):
        if not (depth[t] > 0).any():
            continue
        depth_img = o3d.t.geometry.Image(o3c.Tensor(np.ascontiguousarray(depth[t])))
        color_img = o3d.t.geometry.Image(o3c.Tensor(np.ascontiguousarray(rgb[t], np.float32) / 255.0))
        intrinsic = o3c.Tensor(np.asarray(K[t], np.float64))
        extrinsic = o3c.Tensor(invert_pose(T_world_cam[t]))  # world -> camera
        try:
            blocks = grid.compute_unique_block_coordinates(depth_img, intrinsic, extrinsic, 1.0, depth_max, trunc_voxel_multiplier=trunc_voxels)
        except RuntimeError as err:
            # Open3D looks for blocks only at every 4th pixel; a frame whose few valid pixels all
            # lie between those finds none. Its blocks then come from all its valid pixels.
            if "No block is touched" not in str(err):
                raise
            points_world, _ = depth_to_world_points(depth[t], K[t], T_world_cam[t])
            cloud = o3d.t.geometry.PointCloud(o3c.Tensor(np.ascontiguousarray(points_world, np.float32)))
            blocks = grid.compute_unique_block_coordinates(cloud, trunc_voxel_multiplier=trunc_voxels)
        grid.integrate(blocks, depth_img, color_img, intrinsic, intrinsic, extrinsic, 1.0, depth_max, trunc_voxel_multiplier=trunc_voxels)
    out = FusedSurface()
    pcd = grid.extract_point_cloud()
    if not pcd.is_empty():
        out.points = pcd.point.positions.numpy().astype(np.float32)
        out.colors = _to_uint8(pcd.point.colors.numpy())
        out.normals = pcd.point.normals.numpy().astype(np.float32)
    if mesh:
        tri = grid.extract_triangle_mesh()
        if not tri.is_empty() and "indices" in tri.triangle:
            out.mesh_vertices = tri.vertex.positions.numpy().astype(np.float32)
            out.mesh_faces = tri.triangle.indices.numpy().astype(np.int32)
            out.mesh_colors = _to_uint8(tri.vertex.colors.numpy())
    return out
