"""Keyframe culling in the ORB frontend: the redundancy count against a loop twin, and a lingering camera whose
redundant keyframes get culled without costing accuracy, without losing poses, and through a checkpoint."""

import pickle

import numpy as np
import pytest

from tambridge.evaluation.trajectory import ate_rmse_m
from tambridge.frontend.orb.local_mapping import finer_observer_counts
from tambridge.frontend.orb.frontend import OrbFrontend
from tambridge.frontend.orb.config import OrbFrontendConfig
from tambridge.frontend.orb.vocabulary import KeyframeDatabase
from tambridge.geometry import inverse, look_at
from tambridge.io.synthetic import default_camera, make_room_scene, render
from tambridge.io.tum import Frame
from tambridge.trajectory import Trajectory

# As tests/test_frontend_orb.py: ORB settings for 160x120, depth residuals on (registered synthetic depth). A
# keyframe at every frame that tracks fewer points than its reference keyframe: a lingering camera then makes
# many keyframes that see the same things.
LINGER = dict(n_features=500, n_levels=4, edge_threshold_px=10, grid_cell_px=16, scale_with_image=False, depth_residuals=True,
              depth_noise_per_m=0.003, keyframe_min_frames=1, keyframe_tracked_ratio=1.0, mapping_thread=False)
FRAMES = 30


def test_finer_observer_counts_matches_a_loop():
    rng = np.random.default_rng(0)
    n_points = 50
    point_ids = rng.choice(n_points, 20, replace=False)
    octaves = rng.integers(0, 4, 20)
    observed_ids = rng.integers(0, n_points, 300)
    observed_octaves = rng.integers(0, 4, 300)
    counts = finer_observer_counts(point_ids, octaves, observed_ids, observed_octaves, n_points)
    expected = [sum(1 for p, o in zip(observed_ids, observed_octaves) if p == point and o <= octave + 1)
                for point, octave in zip(point_ids, octaves)]
    np.testing.assert_array_equal(counts, expected)


def test_database_counts_a_culled_keyframes_matches_for_its_parent():
    database = KeyframeDatabase(n_words=10)
    database.add(0, np.array([0, 1]), np.array([0.5, 0.5]))
    database.add(1, np.array([2, 3]), np.array([0.5, 0.5]))
    database.add(2, np.array([3, 4]), np.array([0.5, 0.5]))
    database.add(3, np.array([5, 6]), np.array([0.5, 0.5]))
    database.redirect(1, 2)
    ids, scores = database.query(np.array([2, 3]), np.array([0.5, 0.5]))
    # Keyframe 1 matched fully (1.0), keyframe 2 by half (0.5): keyframe 2 gets the better of the two.
    assert ids.tolist() == [2] and scores.tolist() == [1.0]
    database.redirect(2, 3)  # the parent is culled in turn: both now count for keyframe 3
    ids, scores = database.query(np.array([2, 3]), np.array([0.5, 0.5]))
    assert ids.tolist() == [3] and scores.tolist() == [1.0]


@pytest.fixture(scope="module")
def lingering():
    """30 frames, 160x120, of a camera swaying a few centimetres in the synthetic room (noise-free)."""
    scene = make_room_scene(0)
    camera = default_camera(160, 120)
    frames, poses = [], []
    for index in range(FRAMES):
        sway = np.sin(4 * np.pi * index / FRAMES)
        eye = np.array([-0.3 + 0.08 * sway, 0.05 * np.cos(2 * np.pi * index / FRAMES), 1.4])
        poses.append(look_at(eye, eye + np.array([1.0, 0.15 * sway, -0.3])))
        colour, depth_m = render(scene, camera, poses[-1])
        frames.append(Frame(index, index / 30.0, (colour * 255 + 0.5).astype(np.uint8), depth_m.astype(np.float32)))
    return frames, Trajectory(np.arange(FRAMES) / 30.0, np.stack(poses)), camera


def _track(frames, camera, culling: bool):
    frontend = OrbFrontend(camera, OrbFrontendConfig(**LINGER, keyframe_culling=culling))
    results = [frontend.track(frame) for frame in frames]
    return frontend, results, frontend.finish()


@pytest.fixture(scope="module")
def culled_and_kept(lingering):
    frames, _, camera = lingering
    return _track(frames, camera, culling=True), _track(frames, camera, culling=False)


def test_lingering_camera_culls_redundant_keyframes_at_the_same_accuracy(lingering, culled_and_kept):
    _, truth, _ = lingering
    (frontend, results, final), (_, _, kept) = culled_and_kept
    assert all(r.tracked for r in results)
    assert kept.keyframes_culled == 0
    # About half the keyframes of the lingering camera are redundant; culling them costs at most 2 mm of ATE.
    culled = [k for k in frontend.map.keyframes if k.culled]
    assert final.keyframes_culled == len(culled) >= 5
    assert not frontend.map.keyframes[0].culled
    ate_culled, ate_kept = ate_rmse_m(final.trajectory, truth), ate_rmse_m(kept.trajectory, truth)
    assert ate_kept < 0.01
    assert abs(ate_culled - ate_kept) < 0.002


