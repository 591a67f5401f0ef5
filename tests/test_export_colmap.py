"""``tambridge export``: a synthetic run exported as a COLMAP model and as nerfstudio data, read back and checked
against the run's own files; conventions checked on a hand-made scene point; bad input refused whole."""

import json
import os
import shutil
from pathlib import Path
from types import SimpleNamespace

import cv2
import numpy as np
import pycolmap
import pytest
import yaml
from click.testing import CliRunner

from cli import main
import pipelines.export as export_module
from pipelines.export import export_run
from pipelines.reconstruct import reconstruct
from tambridge.camera import Camera
from tambridge.checkpoint import sequence_fingerprint
from tambridge.config import load_config
from tambridge.errors import ExportError
from tambridge.evaluation.metrics import read_metrics
from tambridge.export.colmap_model import COLMAP_PIXEL_OFFSET, ModelImage, build_model
from tambridge.export.images import DEPTH_PER_METRE, ImageMode, pixels_in_images, undistorted_window
from tambridge.export.mesh import read_mesh
from tambridge.export.sparse_map import SEEN_DEPTH_TOLERANCE, points_seen, read_sparse_map
from tambridge.geometry import inverse, transform_points
from tambridge.io.synthetic import SynthOptions, write_synthetic_sequence
from tambridge.io.tum import open_sequence
from tambridge.trajectory import read_tum_trajectory

FRAMES = 20
RUN_OPTIONS = ["mapper.enabled=false", "frontend.orb.mapping_thread=false"]
# A wide-angle barrel lens (OpenCV's k1 k2 p1 p2 k3, k3 set as on TUM fr1, whose own lens bends an edge of the
# 160x120 images by a third of a pixel only: too little to tell undistortion from interpolation).
LENS = (-0.30, 0.09, 0.001, -0.001, -0.01)


@pytest.fixture(scope="module")
def sequence_dir(tmp_path_factory):
    folder = tmp_path_factory.mktemp("export") / "room"
    write_synthetic_sequence(folder, SynthOptions(frame_count=FRAMES, width=160, height=120))
    return folder


@pytest.fixture(scope="module")
def run_dir(sequence_dir, tmp_path_factory):
    """An ORB run (mapper off, mesh on) of the 20-frame sequence."""
    folder = tmp_path_factory.mktemp("export_run") / "run"
    reconstruct(sequence_dir, folder, load_config(None, RUN_OPTIONS), progress=False)
    return folder


def _colmap_model(run_dir, output, **options):
    export_run(run_dir, output, "colmap", **options)
    return pycolmap.Reconstruction(str(output / "sparse" / "0"))


def _camera_from_world(image) -> np.ndarray:
    matrix = np.eye(4)
    matrix[:3] = image.cam_from_world().matrix()
    return matrix


def _reprojection_errors_px(model) -> np.ndarray:
    errors = [np.linalg.norm(model.images[element.image_id].project_point(point.xyz)
                             - model.images[element.image_id].points2D[element.point2D_idx].xy)
              for point in model.points3D.values() for element in point.track.elements]
    return np.array(errors)


def test_run_writes_its_sparse_map_with_observations(run_dir):
    sparse_map = read_sparse_map(run_dir / "sparse_map.npz")
    observations = sparse_map.observations
    sequence_folder = Path(read_metrics(run_dir / "metrics.json").sequence)
    assert sequence_folder.is_absolute() and sequence_folder.is_dir()
    assert len(sparse_map.points_world_m) > 100 and len(observations) > 2 * len(sparse_map.points_world_m)
    assert set(np.unique(observations.keyframe_ids)) <= set(sparse_map.keyframe_frame_indices)
    assert np.array_equal(np.unique(observations.point_rows), np.arange(len(sparse_map.points_world_m)))
    # A keyframe sees a point at most once.
    pairs = observations.keyframe_ids * len(sparse_map.points_world_m) + observations.point_rows
    assert len(np.unique(pairs)) == len(pairs)


