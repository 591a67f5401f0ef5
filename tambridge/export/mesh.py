"""Triangle meshes for downstream tools: TSDF fusion of posed RGB-D views, and export to PLY, OBJ and GLB.

Fusion uses Open3D's tensor ``VoxelBlockGrid`` (Curless & Levoy 1996 volumetric integration on a hashed grid
of voxel blocks, then marching cubes; Open3D 0.20's legacy ``ScalableTSDFVolume`` extracts empty meshes).
The depth fused is either the sensor's (``mesh.source = tsdf``) or the depth
rendered from the Gaussian map (``mesh.source = gaussians``): both come in as :class:`RgbdView` s.
Meshes travel as ``trimesh.Trimesh`` (vertices in the world frame, metres; RGBA vertex colours) and are
written through trimesh into bytes, then atomically, so a PLY, OBJ or GLB is never seen half written.
"""

from __future__ import annotations

import dataclasses
import logging
from pathlib import Path
from typing import Iterable, Iterator, Sequence

import numpy as np
import open3d as o3d
import open3d.core as o3c
import trimesh

from tambridge.camera import Camera
from tambridge.export.config import MeshConfig, MeshSource
from tambridge.errors import TambridgeError
from tambridge.files import atomic_write_bytes
from tambridge.geometry import inverse
from tambridge.io.tum import RgbdSequence
from tambridge.mapping.stage import MappingStage
from tambridge.trajectory import Trajectory

logger = logging.getLogger("tambridge.export.mesh")

MESH_FORMATS = ("ply", "obj", "glb")
BLOCK_RESOLUTION = 8
"""Voxels along each side of a hashed block of the grid."""
INITIAL_BLOCK_COUNT = 4096
"""Blocks the hash map holds before it first grows."""


class MeshError(TambridgeError):
    """A mesh file is missing, unreadable or asked for in an unknown format."""


@dataclasses.dataclass
class RgbdView:
    """One view to fuse: ``rgb`` (H, W, 3) uint8, ``depth_m`` (H, W) float32 metres (0 = invalid), its
    ``world_from_camera`` (4, 4) float64."""

    rgb: np.ndarray
    depth_m: np.ndarray
    world_from_camera: np.ndarray


def fuse_tsdf_mesh(views: Iterable[RgbdView], camera: Camera, config: MeshConfig) -> trimesh.Trimesh:
    """Integrate ``views`` into a TSDF of ``config.voxel_size_m`` voxels and extract its zero level set.

    Depth beyond ``config.max_depth_m`` is ignored; the signed distance is truncated at ``config.truncation_m``.
    Voxels observed in fewer than ``config.min_views`` views are left out. Returns a mesh in the world
    frame (metres) with per-vertex colours; empty when nothing was seen.
    """
    if config.voxel_size_m <= 0 or config.truncation_m <= config.voxel_size_m:
        raise MeshError(
            f"mesh.voxel_size_m={config.voxel_size_m}, mesh.truncation_m={config.truncation_m}: the voxel size "
            "must be positive and the truncation larger than it (3-5 voxels is usual)"
        )
    grid = o3d.t.geometry.VoxelBlockGrid(
        attr_names=("tsdf", "weight", "color"),
        attr_dtypes=(o3c.float32, o3c.float32, o3c.float32),
        attr_channels=((1), (1), (3)),
        voxel_size=config.voxel_size_m,
        block_resolution=BLOCK_RESOLUTION,
        block_count=INITIAL_BLOCK_COUNT,
        device=o3c.Device("CPU:0"),
    )
    # Open3D's VoxelBlockGrid takes the truncation as a multiple of the voxel size.
    truncation_voxels = config.truncation_m / config.voxel_size_m
    intrinsic = o3c.Tensor(camera.K, o3c.float64)
    # Open3D looks up the depth of a voxel at the pixel int(u), int(v) (truncation), while pixel centres sit at
    # integer coordinates (OpenCV): a principal point moved by +0.5 px turns that into rounding. Without it every
    # surface moves by half a pixel's footprint.
    rounding_K = camera.K.copy()
    rounding_K[:2, 2] += 0.5
    integration_intrinsic = o3c.Tensor(rounding_K, o3c.float64)
    count = 0
    for view in views:
        assert view.rgb.shape == (camera.height, camera.width, 3), view.rgb.shape
        assert view.depth_m.shape == (camera.height, camera.width), view.depth_m.shape
        camera_from_world = o3c.Tensor(inverse(view.world_from_camera), o3c.float64)
        depth = o3d.t.geometry.Image(o3c.Tensor(np.ascontiguousarray(view.depth_m, dtype=np.float32)))
        colour = o3d.t.geometry.Image(o3c.Tensor(np.ascontiguousarray(view.rgb, dtype=np.float32) / 255.0))
        blocks = grid.compute_unique_block_coordinates(
            depth, intrinsic, camera_from_world, 1.0, config.max_depth_m, truncation_voxels
        )
        grid.integrate(blocks, depth, colour, integration_intrinsic, integration_intrinsic, camera_from_world, 1.0,
                       config.max_depth_m, truncation_voxels)
        count += 1
    # Each view adds 1 to a voxel's weight and Open3D keeps voxels whose weight exceeds the threshold.
    mesh = grid.extract_triangle_mesh(weight_threshold=config.min_views - 0.5)
    vertices = mesh.vertex.positions.numpy().astype(np.float64) if "positions" in mesh.vertex else np.zeros((0, 3))
    faces = mesh.triangle.indices.numpy().astype(np.int64) if "indices" in mesh.triangle else np.zeros((0, 3), np.int64)
    colours = mesh.vertex.colors.numpy() if "colors" in mesh.vertex else np.zeros((len(vertices), 3))
    logger.info("TSDF mesh from %d views at %.3f m voxels: %d vertices, %d triangles",
                count, config.voxel_size_m, len(vertices), len(faces))
    rgba = np.concatenate([np.clip(colours * 255.0 + 0.5, 0, 255), np.full((len(colours), 1), 255.0)], axis=1)
    return trimesh.Trimesh(vertices=vertices, faces=faces, vertex_colors=rgba.astype(np.uint8), process=False)


