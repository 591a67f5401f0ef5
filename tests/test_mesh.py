"""TSDF meshes against the synthetic room's true surface, and mesh export round trips."""

from pathlib import Path

import numpy as np
import pytest
import trimesh
from scipy.spatial import cKDTree

from tambridge.export.config import MeshConfig
from tambridge.export.mesh import (
    MeshError,
    RgbdView,
    convert_mesh,
    fuse_tsdf_mesh,
    read_mesh,
    sensor_views,
    write_mesh,
)
from tambridge.geometry import inverse, transform_points
from tambridge.io.synthetic import default_camera, loop_path, make_room_scene, render
from tambridge.io.tum import open_sequence
from tambridge.evaluation.metrics import WorldMetrics, write_metrics
from tambridge.run_folder import RunFolder, Start
from tests.test_report import _metrics as run_metrics

MAX_DEPTH_M = 3.0


def _sample_mesh_surface_m(mesh: trimesh.Trimesh, spacing_m: float, seed: int = 0) -> np.ndarray:
    """About one point per ``spacing_m`` squared of surface, uniformly at random, (N, 3) metres."""
    count = max(1, int(np.ceil(mesh.area / spacing_m**2)))
    points, _ = trimesh.sample.sample_surface(mesh, count, seed=seed)
    return np.asarray(points)


def _seen_surface(surface_m: np.ndarray, views: list[RgbdView], camera, tolerance_m: float = 0.01) -> np.ndarray:
    """The points of ``surface_m`` (N, 3) that some view sees: in the image, in range, and not occluded."""
    seen = np.zeros(len(surface_m), bool)
    for view in views:
        points = transform_points(inverse(view.world_from_camera), surface_m).astype(np.float32)
        z = points[:, 2]
        in_front = (z > 0.1) & (z < MAX_DEPTH_M)
        safe_z = np.where(in_front, z, 1.0)
        u = np.round(camera.fx * points[:, 0] / safe_z + camera.cx).astype(int)
        v = np.round(camera.fy * points[:, 1] / safe_z + camera.cy).astype(int)
        inside = in_front & (u >= 0) & (u < camera.width) & (v >= 0) & (v < camera.height)
        depth = np.zeros(len(surface_m))
        depth[inside] = view.depth_m[v[inside], u[inside]]
        seen |= inside & (np.abs(depth - z) < tolerance_m)
    return surface_m[seen]


@pytest.fixture(scope="module")
def sequence_views(synthetic_sequence_dir: Path):
    """Every third frame of the session's synthetic sequence (160x120, depth quantised to 0.2 mm), true poses."""
    sequence = open_sequence(synthetic_sequence_dir)
    poses = sequence.ground_truth.nearest(sequence.timestamps_s).world_from_camera
    return list(sensor_views(sequence, poses, frame_stride=3)), sequence.camera


@pytest.fixture(scope="module")
def coarse_mesh(sequence_views):
    views, camera = sequence_views
    return fuse_tsdf_mesh(views, camera, MeshConfig(voxel_size_m=0.04, truncation_m=0.16, max_depth_m=MAX_DEPTH_M))


@pytest.mark.slow
def test_tsdf_mesh_lies_on_the_true_surface(sequence_views):
    """Chamfer distance to the seen part of the true surface under 1 cm at 1 cm voxels.

    The true surface is sampled on a 1 cm grid, which alone puts ~4 mm into the mesh -> truth half; the exact
    distance to the planes is checked in the next test.
    """
    views, camera = sequence_views
    assert len(views) == 10
    mesh = fuse_tsdf_mesh(views, camera, MeshConfig(voxel_size_m=0.01, truncation_m=0.04, max_depth_m=MAX_DEPTH_M))
    truth = _seen_surface(make_room_scene(0).sample_surface_m(0.01), views, camera)
    mesh_points = _sample_mesh_surface_m(mesh, 0.005)
    accuracy_m, _ = cKDTree(truth).query(mesh_points)
    completeness_m, _ = cKDTree(mesh_points).query(truth)
    chamfer_m = 0.5 * (accuracy_m.mean() + completeness_m.mean())
    assert chamfer_m < 0.01, chamfer_m
    # The mesh covers what the views saw: nine in ten of the seen points lie within 2 cm of it.
    completeness_m, _ = cKDTree(mesh_points).query(truth)
    assert np.mean(completeness_m < 0.02) > 0.9


def test_mesh_vertices_match_the_exact_planes():
    """Noise-free float depth: vertices lie within a millimetre of the analytic faces (no half-pixel shift)."""
    scene = make_room_scene(0)
    camera = default_camera(160, 120)
    views = []
    for pose in loop_path(6):
        colour, depth_m = render(scene, camera, pose)
        views.append(RgbdView((colour * 255 + 0.5).astype(np.uint8), depth_m, pose))
    mesh = fuse_tsdf_mesh(views, camera, MeshConfig(voxel_size_m=0.02, truncation_m=0.08, max_depth_m=MAX_DEPTH_M))
    distance = np.full(len(mesh.vertices), np.inf)
    for face in scene.faces:
        local = mesh.vertices - face.centre_m
        u = np.clip(local @ face.axis_u, -face.half_u_m, face.half_u_m)
        v = np.clip(local @ face.axis_v, -face.half_v_m, face.half_v_m)
        nearest = face.centre_m + u[:, None] * face.axis_u + v[:, None] * face.axis_v
        distance = np.minimum(distance, np.linalg.norm(mesh.vertices - nearest, axis=1))
    assert len(mesh.vertices) > 10_000
    assert np.median(distance) < 0.001, np.median(distance)
    assert mesh.visual.vertex_colors.shape == (len(mesh.vertices), 4)


