"""The upright world of the exported files: up from the accelerometer or the map's planes, applied once to every
exported file, and ``export.world=first_camera`` writing the run's own frame."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.spatial import cKDTree

from pipelines.reconstruct import reconstruct
from tambridge.config import load_config
from tambridge.errors import SequenceFormatError
from tambridge.evaluation.metrics import read_metrics
from tambridge.export.config import ExportWorld
from tambridge.export.mesh import read_mesh
from tambridge.export.splats import load_ply, save_ply
from tambridge.export.world import (
    UpSource,
    WorldFrame,
    camera_up,
    dominant_planes,
    find_world,
    up_from_accelerometer,
    up_from_planes,
    upright_from_up,
)
from tambridge.gaussians.model import GaussianTensors
from tambridge.gaussians.rasterizer import render
from tambridge.geometry import exp_se3, inverse, transform_points
from tambridge.io.synthetic import SynthOptions, default_camera, write_synthetic_sequence
from tambridge.io.tum import KINECT_CAMERA_FROM_ACCELEROMETER, AccelerometerSamples, read_accelerometer
from tambridge.trajectory import Trajectory, read_tum_trajectory

ROLL_DEG = 20.0
"""The synthetic camera's known tilt about its optical axis (beside the loop's own pitch)."""
GRAVITY_MPS2 = 9.81


def angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip(a @ b / np.linalg.norm(a) / np.linalg.norm(b), -1.0, 1.0))))


def true_up_in_first_camera(truth: Trajectory) -> np.ndarray:
    """The synthetic world's z (up) in the first camera's frame."""
    return truth.world_from_camera[0, :3, :3].T @ np.array([0.0, 0.0, 1.0])


def kinect_samples(truth: Trajectory, seed: int = 0, shake_mps2: float = 0.3) -> AccelerometerSamples:
    """What a Kinect on the truth's poses reports: the specific force (up, plus a shaking hand) in its axes, five
    samples per frame."""
    rng = np.random.default_rng(seed)
    stamps = (truth.timestamps_s[:, None] + np.linspace(-0.01, 0.01, 5)).ravel()
    rotations = np.repeat(truth.world_from_camera[:, :3, :3], 5, axis=0)
    force_world = np.array([0.0, 0.0, GRAVITY_MPS2]) + rng.normal(0.0, shake_mps2, (len(stamps), 3))
    in_camera = np.einsum("nji,nj->ni", rotations, force_world)
    return AccelerometerSamples(stamps, in_camera @ KINECT_CAMERA_FROM_ACCELEROMETER)  # the diagonal is its inverse


def write_accelerometer(path, samples: AccelerometerSamples) -> None:
    lines = ["# accelerometer data", "# timestamp ax ay az"]
    lines += [f"{t:.6f} {a[0]:.6f} {a[1]:.6f} {a[2]:.6f}" for t, a in zip(samples.timestamps_s, samples.acceleration_mps2)]
    path.write_text("\n".join(lines) + "\n")


@pytest.fixture(scope="module")
def tilted_sequence(tmp_path_factory):
    """The 30-frame 160x120 synthetic loop, every camera rolled by ROLL_DEG; (folder, ground truth)."""
    folder = tmp_path_factory.mktemp("tilted") / "room"
    truth = write_synthetic_sequence(folder, SynthOptions(frame_count=30, roll_deg=ROLL_DEG))
    return folder, truth


def test_accelerometer_file_round_trip_and_bad_line(tmp_path):
    samples = AccelerometerSamples(np.array([2.0, 1.0]), np.array([[0.1, 9.7, -0.5], [0.2, 9.8, -0.4]]))
    write_accelerometer(tmp_path / "accelerometer.txt", samples)
    read = read_accelerometer(tmp_path / "accelerometer.txt")
    np.testing.assert_array_equal(read.timestamps_s, [1.0, 2.0])
    np.testing.assert_allclose(read.acceleration_mps2, samples.acceleration_mps2[::-1], atol=1e-6)
    (tmp_path / "bad.txt").write_text("1.0 0.1 9.8\n")
    with pytest.raises(SequenceFormatError, match=r"bad.txt line 1: expected 4 numbers"):
        read_accelerometer(tmp_path / "bad.txt")


def test_upright_from_up_puts_up_on_z_and_keeps_the_first_camera_level_and_facing():
    up = np.array([0.1, -0.9, -0.3])
    transform = upright_from_up(up)
    rotation = transform[:3, :3]
    np.testing.assert_allclose(rotation @ rotation.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(rotation) == pytest.approx(1.0)
    np.testing.assert_allclose(rotation @ (up / np.linalg.norm(up)), [0, 0, 1], atol=1e-12)
    np.testing.assert_array_equal(transform[:3, 3], 0.0)
    # The first camera's right stays horizontal and in the x-z plane of the camera; its view looks along +y.
    assert (rotation @ [1.0, 0.0, 0.0])[1] == pytest.approx(0.0, abs=1e-12)
    assert (rotation @ [0.0, 0.0, 1.0])[1] > 0.9


def test_accelerometer_recovers_up_within_a_degree_of_a_tilted_truth(tilted_sequence):
    folder, truth = tilted_sequence
    first_camera = Trajectory(truth.timestamps_s, inverse(truth.world_from_camera[0]) @ truth.world_from_camera)
    expected = true_up_in_first_camera(truth)
    assert angle_deg(np.array([0.0, -1.0, 0.0]), expected) > ROLL_DEG  # the first camera's image up is far off
    up = up_from_accelerometer(kinect_samples(truth), first_camera)
    assert angle_deg(up, expected) < 1.0
    # Read in the camera's axes as they are (the sign convention wrong), up would point elsewhere.
    assert angle_deg(up_from_accelerometer(kinect_samples(truth), first_camera, np.eye(3)), expected) > 30.0


def room_surface_in_first_camera(truth: Trajectory) -> np.ndarray:
    """(P, 3) points of the synthetic room's surface ahead of the cameras and below the ceiling, in the truth's
    first camera frame."""
    from tambridge.io.synthetic import make_room_scene

    first_from_world = inverse(truth.world_from_camera[0])
    points = make_room_scene().sample_surface_m(0.1)
    visible = points[(points[:, 0] > -0.8) & (points[:, 2] < 2.7)]
    return transform_points(first_from_world, visible)


def test_floor_plane_of_the_synthetic_room_gives_up(tilted_sequence):
    _, truth = tilted_sequence
    points_first = room_surface_in_first_camera(truth)
    poses_first = inverse(truth.world_from_camera[0]) @ truth.world_from_camera
    planes = dominant_planes(points_first)
    found = up_from_planes(planes, camera_up(poses_first))
    assert found is not None and found[1] == UpSource.floor_plane
    assert angle_deg(found[0], true_up_in_first_camera(truth)) < 1.0
    # Two walls without a floor: up is their normals' cross product.
    walls = [plane for plane in planes if abs(plane.normal @ true_up_in_first_camera(truth)) < 0.2]
    found = up_from_planes(walls, camera_up(poses_first))
    assert found is not None and found[1] == UpSource.wall_planes
    assert angle_deg(found[0], true_up_in_first_camera(truth)) < 1.0
    assert up_from_planes([], camera_up(poses_first)) is None


def test_a_floor_near_the_accelerometers_up_levels_the_world_in_its_place(tilted_sequence):
    """An accelerometer whose axes are 5 degrees off (as the Kinect's nominal ones on fr1/xyz): the room's floor,
    within 10 degrees of its up, gives up to within a degree; 15 degrees off, the floor is not taken for it."""
    _, truth = tilted_sequence
    first_camera = Trajectory(truth.timestamps_s, inverse(truth.world_from_camera[0]) @ truth.world_from_camera)
    points_first = room_surface_in_first_camera(truth)
    expected = true_up_in_first_camera(truth)
    for off_deg, source in ((5.0, UpSource.accelerometer_floor), (15.0, UpSource.accelerometer)):
        # A roll of the sensor's axes about the optical axis.
        axes = exp_se3(np.array([0.0, 0.0, 0.0, 0.0, 0.0, np.radians(off_deg)]))[:3, :3]
        samples = kinect_samples(truth)
        misread = AccelerometerSamples(samples.timestamps_s, samples.acceleration_mps2 @ axes.T)
        world = find_world(ExportWorld.upright, first_camera, misread, points_first)
        up = world.upright_from_first_camera[2, :3]
        assert world.up_source == source
        if source == UpSource.accelerometer_floor:
            assert angle_deg(up, expected) < 1.0
        else:
            assert angle_deg(up, expected) > 10.0


def test_splats_render_the_same_in_the_upright_world(tmp_path):
    """splats.ply written in the upright world and rendered at the upright poses shows what the run's own map
    shows at its own poses."""
    rng = np.random.default_rng(0)
    count = 400
    gaussians = GaussianTensors(
        means_m=torch.tensor(rng.uniform([-1, -0.8, 1.5], [1, 0.8, 3.0], (count, 3)), dtype=torch.float32),
        rgb=torch.tensor(rng.uniform(0, 1, (count, 3)), dtype=torch.float32),
        log_radii_m=torch.tensor(np.log(rng.uniform(0.03, 0.08, count)), dtype=torch.float32),
        opacity_logits=torch.tensor(rng.uniform(0, 3, count), dtype=torch.float32),
    )
    camera = default_camera(80, 60)
    world = WorldFrame(ExportWorld.upright, UpSource.floor_plane, upright_from_up(np.array([0.2, -0.8, -0.4])))
    save_ply(tmp_path / "splats.ply", world.gaussians(gaussians))
    loaded = load_ply(tmp_path / "splats.ply")
    poses = Trajectory(np.arange(2.0), np.stack([np.eye(4), exp_se3(np.array([0.1, -0.05, 0.2, 0.02, 0.08, -0.05]))]))
    for pose, upright_pose in zip(poses.world_from_camera, world.trajectory(poses).world_from_camera):
        before = render(gaussians, camera, pose).rgb
        after = render(loaded, camera, upright_pose).rgb
        assert before.std() > 0.05
        # float32 means rounded differently move a pixel's Gaussian order or tile at most here and there.
        difference = np.abs(after.numpy() - before.numpy())
        assert difference.mean() < 1e-5 and difference.max() < 1e-2
    assert not torch.allclose(loaded.means_m, gaussians.means_m, atol=1e-2)


def test_first_camera_world_is_the_identity_written_as_given():
    world = find_world(ExportWorld.first_camera, Trajectory([0.0], np.eye(4)[None]), None, np.zeros((0, 3)))
    assert world.up_source == UpSource.first_camera and world.is_identity
    trajectory = Trajectory([0.0], np.eye(4)[None])
    assert world.trajectory(trajectory) is trajectory


FAST = ("frontend.kind=open3d_f2f", "mapper.iterations=4", "bridge.iterations=3",
        "mapper.final_iterations_per_view=1", "input.max_frames=8")


@pytest.fixture(scope="module")
def first_camera_run(tilted_sequence, tmp_path_factory):
    """The tilted loop reconstructed with FAST in the first camera's frame: (its folder, the run's result). Such a run
    reads no accelerometer (test_a_bad_accelerometer_file_stops_the_run_before_any_output), so both cases below
    compare against this one run."""
    first = tmp_path_factory.mktemp("first_camera") / "first"
    result = reconstruct(tilted_sequence[0], first, load_config(None, (*FAST, "export.world=first_camera")),
                         progress=False)
    return first, result


@pytest.mark.slow
@pytest.mark.parametrize("with_accelerometer", [True, False], ids=["accelerometer", "floor_plane"])
def test_run_writes_every_file_in_one_upright_world(tilted_sequence, first_camera_run, tmp_path, with_accelerometer):
    """Up within a degree of the truth's by either method; trajectory.txt, keyframes.txt, splats.ply and mesh.ply are
    the first-camera files rotated by metrics.json's transform; ATE and RPE do not change."""
    source, truth = tilted_sequence
    first_dir, first = first_camera_run
    folder = tmp_path / "room"
    folder.mkdir()
    for item in source.iterdir():
        (folder / item.name).symlink_to(item)
    if with_accelerometer:
        write_accelerometer(folder / "accelerometer.txt", kinect_samples(truth))
    upright = reconstruct(folder, tmp_path / "upright", load_config(None, FAST), progress=False)
    metrics = read_metrics(tmp_path / "upright" / "metrics.json")
    assert metrics.world.frame == "upright"
    # With the accelerometer the room's floor, which lies near its up, levels the world.
    assert metrics.world.up_source == ("accelerometer_floor" if with_accelerometer else "floor_plane")
    transform = np.array(metrics.world.upright_from_first_camera)
    up_first_camera = transform[2, :3]
    # The run's first pose is close to (not exactly) the identity: compare in the truth's first camera.
    assert angle_deg(up_first_camera, true_up_in_first_camera(truth)) < 1.0
    first_metrics = read_metrics(first_dir / "metrics.json")
    assert first_metrics.world.up_source == "first_camera"
    np.testing.assert_array_equal(first_metrics.world.upright_from_first_camera, np.eye(4))

    for name in ("trajectory.txt", "keyframes.txt"):
        np.testing.assert_allclose(read_tum_trajectory(tmp_path / "upright" / name).world_from_camera,
                                   transform @ read_tum_trajectory(first_dir / name).world_from_camera,
                                   atol=1e-6)
    np.testing.assert_allclose(upright.trajectory.world_from_camera, transform @ first.trajectory.world_from_camera,
                               atol=1e-12)
    splats_upright, splats_first = (load_ply(run / "splats.ply") for run in (tmp_path / "upright", first_dir))
    np.testing.assert_allclose(splats_upright.means_m.numpy(), splats_first.means_m.numpy() @ transform[:3, :3].T,
                               atol=1e-5)
    np.testing.assert_array_equal(splats_upright.rgb.numpy(), splats_first.rgb.numpy())
    mesh_upright, mesh_first = (read_mesh(run / "mesh.ply") for run in (tmp_path / "upright", first_dir))
    # Open3D's hashed grid lists the vertices in no fixed order: compare them as point sets.
    assert len(mesh_upright.vertices) == len(mesh_first.vertices) > 1000
    distances, _ = cKDTree(mesh_upright.vertices).query(mesh_first.vertices @ transform[:3, :3].T)
    assert distances.max() < 1e-5
    # The room's floor is level in the upright mesh.
    assert any(abs(plane.normal[2]) > np.cos(np.radians(1.0)) for plane in dominant_planes(mesh_upright.vertices))
    assert metrics.trajectory.ate_rmse_m == pytest.approx(first_metrics.trajectory.ate_rmse_m, abs=1e-9)
    assert metrics.trajectory.rpe_rot_rmse_deg == pytest.approx(first_metrics.trajectory.rpe_rot_rmse_deg, abs=1e-9)