def test_colmap_model_reads_back_with_the_run_poses_intrinsics_and_tracks(run_dir, sequence_dir, tmp_path):
    model = _colmap_model(run_dir, tmp_path / "colmap", frames="keyframes", images="copy", text=True)
    trajectory = read_tum_trajectory(run_dir / "trajectory.txt")
    sparse_map = read_sparse_map(run_dir / "sparse_map.npz")
    sequence = open_sequence(sequence_dir)
    camera = sequence.camera

    (colmap_camera,) = model.cameras.values()
    assert colmap_camera.model == pycolmap.CameraModelId.PINHOLE
    assert (colmap_camera.width, colmap_camera.height) == (160, 120)
    assert np.allclose(colmap_camera.params, [camera.fx, camera.fy, camera.cx + 0.5, camera.cy + 0.5], atol=1e-12)

    keyframe_frames = sorted(set(sparse_map.keyframe_frame_indices.values()))
    assert sorted(int(image.name[:6]) for image in model.images.values()) == keyframe_frames
    pose_errors = [np.abs(_camera_from_world(image) - inverse(trajectory.world_from_camera[int(image.name[:6])])).max()
                   for image in model.images.values()]
    assert max(pose_errors) < 1e-9
    for image in model.images.values():
        assert (tmp_path / "colmap" / "images" / image.name).read_bytes() == \
            sequence.rgb_paths[int(image.name[:6])].read_bytes()

    # Every map point, with its colour; each track element is the run's keypoint of that point in that keyframe.
    assert model.num_points3D() == len(sparse_map.points_world_m)
    keyframe_of_frame = {frame: keyframe for keyframe, frame in sparse_map.keyframe_frame_indices.items()}
    observed = {(int(k), int(r)): xy for k, r, xy in zip(sparse_map.observations.keyframe_ids,
                                                         sparse_map.observations.point_rows,
                                                         sparse_map.observations.keypoints_px)}
    positions = {tuple(p) for p in np.round(sparse_map.points_world_m, 9)}
    frame_rgb = {}
    checked, coloured_as_seen = 0, 0
    for point in model.points3D.values():
        assert tuple(np.round(point.xyz, 9)) in positions
        assert point.track.length() == 0 or point.track.length() >= 2
        row = int(np.flatnonzero((sparse_map.points_world_m == point.xyz).all(axis=1))[0])
        np.testing.assert_array_equal(point.color, sparse_map.point_colours[row])
        seen_colours = []
        for element in point.track.elements:
            image = model.images[element.image_id]
            frame = int(image.name[:6])
            keypoint = observed[(keyframe_of_frame[frame], row)]
            assert np.allclose(image.points2D[element.point2D_idx].xy, keypoint + COLMAP_PIXEL_OFFSET, atol=1e-12)
            if frame not in frame_rgb:
                frame_rgb[frame] = sequence[frame].rgb
            column, image_row = np.round(keypoint).astype(int)
            seen_colours.append(frame_rgb[frame][image_row, column])
            checked += 1
        # A point takes its colour from the keyframe that made it, at its keypoint there.
        coloured_as_seen += any(np.array_equal(point.color, colour) for colour in seen_colours)
    assert checked == model.compute_num_observations() > 2 * model.num_points3D()
    assert coloured_as_seen >= 0.9 * sum(point.track.length() > 0 for point in model.points3D.values())
    errors = _reprojection_errors_px(model)
    assert np.median(errors) < 2.0, np.median(errors)
    for name in ("cameras", "images", "points3D"):
        assert (tmp_path / "colmap" / "sparse" / "0" / f"{name}.txt").is_file()


def _umeyama(source: np.ndarray, target: np.ndarray) -> np.ndarray:
    """``target ~ s R source + t`` (least squares); returns the aligned ``source`` (N, 3)."""
    source_mean, target_mean = source.mean(0), target.mean(0)
    u, s, vt = np.linalg.svd((target - target_mean).T @ (source - source_mean) / len(source))
    d = np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt))])
    rotation = u @ d @ vt
    scale = np.trace(np.diag(s) @ d) / ((source - source_mean) ** 2).sum(1).mean()
    return scale * (source - source_mean) @ rotation.T + target_mean


def _bundle_adjust(model) -> None:
    options = pycolmap.BundleAdjustmentOptions()
    options.refine_focal_length = options.refine_principal_point = options.refine_extra_params = False
    options.print_summary = False
    pycolmap.bundle_adjustment(model, options)


def test_bundle_adjustment_runs_on_the_exported_model(run_dir, tmp_path):
    model = _colmap_model(run_dir, tmp_path / "colmap", frames="keyframes", images="link")
    ids = sorted(model.reg_image_ids())
    before = np.array([model.images[i].projection_center() for i in ids])
    error_before = np.mean(_reprojection_errors_px(model))
    _bundle_adjust(model)
    after = np.array([model.images[i].projection_center() for i in ids])
    assert np.mean(_reprojection_errors_px(model)) < error_before
    # Reprojection alone leaves scale free and, on 160x120 images with 3-image tracks, depth weakly held: compare
    # up to a similarity. Measured: a few cm (the run's RGB-D BA is better held than COLMAP's monocular one).
    moved_m = np.linalg.norm(_umeyama(after, before) - before, axis=1)
    assert moved_m.max() < 0.15, moved_m.max()


