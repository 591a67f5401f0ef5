"""Point fusion's bookkeeping against obvious twins: the candidate search, covisibility counts and point merges."""

from types import SimpleNamespace

import numpy as np

from tambridge.frontend.orb.local_mapping import points_not_seen_by
from tambridge.frontend.orb.slam_map import SlamMap


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


def _random_map(rng: np.random.Generator, keyframe_count: int, point_count: int) -> SlamMap:
    """Keyframes that each see a random subset of the points once (-1 elsewhere), a tenth of the points bad."""
    slam_map = SlamMap()
    slam_map.points.add(rng.normal(size=(point_count, 3)) + [0.0, 0.0, 3.0], np.zeros((point_count, 32), np.uint8),
                        np.zeros((point_count, 3), np.uint8), np.zeros(3), np.zeros(point_count, np.int64), 0, 1.2, 8)
    slam_map.points.bad[rng.choice(point_count, point_count // 10, replace=False)] = True
    for keyframe_id in range(keyframe_count):
        keypoints = int(rng.integers(0, 60))
        seen = rng.choice(point_count, int(rng.integers(0, keypoints + 1)), replace=False)
        point_ids = np.full(keypoints, -1, np.int64)
        point_ids[rng.choice(keypoints, seen.size, replace=False)] = seen
        slam_map.keyframes.append(SimpleNamespace(id=keyframe_id, point_ids=point_ids, covisibility={}))
    return slam_map


def _recount_alone(slam_map: SlamMap, keyframe, min_shared: int) -> None:
    """The slow twin of one keyframe's recount, with sets: its pairs with every other keyframe by the good points they
    share, dropped from the others and kept at ``min_shared`` or more (or the best, lowest id first) both ways."""
    good = [set(k.point_ids[slam_map.points.good(k.point_ids)].tolist()) for k in slam_map.keyframes]
    shared = {}
    for other in slam_map.keyframes:
        other.covisibility.pop(keyframe.id, None)
        if other.id != keyframe.id and good[keyframe.id] & good[other.id]:
            shared[other.id] = len(good[keyframe.id] & good[other.id])
    kept = {j: w for j, w in shared.items() if w >= min_shared}
    if not kept and shared:
        best = max(shared.values())
        kept = {min(j for j, w in shared.items() if w == best): best}
    keyframe.covisibility = kept
    for j, w in kept.items():
        slam_map.keyframes[j].covisibility[keyframe.id] = w


def test_covisibility_of_several_keyframes_is_that_of_each_recounted_in_turn():
    """Recounting keyframes together gives what a set-based recount of each alone, in the same order, gives: weights
    are the good points two keyframes share, pairs below ``min_shared`` go unless a keyframe has no other, and each
    recount redoes the pairs of the ones before it."""
    rng = np.random.default_rng(1)
    for _ in range(200):
        seed, keyframe_count = int(rng.integers(1 << 30)), int(rng.integers(1, 12))
        together, alone = (_random_map(np.random.default_rng(seed), keyframe_count, 80) for _ in range(2))
        for slam_map in (together, alone):  # covisibility from earlier recounts, which each recount must redo
            slam_map.update_covisibility(slam_map.keyframes, 1)
        chosen = [int(i) for i in rng.permutation(keyframe_count)[: int(rng.integers(1, 6))]]
        min_shared = int(rng.integers(1, 6))
        together.update_covisibility([together.keyframes[i] for i in chosen], min_shared)
        for i in chosen:
            _recount_alone(alone, alone.keyframes[i], min_shared)
        assert [k.covisibility for k in together.keyframes] == [k.covisibility for k in alone.keyframes]


def test_merged_points_leave_each_keyframe_seeing_a_point_once_and_the_others_untouched():
    """``replace_points`` against a twin that renames ids one keypoint at a time: each keyframe sees a survivor
    where it saw a replaced point and keeps the first keypoint of a point it now sees twice; a keyframe that saw no
    replaced point keeps its ids (keyframes see a point once, the map's invariant); the replaced points go bad and
    observations are recounted."""
    rng = np.random.default_rng(2)
    attached = 0
    for _ in range(200):
        slam_map = _random_map(rng, int(rng.integers(1, 10)), 80)
        old = rng.choice(80, int(rng.integers(1, 20)), replace=False)
        new = rng.choice(np.setdiff1d(np.arange(80), old), old.size)
        survivor = dict(zip(old.tolist(), new.tolist()))
        expected = []
        for keyframe in slam_map.keyframes:
            ids, seen = keyframe.point_ids.tolist(), set()
            for index, point in enumerate(ids):
                if point < 0:
                    continue
                point = survivor.get(point, point)
                ids[index] = -1 if point in seen else point
                seen.add(point)
            expected.append(np.array(ids, np.int64))
        slam_map.replace_points(old, new)
        for keyframe, ids in zip(slam_map.keyframes, expected):
            np.testing.assert_array_equal(keyframe.point_ids, ids)
        assert slam_map.points.bad[old].all()
        observed = np.concatenate([keyframe.point_ids for keyframe in slam_map.keyframes])
        np.testing.assert_array_equal(slam_map.points.observations[:80], np.bincount(observed[observed >= 0], minlength=80))
        # With nothing to merge, observations attached since are counted all the same (fusion attaches, then merges).
        free = np.flatnonzero(slam_map.keyframes[0].point_ids < 0)
        unseen = np.setdiff1d(np.arange(80), slam_map.keyframes[0].point_ids)
        if free.size and unseen.size:
            slam_map.keyframes[0].point_ids[free[0]] = unseen[0]
            before = slam_map.points.observations[unseen[0]]
            slam_map.replace_points(np.zeros(0, np.int64), np.zeros(0, np.int64))
            assert slam_map.points.observations[unseen[0]] == before + 1
            attached += 1
    assert attached > 50
