import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from tambridge.errors import ConfigError
from tambridge.geometry import inverse, transform_points
from tambridge.images import sharpness
from tambridge.io.synthetic import (
    BURST_RAMP_S,
    MAX_BLUR_SUBFRAMES,
    RotationBursts,
    SynthOptions,
    blur_subframe_count,
    default_camera,
    loop_path,
    make_room_scene,
    render,
    render_exposure,
    subframe_positions,
    write_synthetic_sequence,
)
from tambridge.io.tum import GT_RGB_FOLDER, open_sequence
from tambridge.trajectory import read_tum_trajectory


def _back_project(depth_m, camera):
    rows, columns = np.nonzero(depth_m > 0)
    z = depth_m[rows, columns].astype(np.float64)
    points = np.stack([(columns - camera.cx) / camera.fx * z, (rows - camera.cy) / camera.fy * z, z], axis=1)
    return points, np.stack([columns, rows], axis=1).astype(np.float64)


def _project(points, camera):
    return np.stack([points[:, 0] / points[:, 2] * camera.fx + camera.cx, points[:, 1] / points[:, 2] * camera.fy + camera.cy], axis=1)


def test_depth_reprojects_onto_the_neighbour_within_a_pixel(synthetic_sequence_dir):
    """Pixels of frame i go to frame i+1 with ground-truth poses, back through i+1's depth, and land within 1 px."""
    sequence = open_sequence(synthetic_sequence_dir)
    camera = sequence.camera
    for index in (0, 10, 20):
        frame_a, frame_b = sequence[index], sequence[index + 1]
        pose_a, pose_b = sequence.ground_truth.nearest([frame_a.timestamp_s, frame_b.timestamp_s]).world_from_camera
        points_a, pixels_a = _back_project(frame_a.depth_m, camera)
        points_b = transform_points(inverse(pose_b) @ pose_a, points_a)
        pixels_b = _project(points_b, camera)
        columns, rows = np.round(pixels_b).astype(int).T
        inside = (columns >= 0) & (columns < camera.width) & (rows >= 0) & (rows < camera.height)
        depth_b = np.zeros(len(points_b))
        depth_b[inside] = frame_b.depth_m[rows[inside], columns[inside]]
        # Visible in b: the depth b sees there agrees with the transformed point (not occluded, not off an edge).
        visible = inside & (np.abs(depth_b - points_b[:, 2]) < 0.02 * points_b[:, 2])
        assert visible.mean() > 0.6
        # Depth stored at 1/5000 m and rounding to the pixel grid cost well under a pixel; a pose error would not.
        depth_at = frame_b.depth_m[rows[visible], columns[visible]].astype(np.float64)
        points_b_measured = np.stack(
            [(columns[visible] - camera.cx) / camera.fx * depth_at, (rows[visible] - camera.cy) / camera.fy * depth_at, depth_at], axis=1
        )
        pixels_back = _project(transform_points(inverse(pose_a) @ pose_b, points_b_measured), camera)
        error_px = np.linalg.norm(pixels_back - pixels_a[visible], axis=1)
        assert np.median(error_px) < 0.5
        assert np.percentile(error_px, 95) < 1.0


def test_ground_truth_is_a_closed_loop_and_colour_is_textured(synthetic_sequence_dir):
    sequence = open_sequence(synthetic_sequence_dir)
    positions = sequence.ground_truth.positions_m
    steps = np.linalg.norm(np.diff(positions, axis=0), axis=1)
    # The end is one step from the start: a loop closure can find it.
    assert np.linalg.norm(positions[-1] - positions[0]) < 2 * steps.max()
    assert len(sequence) == 30 and sequence.camera.width == 160
    frame = sequence[0]
    # Every ray hits the room (no holes); the camera looks across the 6 m room, most of the view on its far side.
    assert (frame.depth_m > 1.0).all() and frame.depth_m.max() < 4.0 and 3.0 < np.median(frame.depth_m) < 3.5
    assert frame.rgb.std() > 20


