"""Loop closure over keyframes: bag-of-words retrieval, PnP verification, pose graph, map point fusion.

1. Candidates: keyframes the database scores at least ``loop_min_score_ratio`` times the lowest score of
   the new keyframe's covisible neighbours (ORB-SLAM's bar), that are not connected to it, and whose
   covisibility group was also a candidate for the ``loop_consistency`` keyframes before (:class:`LoopConsistency`).
2. Verification: :func:`~tambridge.frontend.orb.map_matching.localise` of the new keyframe against the points of
   the candidate and its neighbours; at least ``loop_min_inliers`` inliers.
3. Correction: a pose graph over all keyframes (consecutive-keyframe edges, strong covisibility edges, every
   loop edge so far, weak links between map segments) optimised with Open3D; points follow their reference
   keyframe; the loop's matched points are fused (duplicates merged), which ties the two ends for global BA.
"""

from __future__ import annotations

import dataclasses
import logging

import numpy as np

from tambridge.camera import Camera
from tambridge.frontend.orb.local_mapping import fuse_points
from tambridge.frontend.orb.map_matching import PoseFix, localise
from tambridge.frontend.pose_graph import PoseEdge, optimise_pose_graph
from tambridge.frontend.orb.slam_map import Keyframe, SlamMap
from tambridge.frontend.orb.config import OrbFrontendConfig
from tambridge.frontend.orb.vocabulary import KeyframeDatabase, bow_score
from tambridge.geometry import inverse
from tambridge.settings import Choice

logger = logging.getLogger("tambridge.frontend.orb.loop_closing")

STRONG_COVISIBILITY = 100  # ORB-SLAM's essential graph keeps covisibility edges of at least 100 shared points
LOOP_GROUP_NEIGHBOURS = 5
SEGMENT_LINK_INFORMATION = 1e-6  # a guess across a tracking loss: almost no weight against real constraints


class LoopOutcome(Choice):
    """What became of a keyframe the database returned for a loop query (the checks of :func:`detect_loop`, in
    order)."""

    covisible = "covisible"  # the new keyframe or one that shares map points with it: not a loop
    low_score = "low_score"  # below loop_min_score_ratio times the lowest score of the covisible neighbours
    inconsistent = "inconsistent"  # its group was not a candidate for the loop_consistency keyframes before
    not_tried = "not_tried"  # consistent, but beyond the loop_candidates verified per keyframe
    unverified = "unverified"  # localise against its group found fewer than loop_min_inliers inliers
    accepted = "accepted"


@dataclasses.dataclass
class LoopCandidateTrace:
    """A keyframe the database scored for a loop query: its BoW ``score`` in [0, 1], the ``outcome``, and for a
    verified one the PnP ``inliers`` its best pose had (0: no pose at all; None: not verified)."""

    keyframe_id: int
    score: float
    outcome: LoopOutcome
    inliers: int | None = None


@dataclasses.dataclass
class LoopQueryTrace:
    """One loop query of keyframe ``keyframe_id``: ``min_score`` is the bar's reference (lowest score of its best
    covisible neighbours; None without neighbours: nothing is looked up), ``candidates`` best score first."""

    keyframe_id: int
    frame_index: int
    min_score: float | None
    candidates: list[LoopCandidateTrace]


@dataclasses.dataclass
class LoopDetection:
    """A verified loop: the new keyframe's pose in the map around ``candidate_id`` and the supporting matches."""

    candidate_id: int
    fix: PoseFix


class LoopConsistency:
    """ORB-SLAM's temporal consistency of loop candidates: a candidate is accepted once its covisibility group
    (the candidate and its covisible keyframes) overlaps a group that was a candidate for each of the
    ``required`` keyframes before (0 accepts every candidate). State: the groups of the last query with their
    consistency counts."""

    def __init__(self, required: int) -> None:
        self.required = required
        self.groups: list[tuple[set[int], int]] = []

    def accept(self, candidate_groups: list[tuple[int, set[int]]]) -> list[int]:
        """Candidates ``(keyframe id, group of keyframe ids)`` of the new keyframe, in score order -> accepted ids."""
        current, accepted = [], []
        for candidate_id, group in candidate_groups:
            count = max((previous_count + 1 for previous, previous_count in self.groups if previous & group), default=0)
            current.append((group, count))
            if count >= self.required:
                accepted.append(candidate_id)
        self.groups = current
        return accepted