def test_the_mapping_thread_makes_the_keyframes_an_inline_run_makes(lingering, culled_and_kept):
    """The frame after a keyframe tracks against that keyframe's fused points, as inline: the share of the reference
    keyframe's points seen twice decides the next keyframe (against the unfused map it made far fewer here). Local
    BA may still run meanwhile, so the thread's timing still moves the ATE (docs/benchmarks.md)."""
    frames, truth, camera = lingering
    (inline, _, inline_final), _ = culled_and_kept
    threaded = OrbFrontend(camera, OrbFrontendConfig(**dict(LINGER, mapping_thread=True), keyframe_culling=True))
    results = [threaded.track(frame) for frame in frames]
    final = threaded.finish()
    assert all(r.tracked for r in results)
    assert abs(len(threaded.map.keyframes) - len(inline.map.keyframes)) <= 2
    assert abs(ate_rmse_m(final.trajectory, truth) - ate_rmse_m(inline_final.trajectory, truth)) < 0.002


def test_culled_keyframes_keep_poses_and_leave_the_map(lingering, culled_and_kept):
    _, truth, _ = lingering
    (frontend, results, final), _ = culled_and_kept
    slam_map = frontend.map
    events = [r.keyframe for r in results if r.is_keyframe]
    # Every announced keyframe, culled or not, has a final pose, a frame and a row of keyframes.txt.
    assert set(final.keyframe_poses) == set(final.keyframe_frame_indices) == {e.keyframe_id for e in events}
    assert len(final.keyframe_trajectory) == len(events)
    live = {k.id for k in slam_map.keyframes if not k.culled}
    for keyframe in slam_map.keyframes:
        if not keyframe.culled:
            continue
        assert keyframe.parent in live
        # It follows its parent rigidly, sits where its frame is in the trajectory, and near the truth.
        np.testing.assert_allclose(final.keyframe_poses[keyframe.id],
                                   final.keyframe_poses[keyframe.parent] @ keyframe.parent_from_camera, atol=1e-12)
        frame_pose = final.trajectory.world_from_camera[keyframe.frame_index]
        np.testing.assert_allclose(final.keyframe_poses[keyframe.id], frame_pose, atol=1e-9)
        offset = inverse(truth.world_from_camera[0]) @ truth.world_from_camera[keyframe.frame_index]
        estimate = inverse(final.trajectory.world_from_camera[0]) @ frame_pose
        assert np.linalg.norm(offset[:3, 3] - estimate[:3, 3]) < 0.02
        # Out of the map: no observations, no covisibility either way, not a point's reference.
        assert (keyframe.point_ids == -1).all() and not keyframe.covisibility
        assert all(keyframe.id not in other.covisibility for other in slam_map.keyframes)
        good = ~slam_map.points.bad[: slam_map.points.count]
        assert keyframe.id not in slam_map.points.reference_keyframe[: slam_map.points.count][good]
        # Its view is still retrieved, for a live keyframe.
        ids, _ = frontend.database.query(keyframe.bow_words, keyframe.bow_weights)
        assert keyframe.id not in ids and set(ids.tolist()) <= live and len(ids)
    # Frames whose reference keyframe was culled afterwards still have right poses.
    referencing = [r.frame_index for r in frontend._records if slam_map.keyframes[r.reference_keyframe].culled]
    assert referencing
    aligned = Trajectory(truth.timestamps_s[referencing], truth.world_from_camera[referencing])
    estimate = Trajectory(final.trajectory.timestamps_s[referencing], final.trajectory.world_from_camera[referencing])
    assert ate_rmse_m(estimate, aligned) < 0.01


def test_culling_state_survives_a_checkpoint(lingering, culled_and_kept):
    frames, _, camera = lingering
    (_, _, uninterrupted), _ = culled_and_kept
    first = OrbFrontend(camera, OrbFrontendConfig(**LINGER, keyframe_culling=True))
    for frame in frames[:18]:
        first.track(frame)
    assert first.keyframes_culled > 0
    state = pickle.loads(pickle.dumps(first.state_dict()))
    second = OrbFrontend(camera, OrbFrontendConfig(**LINGER, keyframe_culling=True))
    second.load_state_dict(state)
    assert second.keyframes_culled == first.keyframes_culled
    assert [k.parent for k in second.map.keyframes] == [k.parent for k in first.map.keyframes]
    for frame in frames[18:]:
        second.track(frame)
    resumed = second.finish()
    assert resumed.keyframes_culled == uninterrupted.keyframes_culled
    np.testing.assert_allclose(resumed.trajectory.world_from_camera, uninterrupted.trajectory.world_from_camera, atol=1e-9)
