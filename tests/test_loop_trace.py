"""The loop-query trace (what benchmarks/loops.py reads): it records every query and what became of each keyframe
the database returned, and changes no decision of the frontend."""

import numpy as np
import pytest

import tambridge.frontend.orb.frontend as orb_frontend
from tambridge.frontend.orb.config import OrbFrontendConfig
from tambridge.frontend.orb.loop_closing import LoopOutcome, detect_loop
from tambridge.io.tum import open_sequence
from tests.test_frontend_orb import _panorama


def _run(sequence, monkeypatch, trace, connected=None):
    """Inline mapping (deterministic), the settings of the synthetic loop tests; ``trace``: a list or None;
    ``connected``: a dict to fill with each query keyframe's covisible keyframes at the time of its query."""
    if trace is not None:
        def traced(slam_map, keyframe, *arguments):
            connected[keyframe.id] = set(keyframe.covisibility)
            return detect_loop(slam_map, keyframe, *arguments, trace=trace)

        monkeypatch.setattr(orb_frontend, "detect_loop", traced)
    frontend = orb_frontend.OrbFrontend(sequence.camera, OrbFrontendConfig(
        depth_residuals=True, depth_noise_per_m=0.003, mapping_thread=False, loop_consistency=0))
    for frame in sequence:
        frontend.track(frame)
    monkeypatch.undo()
    return frontend, frontend.finish()


def test_the_trace_records_every_query_and_changes_nothing(synthetic_sequence_dir, monkeypatch):
    sequence = open_sequence(synthetic_sequence_dir)
    queries, connected = [], {}
    _, traced = _run(sequence, monkeypatch, queries, connected)
    _, plain = _run(sequence, monkeypatch, None)
    np.testing.assert_array_equal(traced.trajectory.world_from_camera, plain.trajectory.world_from_camera)
    assert traced.loops_closed == plain.loops_closed
    # One query per keyframe after the first (no loop closed: no cool-down), in keyframe order.
    keyframes = len(traced.keyframe_poses)
    assert traced.loops_closed == 0 and [q.keyframe_id for q in queries] == list(range(1, keyframes))
    for query in queries:
        assert query.frame_index == traced.keyframe_frame_indices[query.keyframe_id]
        ids = [c.keyframe_id for c in query.candidates]
        # The database holds the keyframes before the query, each returned once, best score first.
        assert len(set(ids)) == len(ids) and all(i < query.keyframe_id for i in ids)
        scores = [c.score for c in query.candidates]
        assert scores == sorted(scores, reverse=True) and all(0 < s <= 1 for s in scores)
        for candidate in query.candidates:
            covisible = candidate.keyframe_id in connected[query.keyframe_id]
            assert (candidate.outcome == LoopOutcome.covisible) == covisible
            if candidate.outcome == LoopOutcome.low_score:
                assert candidate.score < 0.75 * query.min_score
            assert (candidate.inliers is not None) == (candidate.outcome in (LoopOutcome.unverified, LoopOutcome.accepted))
            if candidate.outcome == LoopOutcome.unverified:
                assert candidate.inliers < 40
    # The synthetic room is small: the tracker keeps seeing the first keyframes, which no loop may claim.
    assert sum(c.outcome == LoopOutcome.covisible for q in queries for c in q.candidates) > 0


@pytest.mark.slow
def test_the_trace_of_a_closed_loop_holds_its_accepted_candidate(monkeypatch):
    """The 380-degree panorama of test_frontend_orb closes a loop: the trace holds it, verified by enough inliers,
    against a keyframe that shares no map point with the query."""
    frames, _, camera = _panorama(48, seed=2)
    queries, connected = [], {}

    def traced(slam_map, keyframe, *arguments):
        connected[keyframe.id] = set(keyframe.covisibility)
        return detect_loop(slam_map, keyframe, *arguments, trace=queries)

    monkeypatch.setattr(orb_frontend, "detect_loop", traced)
    config = OrbFrontendConfig(n_features=800, n_levels=5, edge_threshold_px=12, grid_cell_px=20, scale_with_image=False,
                               depth_residuals=True, depth_noise_per_m=0.003, mapping_thread=False)
    frontend = orb_frontend.OrbFrontend(camera, config)
    for frame in frames:
        frontend.track(frame)
    final = frontend.finish()
    accepted = [(q, c) for q in queries for c in q.candidates if c.outcome == LoopOutcome.accepted]
    assert final.loops_closed >= 1 and len(accepted) == final.loops_closed
    for query, candidate in accepted:
        assert candidate.inliers >= config.loop_min_inliers
        assert candidate.keyframe_id not in connected[query.keyframe_id]
        assert candidate.score >= config.loop_min_score_ratio * query.min_score