def test_bundle_adjustment_keeps_an_exact_model_where_it_is(sequence_dir):
    """A model of the ground-truth poses with exact projections: any convention slip in the export would make
    bundle adjustment move the cameras."""
    sequence = open_sequence(sequence_dir)
    camera = sequence.camera
    rng = np.random.default_rng(0)
    poses = sequence.ground_truth.world_from_camera[:6]
    # Points 2-4 m in front of the first camera, seen by every camera that has them in view.
    points_world = transform_points(poses[0], camera.backproject(
        rng.uniform([0, 0], [camera.width - 1, camera.height - 1], (200, 2)), rng.uniform(2.0, 4.0, 200)))
    images = []
    for index, pose in enumerate(poses):
        points_camera = transform_points(inverse(pose), points_world)
        pixels = camera.project(points_camera)
        seen = np.flatnonzero((points_camera[:, 2] > 0.1) & camera.in_image(pixels))
        images.append(ModelImage(f"{index:06d}.png", pose, seen, pixels[seen]))
    model = build_model(camera, images, points_world, np.zeros((200, 3), np.uint8))
    assert np.max(_reprojection_errors_px(model)) < 1e-9
    before = np.array([image.projection_center() for image in model.images.values()])
    _bundle_adjust(model)
    after = np.array([image.projection_center() for image in model.images.values()])
    assert np.abs(after - before).max() < 1e-6


def _scene_point(trajectory, in_first_camera_m=(0.1, -0.05, 2.5)) -> np.ndarray:
    """A point given in the first camera's frame (the run's world), by default 2.5 m ahead: every camera of the loop
    sees it."""
    return transform_points(trajectory.world_from_camera[0], np.array([in_first_camera_m]))[0]


def _nerfstudio_pixel(contents: dict, transform: np.ndarray, point_world: np.ndarray) -> np.ndarray:
    """nerfstudio's projection, written from its conventions: OpenGL camera (looks down -z, y up), pixel centres
    at +0.5, pinhole (no distortion)."""
    x, y, z = transform_points(np.linalg.inv(transform), point_world[None])[0]
    return np.array([contents["fl_x"] * x / -z + contents["cx"], contents["fl_y"] * -y / -z + contents["cy"]]) - 0.5


def test_a_scene_point_lands_on_the_same_pixel_through_our_camera_colmap_and_transforms_json(run_dir, sequence_dir,
                                                                                             tmp_path):
    model = _colmap_model(run_dir, tmp_path / "colmap", frames="every:7", images="undistort")
    export_run(run_dir, tmp_path / "nerfstudio", "nerfstudio", frames="every:7", images="undistort")
    contents = json.loads((tmp_path / "nerfstudio" / "transforms.json").read_text())
    trajectory = read_tum_trajectory(run_dir / "trajectory.txt")
    camera = open_sequence(sequence_dir).camera
    point_world = _scene_point(trajectory)
    frames = {frame["file_path"]: np.array(frame["transform_matrix"]) for frame in contents["frames"]}
    assert len(frames) == len(model.images) == 3
    for image in model.images.values():
        index = int(image.name[:6])
        ours = camera.project(transform_points(inverse(trajectory.world_from_camera[index]), point_world[None]))[0]
        assert camera.in_image(ours)
        colmap = image.project_point(point_world) - COLMAP_PIXEL_OFFSET
        nerfstudio = _nerfstudio_pixel(contents, frames[f"images/{image.name}"], point_world)
        assert np.abs(colmap - ours).max() < 1e-9 and np.abs(nerfstudio - ours).max() < 1e-9, (ours, colmap, nerfstudio)


def _distorted_sequence(sequence_dir, folder, lens=LENS):
    """The sequence seen through ``lens`` (by default a wide-angle one): same camera matrix, images warped by its
    distortion, and a camera.yaml that says so (so that the run's undistorted frames are the original images again)."""
    shutil.copytree(sequence_dir, folder)
    values = yaml.safe_load((folder / "camera.yaml").read_text())
    values["distortion"] = list(lens)
    (folder / "camera.yaml").write_text(yaml.safe_dump(values))
    camera = open_sequence(folder).sensor.camera
    map_x, map_y = _distorting_maps(camera)
    for path in list((folder / "rgb").iterdir()) + list((folder / "depth").iterdir()):
        image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        interpolation = cv2.INTER_NEAREST if image.dtype == np.uint16 else cv2.INTER_LINEAR
        cv2.imwrite(str(path), cv2.remap(image, map_x, map_y, interpolation, borderMode=cv2.BORDER_REPLICATE))
    return folder


