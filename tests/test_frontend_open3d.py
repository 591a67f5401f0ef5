"""The Open3D keyframe frontend on the synthetic loop: accuracy against ground truth and the shared interface."""

import numpy as np
import pytest

from tambridge.evaluation.trajectory import ate_rmse_m
from tambridge.frontend.open3d.frontend import Open3dFrontend
from tambridge.frontend.open3d.odometry import FrameToFrameOdometry
from tambridge.frontend.open3d.config import Open3dFrontendConfig
from tambridge.io.tum import open_sequence


def test_open3d_frontend_ate_and_interface(synthetic_sequence_dir):
    sequence = open_sequence(synthetic_sequence_dir)
    frontend = Open3dFrontend(sequence.camera)
    results = [frontend.track(frame) for frame in sequence]
    final = frontend.finish()
    assert all(r.tracked for r in results) and final.frames_lost == 0
    # 30 frames, 160x120, noise-free; it closes loops back to the first keyframes.
    assert ate_rmse_m(final.trajectory, sequence.ground_truth) < 0.015
    assert final.loops_closed >= 1
    events = [r.keyframe for r in results if r.is_keyframe]
    assert [e.keyframe_id for e in events] == sorted(final.keyframe_poses)
    assert all(len(e.points_world_m) == len(e.keypoints_px) == len(e.map_point_ids) == 0 for e in events)
    for keyframe_id, frame_index in final.keyframe_frame_indices.items():
        np.testing.assert_allclose(final.trajectory.world_from_camera[frame_index], final.keyframe_poses[keyframe_id], atol=1e-9)


@pytest.mark.parametrize("kind", ["open3d", "open3d_f2f"])
def test_a_requested_keyframe_is_the_next_registered_frame(synthetic_sequence_dir, kind):
    """``request_keyframe`` (the mapper's coverage rule) overrides the motion rule once; the rule is set here to
    make no keyframe after the first by itself."""
    sequence = open_sequence(synthetic_sequence_dir, max_frames=4)
    if kind == "open3d":
        frontend = Open3dFrontend(sequence.camera, Open3dFrontendConfig(keyframe_translation_m=100.0, keyframe_rotation_deg=360.0,
                                                                        keyframe_max_frames=100))
    else:
        frontend = FrameToFrameOdometry(sequence.camera, keyframe_translation_m=100.0, keyframe_rotation_deg=360.0)
    made = []
    for frame in sequence:
        if frame.index == 2:
            frontend.request_keyframe()
        if frontend.track(frame).is_keyframe:
            made.append(frame.index)
    assert made == [0, 2]