def test_a_bad_accelerometer_file_stops_the_run_before_any_output(tilted_sequence, tmp_path):
    source, _ = tilted_sequence
    folder = tmp_path / "room"
    folder.mkdir()
    for item in source.iterdir():
        (folder / item.name).symlink_to(item)
    (folder / "accelerometer.txt").write_text("0.0 0.1 nine 0.3\n")
    with pytest.raises(SequenceFormatError, match=r"accelerometer.txt line 1: expected 4 numbers"):
        reconstruct(folder, tmp_path / "out", load_config(None, FAST), progress=False)
    assert not (tmp_path / "out").exists()
    # With the files in the first camera's frame the accelerometer is not read.
    reconstruct(folder, tmp_path / "first", load_config(None, (*FAST, "export.world=first_camera", "mapper.enabled=false",
                                                                "mesh.enabled=false")), progress=False)
    assert read_metrics(tmp_path / "first" / "metrics.json").world.up_source == "first_camera"


def test_planes_do_not_depend_on_the_order_of_the_points():
    rng = np.random.default_rng(1)
    floor = np.column_stack([rng.uniform(-2, 2, (3000, 2)), rng.normal(0, 0.003, 3000)])
    wall = np.column_stack([rng.uniform(-2, 2, 2000), np.full(2000, 1.5), rng.uniform(0, 2.5, 2000)])
    points = np.concatenate([floor, wall, rng.uniform(-2, 2, (500, 3))])
    planes = dominant_planes(points)
    shuffled = dominant_planes(points[rng.permutation(len(points))])
    assert len(planes) == len(shuffled) >= 2
    for plane, other in zip(planes, shuffled):
        np.testing.assert_array_equal(plane.normal, other.normal)
    assert abs(planes[0].normal[2]) > np.cos(np.radians(0.5)) and abs(planes[1].normal[1]) > np.cos(np.radians(0.5))