def _distorting_maps(camera: Camera) -> tuple[np.ndarray, np.ndarray]:
    """Maps for cv2.remap that make a distorted image of a pinhole one: each distorted pixel samples the pinhole
    pixel of its ray."""
    rows, columns = np.mgrid[0:camera.height, 0:camera.width].astype(np.float64)
    pixels = np.stack([columns.ravel(), rows.ravel()], axis=1)
    undistorted = cv2.undistortPoints(pixels.reshape(-1, 1, 2), camera.K, np.array(camera.distortion), P=camera.K)
    undistorted = undistorted.reshape(camera.height, camera.width, 2).astype(np.float32)
    return undistorted[..., 0], undistorted[..., 1]


@pytest.fixture(scope="module")
def distorted_run_dir(run_dir, sequence_dir, tmp_path_factory):
    """The run, pointed at a distorted copy of its sequence (the poses and keypoints stay valid: the run's frames
    are the undistorted images)."""
    root = tmp_path_factory.mktemp("distorted")
    folder = _distorted_sequence(sequence_dir, root / "room_lens")
    moved = root / "run"
    shutil.copytree(run_dir, moved)
    _point_run_at(moved, folder)
    return moved


def _point_run_at(run_dir, sequence_folder) -> None:
    """Make a run's metrics.json name ``sequence_folder`` as the run's sequence (a moved or copied sequence), with
    the fingerprint a run of that folder writes (none where the folder does not exist)."""
    metrics = json.loads((run_dir / "metrics.json").read_text())
    metrics["sequence"] = str(sequence_folder)
    metrics.pop("sequence_fingerprint")
    if Path(sequence_folder).is_dir():
        metrics["sequence_fingerprint"] = sequence_fingerprint(open_sequence(sequence_folder))
    (run_dir / "metrics.json").write_text(json.dumps(metrics, indent=2) + "\n")


def test_distorted_images_export_with_an_opencv_camera_whose_tracks_still_fit(distorted_run_dir, tmp_path):
    model = _colmap_model(distorted_run_dir, tmp_path / "colmap", frames="keyframes", images="copy")
    (camera,) = model.cameras.values()
    # k3 is set: FULL_OPENCV holds OpenCV's 5-coefficient model (OPENCV has no k3).
    assert camera.model == pycolmap.CameraModelId.FULL_OPENCV
    k1, k2, p1, p2, k3 = LENS
    assert np.allclose(camera.params[4:], [k1, k2, p1, p2, k3, 0, 0, 0])
    assert np.median(_reprojection_errors_px(model)) < 2.0
    export_run(distorted_run_dir, tmp_path / "nerfstudio", "nerfstudio", frames="every:10", images="copy")
    contents = json.loads((tmp_path / "nerfstudio" / "transforms.json").read_text())
    assert contents["camera_model"] == "OPENCV"
    assert [contents[key] for key in ("k1", "k2", "p1", "p2", "k3", "k4")] == [k1, k2, p1, p2, k3, 0.0]


def test_distortion_agrees_with_opencv_and_pycolmap_for_a_scene_point(distorted_run_dir, tmp_path):
    model = _colmap_model(distorted_run_dir, tmp_path / "colmap", frames="every:9", images="copy")
    sequence = open_sequence(read_metrics(distorted_run_dir / "metrics.json").sequence)
    sensor_camera = sequence.sensor.camera
    trajectory = read_tum_trajectory(distorted_run_dir / "trajectory.txt")
    point_world = _scene_point(trajectory, (-0.8, -0.55, 2.5))  # towards the top-left corner, where the lens bends most
    for image in model.images.values():
        camera_from_world = inverse(trajectory.world_from_camera[int(image.name[:6])])
        pinhole_pixel = sensor_camera.undistorted().project(transform_points(camera_from_world, point_world[None]))
        ours = pixels_in_images(pinhole_pixel, sequence, ImageMode.copy)[0]
        assert np.abs(image.project_point(point_world) - COLMAP_PIXEL_OFFSET - ours).max() < 1e-6
        assert np.linalg.norm(ours - pinhole_pixel[0]) > 1.0  # the lens does move the point