def test_min_views_drops_surfaces_seen_once(sequence_views):
    views, camera = sequence_views
    once = fuse_tsdf_mesh(views[:2], camera, MeshConfig(voxel_size_m=0.02, truncation_m=0.08, min_views=1))
    twice = fuse_tsdf_mesh(views[:2], camera, MeshConfig(voxel_size_m=0.02, truncation_m=0.08, min_views=2))
    assert 0 < len(twice.vertices) < len(once.vertices)


def test_bad_voxel_settings_name_the_keys():
    with pytest.raises(MeshError, match="mesh.truncation_m"):
        fuse_tsdf_mesh([], default_camera(32, 24), MeshConfig(voxel_size_m=0.05, truncation_m=0.02))


@pytest.mark.parametrize("format", ["ply", "obj", "glb"])
def test_export_round_trip_keeps_vertices(coarse_mesh, tmp_path, format):
    mesh = coarse_mesh
    write_mesh(tmp_path / "mesh.ply", mesh)
    converted = convert_mesh(tmp_path / "mesh.ply", tmp_path / f"mesh.{format}")
    loaded = trimesh.load(tmp_path / f"mesh.{format}", force="mesh", process=False)
    assert len(converted.vertices) == len(mesh.vertices)
    assert len(loaded.vertices) == len(mesh.vertices)
    assert len(loaded.faces) == len(mesh.faces)
    np.testing.assert_allclose(loaded.vertices, mesh.vertices, atol=1e-5)
    assert not list(tmp_path.glob("*.partial"))


def test_unknown_format_and_missing_file(tmp_path):
    mesh = trimesh.creation.box()
    with pytest.raises(MeshError, match="unknown mesh format 'stl'"):
        write_mesh(tmp_path / "mesh.stl", mesh)
    with pytest.raises(MeshError, match="not found"):
        read_mesh(tmp_path / "missing.ply")


def test_export_mesh_command(coarse_mesh, tmp_path):
    from click.testing import CliRunner

    from cli import main

    with RunFolder(tmp_path, Start.NEW, ["mesh.ply"]):
        write_mesh(tmp_path / "mesh.ply", coarse_mesh)
    no_world = CliRunner().invoke(main, ["export-mesh", str(tmp_path), "--format", "glb"])
    assert no_world.exit_code == 2 and "metrics.json: not found" in no_world.output and not (tmp_path / "mesh.glb").exists()
    for up_source, gltf_from_world in (("floor_plane", [[1, 0, 0], [0, 0, 1], [0, -1, 0]]),
                                       ("first_camera", [[1, 0, 0], [0, -1, 0], [0, 0, -1]])):
        world = WorldMetrics(frame="upright", up_source=up_source, upright_from_first_camera=np.eye(4).tolist())
        write_metrics(tmp_path / "metrics.json", run_metrics(world=world))
        for _ in range(2):  # a second export replaces the first: the run's manifest lists it
            result = CliRunner().invoke(main, ["export-mesh", str(tmp_path), "--format", "glb"])
            assert result.exit_code == 0, result.output
            # glTF's y is up: the world's up (z, or the first camera's -y) becomes +y.
            np.testing.assert_allclose(read_mesh(tmp_path / "mesh.glb").vertices,
                                       np.asarray(coarse_mesh.vertices) @ np.array(gltf_from_world, float).T, atol=1e-6)
    result = CliRunner().invoke(main, ["export-mesh", str(tmp_path), "--format", "obj"])
    assert result.exit_code == 0, result.output
    np.testing.assert_allclose(read_mesh(tmp_path / "mesh.obj").vertices, coarse_mesh.vertices, atol=1e-6)
    # A file that is no output of the run is the user's: refused, untouched.
    (tmp_path / "mine.obj").write_text("mine")
    refused = CliRunner().invoke(main, ["export-mesh", str(tmp_path), "-o", str(tmp_path / "mine.obj")])
    assert refused.output == (f"error: -o {tmp_path / 'mine.obj'}: exists and is not a file of the run in {tmp_path}; "
                              "remove it or name a new file\n")
    assert refused.exit_code == 2 and (tmp_path / "mine.obj").read_text() == "mine"
    missing = CliRunner().invoke(main, ["export-mesh", str(tmp_path / "nothing")])
    assert missing.exit_code == 2 and "mesh.ply" in missing.output
    # Refused before anything is written: the run's own mesh.ply as output, a suffix that is not the format's.
    before = (tmp_path / "mesh.ply").read_bytes()
    for arguments, message in ((["--format", "ply"], "mesh.ply: is an input of this command"),
                               (["--format", "glb", "-o", str(tmp_path / "m.obj")], "--format glb writes a .glb file")):
        refused = CliRunner().invoke(main, ["export-mesh", str(tmp_path), *arguments])
        assert refused.exit_code == 2 and message in refused.output and len(refused.output.splitlines()) == 1
    assert (tmp_path / "mesh.ply").read_bytes() == before and not (tmp_path / "m.obj").exists()