def sensor_views(sequence, trajectory_world_from_camera: np.ndarray, frame_stride: int) -> Iterator[RgbdView]:
    """Every ``frame_stride``-th frame of ``sequence`` (an RgbdSequence) with its pose in ``(N, 4, 4)``."""
    assert len(trajectory_world_from_camera) == len(sequence), (len(trajectory_world_from_camera), len(sequence))
    for index in range(0, len(sequence), max(1, frame_stride)):
        frame = sequence[index]
        yield RgbdView(frame.rgb, frame.depth_m, trajectory_world_from_camera[index])


def gaussian_views(
    gaussians, camera: Camera, world_from_camera: Sequence[np.ndarray], min_silhouette: float = 0.9
) -> Iterator[RgbdView]:
    """Views rendered from a Gaussian map (``tambridge.gaussians.GaussianTensors``) at the given poses.

    The rendered depth is divided by the silhouette (it is accumulated unnormalised) and kept only where the
    silhouette exceeds ``min_silhouette``: at the map's border the depth is a blend with empty space.
    """
    import torch

    from tambridge.gaussians.rasterizer import render

    with torch.no_grad():
        for pose in world_from_camera:
            output = render(gaussians, camera, np.asarray(pose, np.float64))
            silhouette = output.silhouette.detach().cpu().numpy()
            depth = output.depth_m.detach().cpu().numpy()
            covered = silhouette > min_silhouette
            depth_m = np.where(covered, depth / np.maximum(silhouette, 1e-6), 0.0).astype(np.float32)
            rgb = np.clip(output.rgb.detach().cpu().numpy() * 255.0 + 0.5, 0, 255).astype(np.uint8)
            yield RgbdView(rgb, depth_m, np.asarray(pose, np.float64))


def mesh_format(path: Path, format: str | None = None) -> str:
    """The mesh format named by ``format`` or, when None, by ``path``'s suffix; one of :data:`MESH_FORMATS`."""
    name = (format or Path(path).suffix.lstrip(".")).lower()
    if name not in MESH_FORMATS:
        raise MeshError(f"{path}: unknown mesh format {name!r}; use one of {', '.join(MESH_FORMATS)}")
    return name


def write_mesh(path: Path, mesh: trimesh.Trimesh, format: str | None = None) -> None:
    """Write ``mesh`` to ``path`` atomically as PLY (binary), OBJ (vertex colours as extra columns) or GLB."""
    data = mesh.export(file_type=mesh_format(path, format))
    atomic_write_bytes(Path(path), data if isinstance(data, bytes) else data.encode())


def read_mesh(path: Path) -> trimesh.Trimesh:
    """Read a PLY, OBJ or GLB mesh as one ``trimesh.Trimesh``, vertices as stored (nothing merged)."""
    path = Path(path)
    if not path.is_file():
        raise MeshError(f"{path}: mesh not found; 'tambridge reconstruct' writes mesh.ply (mesh.enabled=true)")
    try:
        return trimesh.load(path, file_type=mesh_format(path), force="mesh", process=False)
    except (ValueError, KeyError, IndexError) as error:
        raise MeshError(f"{path}: cannot read mesh ({error})") from error


def convert_mesh(source: Path, target: Path, format: str | None = None,
                 target_from_source: np.ndarray | None = None) -> trimesh.Trimesh:
    """Convert a mesh file to another format (by ``format`` or ``target``'s suffix), its vertices rotated by
    ``target_from_source`` (3, 3) where given; returns the mesh written."""
    mesh = read_mesh(source)
    if target_from_source is not None:
        mesh = trimesh.Trimesh(vertices=np.asarray(mesh.vertices) @ np.asarray(target_from_source).T, faces=mesh.faces,
                               vertex_colors=mesh.visual.vertex_colors, process=False)
    write_mesh(target, mesh, format)
    return mesh


def run_mesh(sequence: RgbdSequence, trajectory: Trajectory, config: MeshConfig,
             mapping: MappingStage | None) -> trimesh.Trimesh:
    """TSDF mesh of every ``frame_stride``-th frame at its final pose; ``source=rendered`` fuses the
    map's rendered depth (at the mapping resolution, from the rendering poses) instead of the sensor's."""
    source = config.source
    stride = config.frame_stride
    if source == MeshSource.rendered and mapping is not None and len(mapping.map):
        poses = mapping.rendering_poses(trajectory)[::stride]
        views, camera = gaussian_views(mapping.map.world_gaussians(), mapping.camera, poses), mapping.camera
    else:
        if source == MeshSource.rendered:
            logger.warning("mesh.source=rendered but no Gaussian map was built (mapper.enabled=false?): fusing sensor depth")
        views, camera = sensor_views(sequence, trajectory.world_from_camera, stride), sequence.camera
    return fuse_tsdf_mesh(views, camera, config)