def test_supersampled_render_keeps_the_centre_depth_and_removes_aliasing():
    scene, camera = make_room_scene(0), default_camera(80, 60)
    pose = loop_path(8)[3]
    colour_1, depth_1 = render(scene, camera, pose)
    colour_3, depth_3 = render(scene, camera, pose, supersampling=3)
    colour_7, _ = render(scene, camera, pose, supersampling=7)
    # The centre ray of each 3 x 3 block is the pixel-centre ray: depth is unchanged to float rounding.
    np.testing.assert_allclose(depth_3, depth_1, atol=1e-5)
    # Against a 7 x 7 area average (close to the band-limited image), 3 x 3 rays are far nearer than one ray.
    error_1 = np.sqrt(np.mean((colour_1 - colour_7) ** 2))
    error_3 = np.sqrt(np.mean((colour_3 - colour_7) ** 2))
    assert error_3 < 0.4 * error_1, (error_3, error_1)
    with pytest.raises(ValueError, match="odd"):
        render(scene, camera, pose, supersampling=2)


# The blurred benchmark sequence (its loop turns at most about 40 deg/s), at a tiny image size.
BLUR = SynthOptions(frame_count=120, width=64, height=48, exposure_s=1 / 30,
                    bursts=RotationBursts(count=2, speed_deg_s=90.0, duration_s=1.5))


@pytest.fixture(scope="module")
def blurred_dir(tmp_path_factory):
    """A 120-frame 64x48 sequence with a 1/30 s exposure and two 1.5 s bursts at 90 deg/s."""
    folder = tmp_path_factory.mktemp("blurred") / "room"
    write_synthetic_sequence(folder, BLUR)
    return folder


def _read_rgb(path):
    return cv2.imread(str(path))[:, :, ::-1]


def _frame_speeds_deg_s(trajectory):
    """Angular speed (N-1,) between consecutive poses, degrees per second."""
    rotations = trajectory.world_from_camera[:, :3, :3]
    relative = Rotation.from_matrix(np.transpose(rotations[:-1], (0, 2, 1)) @ rotations[1:])
    return np.rad2deg(relative.magnitude()) / np.diff(trajectory.timestamps_s)


@pytest.mark.slow  # writes a 120-frame blurred sequence (once per module)
def test_blurred_frame_is_the_mean_of_sharp_renders_along_the_true_path(blurred_dir):
    scene, camera, path = make_room_scene(0), default_camera(64, 48), BLUR.path
    truth = read_tum_trajectory(blurred_dir / "groundtruth.txt")
    names = sorted((blurred_dir / "rgb").iterdir())
    for index in (3, 30):
        pose = truth.world_from_camera[index]
        np.testing.assert_allclose(path.poses([index])[0], pose, atol=1e-6)  # groundtruth.txt is the path
        count = blur_subframe_count(camera, render(scene, camera, pose)[1], pose,
                                    *path.poses(index + np.array([-0.5, 0.5])))
        assert 2 <= count < MAX_BLUR_SUBFRAMES
        positions = subframe_positions(index, BLUR.fps, BLUR.exposure_s, count)
        # The sub-frames span the exposure, centred on the frame's timestamp.
        assert positions.mean() == pytest.approx(index) and np.ptp(positions) == pytest.approx(1.0 - 1.0 / count)
        mean = np.mean([render(scene, camera, sub)[0] for sub in path.poses(positions)], axis=0)
        stored = _read_rgb(names[index]).astype(np.float64)
        # Equal to the 8-bit rounding (float32 sums in another order can flip a rounding at .5).
        assert np.abs(stored - np.clip(mean, 0, 1) * 255.0).max() <= 0.5 + 1e-3
        sharp = render(scene, camera, pose)[0]
        assert np.abs(stored / 255.0 - sharp).mean() > 0.01  # and visibly not the sharp frame


def test_zero_exposure_is_the_sharp_frame(tmp_path):
    scene, camera = make_room_scene(0), default_camera(80, 60)
    pose = loop_path(10)[4]
    sharp = render(scene, camera, pose)[0]
    np.testing.assert_array_equal(render_exposure(scene, camera, pose[None]), sharp)
    # A vanishing exposure renders every sub-frame at the frame's pose: rgb/ is the unblurred sequence's (to a
    # rounding of the 8-bit value) and gt_rgb/ is it byte for byte.
    write_synthetic_sequence(tmp_path / "instant", SynthOptions(frame_count=10, width=80, height=60, exposure_s=1e-9,
                                                               blur_subframes=3))
    write_synthetic_sequence(tmp_path / "none", SynthOptions(frame_count=10, width=80, height=60))
    names = sorted(p.name for p in (tmp_path / "none" / "rgb").iterdir())
    for name in names:
        reference = (tmp_path / "none" / "rgb" / name).read_bytes()
        assert (tmp_path / "instant" / GT_RGB_FOLDER / name).read_bytes() == reference
        difference = np.abs(_read_rgb(tmp_path / "instant" / "rgb" / name).astype(int) - _read_rgb(tmp_path / "none" / "rgb" / name))
        assert difference.max() <= 1 and difference.mean() < 0.01
    assert not (tmp_path / "none" / GT_RGB_FOLDER).exists()  # an unblurred, noise-free rgb/ is its own ground truth
    np.testing.assert_allclose(_read_rgb(tmp_path / "none" / "rgb" / names[4]) / 255.0, sharp, atol=0.5 / 255 + 1e-6)