def detect_loop(
    slam_map: SlamMap, keyframe: Keyframe, database: KeyframeDatabase, camera: Camera, config: OrbFrontendConfig,
    consistency: LoopConsistency, trace: list[LoopQueryTrace] | None = None,
) -> LoopDetection | None:
    """Look for a keyframe the new one revisits; consistent over consecutive keyframes and verified geometrically,
    else None. ``trace``: a list to append this query's :class:`LoopQueryTrace` to (diagnostics; a rejected
    verification is then run again with a low inlier bar to count its inliers, which changes no decision)."""
    neighbours = keyframe.best_covisible(10)
    if not neighbours:
        consistency.accept([])
        if trace is not None:
            trace.append(LoopQueryTrace(keyframe.id, keyframe.frame_index, None, []))
        return None
    min_score = min(
        bow_score(keyframe.bow_words, keyframe.bow_weights, slam_map.keyframes[n].bow_words, slam_map.keyframes[n].bow_weights)
        for n in neighbours
    )
    ids, scores = database.query(keyframe.bow_words, keyframe.bow_weights)
    connected = set(keyframe.covisibility) | {keyframe.id}
    outcomes = {int(i): LoopOutcome.covisible if i in connected else LoopOutcome.low_score for i in ids}
    candidates = [int(i) for i, s in zip(ids, scores) if i not in connected and s >= config.loop_min_score_ratio * min_score]
    outcomes.update((c, LoopOutcome.inconsistent) for c in candidates)
    candidates = consistency.accept([(c, {c} | set(slam_map.keyframes[c].covisibility)) for c in candidates])
    outcomes.update((c, LoopOutcome.not_tried) for c in candidates)
    inliers: dict[int, int] = {}
    detection = None
    for candidate_id in candidates[: config.loop_candidates]:
        candidate = slam_map.keyframes[candidate_id]
        group = [candidate] + [slam_map.keyframes[i] for i in candidate.best_covisible(LOOP_GROUP_NEIGHBOURS)]
        group_points = slam_map.points_of([k for k in group if k.id not in connected])
        fix = localise(slam_map, keyframe.features, keyframe.keypoint_grid, group_points, camera, config,
                       config.loop_min_inliers)
        if fix is not None and fix.inlier_count >= config.loop_min_inliers:
            outcomes[candidate_id], inliers[candidate_id] = LoopOutcome.accepted, fix.inlier_count
            detection = LoopDetection(candidate_id, fix)
            break
        outcomes[candidate_id] = LoopOutcome.unverified
        if trace is not None:
            probe = localise(slam_map, keyframe.features, keyframe.keypoint_grid, group_points, camera, config, 6)
            inliers[candidate_id] = 0 if probe is None else probe.inlier_count
    if trace is not None:
        trace.append(LoopQueryTrace(keyframe.id, keyframe.frame_index, float(min_score), [
            LoopCandidateTrace(int(i), float(s), outcomes[int(i)], inliers.get(int(i))) for i, s in zip(ids, scores)]))
    return detection


def _graph_edges(slam_map: SlamMap, world_from_camera: np.ndarray) -> list[PoseEdge]:
    """Consecutive live keyframes of a segment, strong covisibility, loops and segment links, measured at the
    given poses; a culled keyframe hangs from its parent by one edge (it follows the parent exactly afterwards)."""
    edges = []
    identity = np.eye(6)

    def relative(source: int, target: int) -> np.ndarray:
        return inverse(world_from_camera[target]) @ world_from_camera[source]

    previous_of_segment: dict[int, int] = {}
    for keyframe in slam_map.keyframes:
        if keyframe.culled:
            edges.append(PoseEdge(keyframe.parent, keyframe.id, relative(keyframe.parent, keyframe.id), identity))
            continue
        previous = previous_of_segment.get(keyframe.segment)
        if previous is not None:
            edges.append(PoseEdge(previous, keyframe.id, relative(previous, keyframe.id), identity))
        previous_of_segment[keyframe.segment] = keyframe.id
        for other, weight in keyframe.covisibility.items():
            if other < keyframe.id and weight >= STRONG_COVISIBILITY and other != previous:
                edges.append(PoseEdge(other, keyframe.id, relative(other, keyframe.id), identity))
    for source, target, target_from_source in slam_map.loop_edges:
        edges.append(PoseEdge(source, target, target_from_source, identity))
    for source, target, target_from_source in slam_map.segment_links:
        edges.append(PoseEdge(source, target, target_from_source, SEGMENT_LINK_INFORMATION * identity))
    return edges


def close_loop(slam_map: SlamMap, keyframe: Keyframe, loop: LoopDetection, camera: Camera, config: OrbFrontendConfig) -> None:
    """Correct the keyframe poses and the map for a verified loop (see the module docstring)."""
    before = np.stack([k.world_from_camera for k in slam_map.keyframes])
    world_from_corrected = inverse(loop.fix.camera_from_world)
    correction = world_from_corrected @ inverse(keyframe.world_from_camera)
    candidate = slam_map.keyframes[loop.candidate_id]
    slam_map.loop_edges.append(
        (loop.candidate_id, keyframe.id, loop.fix.camera_from_world @ candidate.world_from_camera)
    )
    initial = before.copy()
    for moved in [keyframe.id] + keyframe.best_covisible(len(slam_map.keyframes)):
        initial[moved] = correction @ before[moved]
    edges = _graph_edges(slam_map, before)
    optimised, _ = optimise_pose_graph(initial, edges, reference_node=0)
    for k, pose in zip(slam_map.keyframes, optimised):
        k.world_from_camera = pose
    slam_map.update_culled_poses()
    slam_map.move_points_with_keyframes(before)

    # Fuse the loop side's points into the new keyframe and its neighbours (now at corrected poses).
    group = [candidate] + [slam_map.keyframes[i] for i in candidate.best_covisible(LOOP_GROUP_NEIGHBOURS)]
    loop_points = slam_map.points_of(group)
    olds, news = [], []
    touched = [keyframe.id] + keyframe.best_covisible(LOOP_GROUP_NEIGHBOURS)
    for keyframe_id in touched:
        o, n = fuse_points(slam_map, slam_map.keyframes[keyframe_id], loop_points, camera, config, incoming_wins=True)
        olds += o
        news += n
    slam_map.replace_points(np.array(olds, np.int64), np.array(news, np.int64))
    slam_map.update_covisibility([slam_map.keyframes[k] for k in set(touched) | {k.id for k in group}],
                                 config.covisibility_min_shared)
    shift_m = float(np.linalg.norm(correction[:3, 3]))
    logger.info("loop closed: keyframe %d (frame %d) revisits keyframe %d (frame %d), %d inliers, correction %.3f m",
                keyframe.id, keyframe.frame_index, candidate.id, candidate.frame_index, loop.fix.inlier_count, shift_m)
