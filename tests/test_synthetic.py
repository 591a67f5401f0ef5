import numpy as np
import pytest

from tambridge.geometry import inverse, transform_points
from tambridge.io.synthetic import default_camera, loop_path, make_room_scene, render
from tambridge.io.tum import open_sequence


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