def _burst_masks(times_s):
    """Per interval between consecutive times: inside a burst clear of its speed ramps, and outside any burst."""
    middles, half_step = (times_s[:-1] + times_s[1:]) / 2.0, 0.5 / BLUR.fps
    steady, outside = np.zeros(len(middles), bool), np.ones(len(middles), bool)
    for start_s, end_s in BLUR.bursts.windows_s(BLUR.frame_count / BLUR.fps):
        # Clear of the ramps at the start, at the turn in the middle and at the end.
        steady |= (middles - half_step >= start_s + BURST_RAMP_S) & (middles + half_step <= end_s - BURST_RAMP_S) & (
            np.abs(middles - (start_s + end_s) / 2.0) >= BURST_RAMP_S / 2.0 + half_step)
        outside &= (middles + half_step <= start_s) | (middles - half_step >= end_s)
    return steady, outside


@pytest.mark.slow  # writes a 120-frame blurred sequence (once per module)
def test_bursts_turn_at_the_requested_speed_in_groundtruth(blurred_dir):
    truth = read_tum_trajectory(blurred_dir / "groundtruth.txt")
    speeds = _frame_speeds_deg_s(truth)
    steady, outside = _burst_masks(truth.timestamps_s)
    assert steady.sum() >= 60 and outside.sum() >= 20
    assert np.all((speeds[steady] > 60.0) & (speeds[steady] < 120.0)), speeds[steady]
    assert np.median(speeds[steady]) == pytest.approx(90.0, rel=0.1)
    # Outside the bursts the camera follows the plain loop, and the loop still closes.
    np.testing.assert_allclose(truth.world_from_camera[[0, -1]], loop_path(BLUR.frame_count)[[0, -1]], atol=1e-6)
    assert speeds[outside].max() < 45.0


@pytest.mark.slow  # writes a 120-frame blurred sequence (once per module)
def test_gt_rgb_holds_the_sharp_render_and_blur_lowers_sharpness_in_bursts(blurred_dir):
    scene, camera = make_room_scene(0), default_camera(64, 48)
    truth = read_tum_trajectory(blurred_dir / "groundtruth.txt")
    names = sorted(p.name for p in (blurred_dir / "rgb").iterdir())
    assert names == sorted(p.name for p in (blurred_dir / GT_RGB_FOLDER).iterdir())
    for index in (0, 30):
        sharp = render(scene, camera, truth.world_from_camera[index])[0]
        np.testing.assert_allclose(_read_rgb(blurred_dir / GT_RGB_FOLDER / names[index]) / 255.0, sharp,
                                   atol=0.5 / 255 + 1e-6)
    steady, outside = _burst_masks(truth.timestamps_s)
    in_burst, plain = steady[:-1] & steady[1:], outside[:-1] & outside[1:]  # frames between two such intervals
    blurred = np.array([sharpness(_read_rgb(blurred_dir / "rgb" / name)) for name in names])[1:-1]
    sharp = np.array([sharpness(_read_rgb(blurred_dir / GT_RGB_FOLDER / name)) for name in names])[1:-1]
    assert np.all(blurred < sharp)
    assert np.median(blurred[in_burst] / sharp[in_burst]) < 0.7 * np.median(blurred[plain] / sharp[plain])


def test_bursts_that_do_not_fit_are_refused():
    with pytest.raises(ConfigError, match="do not fit"):
        SynthOptions(frame_count=30, bursts=RotationBursts(count=1, duration_s=1.0))
    with pytest.raises(ConfigError, match="exposure"):
        SynthOptions(exposure_s=0.1)