def test_sparse_points_and_mesh_turn_with_the_poses():
    import trimesh

    from tambridge.frontend.contract import FrontendResult

    world = WorldFrame(ExportWorld.upright, UpSource.accelerometer, upright_from_up(np.array([0.3, -0.9, 0.2])))
    trajectory = Trajectory([0.0], exp_se3(np.array([0.2, 0.1, -0.3, 0.1, 0.2, 0.3]))[None])
    points = np.array([[0.1, 0.2, 1.5], [-0.4, 0.3, 2.0]])
    result = FrontendResult(trajectory, np.array([True]), trajectory, {0: trajectory.world_from_camera[0]}, {0: 0},
                            points, np.zeros((2, 3), np.uint8), np.arange(2), {}, 0, 0, 0)
    turned = world.frontend_result(result)
    # A point keeps its place in its camera: camera_from_world times point is the same in both worlds.
    in_camera = transform_points(inverse(trajectory.world_from_camera[0]), points)
    upright_pose = world.trajectory(trajectory).world_from_camera[0]
    np.testing.assert_allclose(transform_points(inverse(upright_pose), turned.map_points_world_m), in_camera, atol=1e-12)
    np.testing.assert_array_equal(result.map_points_world_m, points)  # the run's own result is left as it was
    mesh = trimesh.Trimesh(vertices=points.tolist() + [[0.0, 0.0, 1.0]], faces=[[0, 1, 2]], process=False)
    np.testing.assert_allclose(world.mesh(mesh).vertices, transform_points(world.upright_from_first_camera, mesh.vertices))
    np.testing.assert_array_equal(world.mesh(mesh).faces, mesh.faces)