def _edge_columns(image: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """Sub-pixel column per row where the grey level crosses mid-way from dark (left) to bright (right)."""
    grey = image.astype(np.float64).mean(axis=2) if image.ndim == 3 else image.astype(np.float64)
    columns = []
    for row in rows:
        line = grey[row]
        crossing = int(np.flatnonzero(line >= 127.5)[0])
        columns.append(crossing - 1 + (127.5 - line[crossing - 1]) / (line[crossing] - line[crossing - 1]))
    return np.array(columns)


def _line_residual_px(rows: np.ndarray, columns: np.ndarray) -> float:
    fit = np.polyfit(rows, columns, 1)
    return float(np.abs(np.polyval(fit, rows) - columns).max())


def test_undistort_keeps_a_straight_edge_straight_as_opencv_does(distorted_run_dir, tmp_path):
    run, folder = tmp_path / "run", tmp_path / "room_lens"
    shutil.copytree(distorted_run_dir, run)
    shutil.copytree(read_metrics(distorted_run_dir / "metrics.json").sequence, folder)
    sequence = open_sequence(folder)
    camera = sequence.sensor.camera
    # Frame 0 becomes the lens's image of a straight, slanted edge near the left border (where the lens bends most).
    rows, columns = np.mgrid[0:camera.height, 0:camera.width].astype(np.float64)
    # A soft edge (a 4-pixel ramp), so that the sub-pixel crossing survives resampling.
    pinhole = np.clip((columns - (12.0 + 0.05 * rows)) * 64.0 + 127.5, 0, 255)
    pinhole = np.repeat(pinhole[..., None], 3, axis=2).astype(np.float32)
    distorted = cv2.remap(pinhole, *_distorting_maps(camera), cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    cv2.imwrite(str(sequence.rgb_paths[0]), np.round(distorted).astype(np.uint8))
    _point_run_at(run, folder)  # as a run of the folder with this frame records it

    model = _colmap_model(run, tmp_path / "colmap", frames="every:100", images="undistort")
    (colmap_camera,) = model.cameras.values()
    assert colmap_camera.model == pycolmap.CameraModelId.PINHOLE
    exported = cv2.imread(str(tmp_path / "colmap" / "images" / "000000.png"))
    raw = cv2.imread(str(sequence.rgb_paths[0]))
    opencv = cv2.undistort(raw, camera.K, np.array(camera.distortion))
    rows_checked = np.arange(5, camera.height - 5)
    assert _line_residual_px(rows_checked, _edge_columns(raw, rows_checked)) > 1.0  # the lens bends it
    assert _line_residual_px(rows_checked, _edge_columns(exported, rows_checked)) < 0.1
    assert np.abs(_edge_columns(exported, rows_checked) - _edge_columns(opencv, rows_checked)).max() < 0.05
    assert np.abs(_edge_columns(exported, rows_checked) - (12.0 + 0.05 * rows_checked)).max() < 0.1


@pytest.mark.parametrize("cx, cy, region", [(79.5, 59.5, (0, 120, 0, 160)), (82.3, 71.8, (4, 117, 9, 151)),
                                             (20.0, 100.6, (3, 120, 0, 160)), (148.3, 59.5, (0, 120, 0, 151)),
                                             (100.5, 59.5, (0, 120, 0, 160))])
def test_undistorted_window_is_the_longest_span_centred_on_the_principal_point(cx, cy, region):
    sequence = SimpleNamespace(valid_region=region, camera=Camera(160, 120, 100.0, 100.0, cx, cy), folder=Path("seq"))
    top, bottom, left, right = undistorted_window(sequence)
    for (first, last), centre, (start, stop) in (((top, bottom), cy, region[:2]), ((left, right), cx, region[2:])):
        assert start <= first < last <= stop and abs((first + last - 1) / 2 - centre) <= 0.5
        # Its slow twin: every span of the region.
        longest = max(b - a for a in range(start, stop) for b in range(a + 1, stop + 1) if abs((a + b - 1) / 2 - centre) <= 0.5)
        assert last - first == longest


def test_a_principal_point_outside_the_pixels_with_data_is_refused_for_undistort():
    sequence = SimpleNamespace(valid_region=(0, 120, 10, 160), camera=Camera(160, 120, 100.0, 100.0, 5.0, 59.5),
                               folder=Path("seq"))
    with pytest.raises(ExportError, match=r"^seq: the principal point \(5\.0, 59\.5\) lies outside the pixels the frames "
                                          r"have data for \(rows 0-120, columns 10-160\); check cx and cy in the camera file$"):
        undistorted_window(sequence)


# TUM fr1's lens (pincushion): undistorted frames keep a border that no raw pixel reaches.
PINCUSHION = (0.2624, -0.9531, -0.0054, 0.0026, 1.1633)


def test_undistorted_images_hold_only_pixels_with_data_and_centre_the_principal_point(run_dir, sequence_dir, tmp_path):
    folder = _distorted_sequence(sequence_dir, tmp_path / "room_fr1_lens", PINCUSHION)
    run = tmp_path / "run"
    shutil.copytree(run_dir, run)
    _point_run_at(run, folder)
    sequence = open_sequence(folder)
    top, bottom, left, right = undistorted_window(sequence)
    model = _colmap_model(run, tmp_path / "colmap", frames="every:6", images="undistort")
    (colmap_camera,) = model.cameras.values()
    width, height = right - left, bottom - top
    assert (colmap_camera.width, colmap_camera.height) == (width, height) and width * height < 0.97 * 160 * 120
    # Trainers that ignore COLMAP's principal point (INRIA's) take the image's centre: it is within half a pixel.
    fx, fy, cx, cy = colmap_camera.params
    assert abs(cx - width / 2) <= 0.5 and abs(cy - height / 2) <= 0.5 and (fx, fy) == (sequence.camera.fx, sequence.camera.fy)
    trajectory = read_tum_trajectory(run / "trajectory.txt")
    point_world = _scene_point(trajectory)
    for image in model.images.values():
        index = int(image.name[:6])
        frame = sequence[index]
        # The run's frame has pixels without data (black) outside the window; the image is the window, to the bit.
        assert (frame.rgb.max(axis=2) == 0).sum() > 50
        exported = cv2.cvtColor(cv2.imread(str(tmp_path / "colmap" / "images" / image.name)), cv2.COLOR_BGR2RGB)
        assert np.array_equal(exported, frame.rgb[top:bottom, left:right]) and (exported.max(axis=2) > 0).all()
        ours = sequence.camera.project(transform_points(inverse(trajectory.world_from_camera[index]), point_world[None]))[0]
        assert np.abs(image.project_point(point_world) - COLMAP_PIXEL_OFFSET - (ours - [left, top])).max() < 1e-9
    assert np.median(_reprojection_errors_px(model)) < 2.0


def test_points_seen_are_those_in_view_whose_depth_the_frame_measures():
    camera = Camera(160, 120, 100.0, 100.0, 79.5, 59.5)
    world_from_camera = np.eye(4)
    world_from_camera[:3, 3] = [0.5, -0.2, 1.0]
    in_camera_m = np.array([[0.1, 0.05, 2.0],    # seen: depth measured 2.05 m (2.5 % off)
                            [-0.3, 0.2, 1.5],    # hidden: something measured at 1.2 m in front of it
                            [0.0, 0.0, 2.5],     # no depth measured there
                            [2.0, 0.0, 1.0],     # outside the image (u = 279.5)
                            [0.0, 0.0, -1.0],    # behind the camera
                            [-0.5, -0.4, 3.0]])  # seen: depth measured 2.9 m (3.3 % off)
    pixels = camera.project(in_camera_m, np.abs(in_camera_m[:, 2]))
    depth_m = np.zeros((120, 160), np.float32)
    for (u, v), measured in zip(np.round(pixels[[0, 1, 5]]).astype(int), (2.05, 1.2, 2.9)):
        depth_m[v, u] = measured
    rows, seen_px = points_seen(transform_points(world_from_camera, in_camera_m), world_from_camera, camera, depth_m)
    assert rows.tolist() == [0, 5]
    assert np.abs(seen_px - pixels[[0, 5]]).max() < 1e-9
    depth_m[tuple(np.round(pixels[0, ::-1]).astype(int))] = 2.0 / (1 - 1.01 * SEEN_DEPTH_TOLERANCE)
    assert points_seen(transform_points(world_from_camera, in_camera_m), world_from_camera, camera, depth_m)[0].tolist() == [5]


def test_every_exported_frame_sees_map_points_and_frames_that_are_no_keyframes_see_them_where_they_project(run_dir, tmp_path):
    model = _colmap_model(run_dir, tmp_path / "colmap", frames="all", images="undistort")
    keyframes = set(read_sparse_map(run_dir / "sparse_map.npz").keyframe_frame_indices.values())
    assert model.num_images() == FRAMES and len(keyframes) < FRAMES
    for image in model.images.values():
        observed = [point for point in image.points2D if point.has_point3D()]
        # gsplat's depth loss looks every image up among the tracks.
        assert len(observed) >= 20, image.name
        if int(image.name[:6]) not in keyframes:
            errors = [np.linalg.norm(image.project_point(model.points3D[point.point3D_id].xyz) - point.xy) for point in observed]
            assert max(errors) < 1e-6
    assert np.median(_reprojection_errors_px(model)) < 2.0


def test_nerfstudio_export_names_images_depth_and_points(run_dir, sequence_dir, tmp_path):
    output = tmp_path / "nerfstudio"
    export_run(run_dir, output, "nerfstudio", frames="every:5", images="copy")
    contents = json.loads((output / "transforms.json").read_text())
    camera = open_sequence(sequence_dir).camera
    trajectory = read_tum_trajectory(run_dir / "trajectory.txt")
    assert contents["camera_model"] == "PINHOLE"
    # The world is upright already: nerfstudio must not turn it to the cameras' mean up.
    assert contents["orientation_override"] == "none"
    assert (contents["w"], contents["h"], contents["fl_x"], contents["fl_y"]) == (160, 120, camera.fx, camera.fy)
    assert (contents["cx"], contents["cy"]) == (camera.cx + 0.5, camera.cy + 0.5)
    assert all(contents[key] == 0.0 for key in ("k1", "k2", "p1", "p2"))
    assert [frame["file_path"] for frame in contents["frames"]] == [f"images/{i:06d}.png" for i in (0, 5, 10, 15)]
    sequence = open_sequence(sequence_dir)
    for frame, index in zip(contents["frames"], (0, 5, 10, 15)):
        expected = trajectory.world_from_camera[index] @ np.diag([1.0, -1.0, -1.0, 1.0])
        assert np.abs(np.array(frame["transform_matrix"]) - expected).max() < 1e-12
        assert (output / frame["file_path"]).is_file()
        depth = cv2.imread(str(output / frame["depth_file_path"]), cv2.IMREAD_UNCHANGED)
        assert depth.dtype == np.uint16
        assert np.abs(depth / DEPTH_PER_METRE - sequence[index].depth_m).max() <= 0.5 / DEPTH_PER_METRE + 1e-6
    ply = (output / contents["ply_file_path"]).read_bytes()
    assert f"element vertex {len(read_sparse_map(run_dir / 'sparse_map.npz').points_world_m)}".encode() in ply


def test_open3d_run_exports_the_mesh_vertices_as_points(sequence_dir, tmp_path):
    run = tmp_path / "run"
    reconstruct(sequence_dir, run, load_config(None, ["mapper.enabled=false", "frontend.kind=open3d_f2f",
                                                      "input.max_frames=8"]), progress=False)
    result = export_run(run, tmp_path / "colmap", "colmap", frames="all")
    assert "mesh.ply" in result.points_source and "no sparse map" in result.points_source
    model = pycolmap.Reconstruction(str(tmp_path / "colmap" / "sparse" / "0"))
    mesh = read_mesh(run / "mesh.ply")
    assert model.num_points3D() == len(mesh.vertices) > 100 and model.num_images() == 8
    assert model.compute_num_observations() == 0 and result.observations is None


def test_cli_export_prints_what_it_wrote(run_dir, tmp_path):
    result = CliRunner().invoke(main, ["export", str(run_dir), "--format", "colmap", "-o", str(tmp_path / "out"),
                                       "--frames", "every:4", "--text"])
    assert result.exit_code == 0, result.output
    assert "wrote 5 images" in result.output and "ORB frontend's map points" in result.output
    assert (tmp_path / "out" / "sparse" / "0" / "points3D.txt").is_file()
    # One image (frame 0): no point has a track, and the summary says why.
    single = CliRunner().invoke(main, ["export", str(run_dir), "--format", "colmap", "-o", str(tmp_path / "single"),
                                       "--frames", "every:1000"])
    assert single.exit_code == 0, single.output
    assert single.output.startswith("wrote 1 images and ") and \
        " (none with a track: a track needs a point seen in two images) to " in single.output


def _refused(arguments, tmp_path) -> str:
    result = CliRunner().invoke(main, ["export", *map(str, arguments)])
    assert result.exit_code == 2, result.output
    lines = result.output.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: "), result.output
    # Nothing half-written: no staging folder is left beside the target.
    assert not list(tmp_path.glob(".*partial"))
    return lines[0]


def test_bad_input_is_refused_in_one_line_leaving_nothing(run_dir, sequence_dir, tmp_path):
    no_trajectory = tmp_path / "no_trajectory"
    shutil.copytree(run_dir, no_trajectory)
    (no_trajectory / "trajectory.txt").unlink()
    line = _refused([no_trajectory, "--format", "colmap", "-o", tmp_path / "a"], tmp_path)
    assert "trajectory.txt" in line and not (tmp_path / "a").exists()

    moved = tmp_path / "moved"
    shutil.copytree(run_dir, moved)
    _point_run_at(moved, tmp_path / "gone" / "room")
    line = _refused([moved, "--format", "nerfstudio", "-o", tmp_path / "b"], tmp_path)
    assert "gone" in line and "sequence folder" in line and not (tmp_path / "b").exists()

    taken = tmp_path / "taken"
    taken.mkdir()
    (taken / "keep.txt").write_text("mine")
    line = _refused([run_dir, "--format", "colmap", "-o", taken], tmp_path)
    assert "not empty" in line and [p.name for p in taken.iterdir()] == ["keep.txt"]
    line = _refused([run_dir, "--format", "colmap", "-o", taken / "keep.txt"], tmp_path)
    assert line == f"error: -o {taken / 'keep.txt'}: is a file; give a folder"
    line = _refused([run_dir, "--format", "colmap", "-o", ""], tmp_path)
    assert line.startswith("error: Invalid value for '-o' / '--output': is empty (an unset shell variable?)")

    no_config = tmp_path / "no_config"
    shutil.copytree(run_dir, no_config)
    (no_config / "config.yaml").unlink()
    line = _refused([no_config, "--format", "colmap", "-o", tmp_path / "d"], tmp_path)
    assert line == f"error: {no_config / 'config.yaml'}: not found; the run folder is incomplete (it says how the " \
                   "sequence was read): run reconstruct again" and not (tmp_path / "d").exists()

    line = _refused([run_dir, "--format", "colmap", "-o", tmp_path / "c", "--frames", "every:x"], tmp_path)
    assert "--frames" in line and not (tmp_path / "c").exists()


def _copied_run_and_an_image(run_dir, sequence_dir, tmp_path):
    """A copy of the run pointing at a copy of its sequence, and the path of one of that copy's colour images."""
    sequence_copy = tmp_path / "room"
    shutil.copytree(sequence_dir, sequence_copy)
    run = tmp_path / "run"
    shutil.copytree(run_dir, run)
    _point_run_at(run, sequence_copy)
    return run, open_sequence(sequence_copy).rgb_paths[12]


def test_a_missing_image_is_refused_before_the_export_writes_anything(run_dir, sequence_dir, tmp_path):
    """The sequence is re-opened, and each listed image checked, before any output folder appears."""
    run, victim = _copied_run_and_an_image(run_dir, sequence_dir, tmp_path)
    victim.unlink()
    line = _refused([run, "--format", "colmap", "-o", tmp_path / "out", "--frames", "all"], tmp_path)
    assert victim.name in line and "rgb.txt" in line
    assert not (tmp_path / "out").exists() and not list(tmp_path.glob(".*partial"))


def test_an_image_changed_since_the_run_is_refused_before_the_export_writes_anything(run_dir, sequence_dir, tmp_path):
    """Same names, same frame count and stamps, other pixels: the run's poses would be paired with images it never
    read. metrics.json's fingerprint hashes the first, middle and last frames and stats every other."""
    run, _ = _copied_run_and_an_image(run_dir, sequence_dir, tmp_path)
    assert len(export_module.read_run(run).trajectory) == FRAMES
    # The fingerprint of a run made before the sizes had their own digest: the same frames, read as such.
    written = (run / "metrics.json").read_text()
    older = json.loads(written)
    del older["sequence_fingerprint"]["images_size_sha1"]
    (run / "metrics.json").write_text(json.dumps(older))
    assert len(export_module.read_run(run).trajectory) == FRAMES
    (run / "metrics.json").write_text(written)
    # New modification times (a copy without -p) and a mended groundtruth.txt, which the export never reads: the
    # same frames.
    for image in (tmp_path / "room").rglob("*.png"):
        os.utime(image, (1e9, 1e9))
    with open(tmp_path / "room" / "groundtruth.txt", "a") as ground_truth:
        ground_truth.write("# mended\n")
    assert len(export_module.read_run(run).trajectory) == FRAMES
    for index, name in ((FRAMES // 2, "rgb"), (3, "depth")):
        image = getattr(open_sequence(tmp_path / "room"), f"{name}_paths")[index]
        saved = image.read_bytes()
        pixels = cv2.imread(str(image), cv2.IMREAD_UNCHANGED)
        assert cv2.imwrite(str(image), pixels[::-1])  # upside down: the same size, other pixels
        line = _refused([run, "--format", "colmap", "-o", tmp_path / "out"], tmp_path)
        assert line.startswith(f"error: {tmp_path / 'room'}: not the frames the run read (")
        assert line.endswith("run reconstruct again on the folder as it is now") and not (tmp_path / "out").exists()
        assert (image.name in line) == (index == FRAMES // 2), line  # hashed by name; the others by their stats
        image.write_bytes(saved)


def test_an_export_that_fails_midway_leaves_nothing(run_dir, sequence_dir, tmp_path, monkeypatch):
    """A colour image that vanishes after the sequence was checked stops the export while it copies images: no
    folder appears, not even a partial one."""
    run, victim = _copied_run_and_an_image(run_dir, sequence_dir, tmp_path)
    checked_run = export_module.read_run

    def read_run_then_lose_an_image(folder):
        record = checked_run(folder)
        victim.unlink()
        return record

    monkeypatch.setattr(export_module, "read_run", read_run_then_lose_an_image)
    with pytest.raises(ExportError, match=victim.name):
        export_run(run, tmp_path / "out", "colmap", frames="all")
    assert not (tmp_path / "out").exists() and not list(tmp_path.glob(".*partial"))
