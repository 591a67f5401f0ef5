"""Point fusion's candidate search against its obvious twin."""

from types import SimpleNamespace

import numpy as np

from tambridge.frontend.orb.local_mapping import points_not_seen_by


def test_points_not_seen_by_a_keyframe_are_numpys_set_difference():
    """Marking gives what ``np.setdiff1d`` gives, sorted and unique, for ids repeated, unsorted or absent, and
    keypoints without a point (-1)."""
    rng = np.random.default_rng(0)
    for _ in range(500):
        count = int(rng.integers(1, 400))
        point_ids = rng.integers(0, count, int(rng.integers(0, 300)))
        keyframe = SimpleNamespace(point_ids=rng.integers(-1, count, int(rng.integers(0, 300))))
        slam_map = SimpleNamespace(points=SimpleNamespace(count=count))
        candidates = points_not_seen_by(slam_map, keyframe, point_ids)
        expected = np.setdiff1d(point_ids, keyframe.point_ids)
        assert candidates.dtype == np.int64
        np.testing.assert_array_equal(candidates, expected)
