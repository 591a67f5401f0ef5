"""The tracking-centred ORB RGB-D frontend (paper sec. 3.2, "ORB visual odometry similar to ORB-SLAM3").

Per frame: ORB features with depth (with ``depth_time_compensation``, the depth first moved to the colour image's
time by the constant-velocity prior: :mod:`~tambridge.frontend.orb.depth_time`) -> map points of the local map
projected with the constant-velocity prior and matched by descriptor near their projection -> motion-only
refinement with a Huber kernel from the prior (PnP-RANSAC only if the prior leaves most matches outliers) -> a
second, tighter projection search and refinement (with a rolling shutter, a third after the keypoints are moved
from their rows' times to the frame's by the frame's own motion: :mod:`~tambridge.rolling_shutter`).
Tracking a frame decides whether it becomes a keyframe
(ORB-SLAM2's rules); a keyframe adds map points from its depth, culls bad recent points, fuses duplicates (points keep their most distinctive
descriptor), runs local BA, and looks for a loop (bag of words, candidates consistent over consecutive
keyframes, PnP verification, pose graph, point fusion). A frame the local map cannot place tries
relocalisation against the keyframes, then its depth alone against the dense term's keyframe surface
(``depth_only_tracking``, from a measured velocity only); failing both it is lost, reported (warning) and, after a
few failures, a new map segment starts, to be joined to the old one by the next loop closure or, at the end, by
localising its newest keyframes against the whole map; a segment still unjoined then is placed between the frames
around it. Relocalisation asks few PnP-RANSAC inliers of the descriptor matches and many of
the pose after a projection search (ORB-SLAM's two bars), and only places a frame in the current segment or one
joined to the first keyframe's world. Lost frames between tracked ones end on the path between them
(:meth:`~tambridge.trajectory.Trajectory.bridged`). ``finish()`` tries once more to join unjoined segments, runs
global BA, places the segments still unjoined and re-anchors every frame to its reference keyframe.

Keyframe culling (``keyframe_culling``, ORB-SLAM's KeyFrameCulling after local BA) takes redundant keyframes
out of the map. Every keyframe has already been announced to the pipeline as a ``KeyframeEvent`` by then (the
event goes out when the keyframe is made), so a culled keyframe is not forgotten: it keeps its id, follows a
live parent keyframe rigidly (:meth:`SlamMap.cull_keyframe`), and stays in ``keyframe_poses()``, in the
keyframe trajectory and as the reference of the frames anchored to it, which therefore keep correct poses.

With ``mapping_thread`` (the default) the keyframe work (point fusion, local BA, loop closing) runs in a
background thread, as ORB-SLAM's local-mapping and loop-closing threads do, while ``track`` goes on with the
next frames. Keyframes are chosen by the same rules as without the thread; when one is due while the thread
still maps the previous one, tracking waits for it (ORB-SLAM, fed frames in real time, would skip the keyframe
instead, but frames here come as fast as tracking takes them: under CPU load, skipping starved the map of
keyframes and lost tracking). The frame after a keyframe waits until that keyframe's points are fused with its
neighbours' (local BA may still be running), as inline it would track against the fused map: the share of the reference
keyframe's points seen twice decides the next keyframe. One lock guards the map: tracking holds it for each frame, and
while the thread has keyframes it changes nothing in the map but the points' visible / found counters (it waits for the
thread before it adds a keyframe); the mapping thread reads the map without the lock, except those counters, and holds
it while it changes the map. Frame poses are kept relative to their reference keyframe, so corrections made in the
background carry over to tracking. A frame that fails against the local map while the thread still holds keyframes waits
for it and tries again, before relocalisation. Without the thread everything runs inside ``track`` and results are
deterministic. ``timings_s`` sums wall time per stage over both threads.
"""

from __future__ import annotations

import dataclasses
import enum
import logging
import queue
import threading
import time
from contextlib import contextmanager

import numpy as np

from tambridge.camera import Camera
from tambridge.state import attribute_state, restore_attributes
from tambridge.frontend.orb.local_mapping import (
    create_points_from_depth,
    cull_recent_points,
    cull_redundant_keyframes,
    fuse_with_neighbours,
    global_bundle_adjustment,
    local_bundle_adjustment,
)
from tambridge.frontend.orb.loop_closing import LoopConsistency, LoopDetection, close_loop, detect_loop
from tambridge.frontend.orb.depth_time import colour_from_depth_motion, depth_at_colour_time
from tambridge.frontend.orb.dense_depth import DenseReference, DenseTerm, align_depth, dense_reference, dense_samples
from tambridge.frontend.orb.map_matching import PoseFix, localise, match_map_points, refine_with_matches
from tambridge.frontend.orb.matching import build_keypoint_grid
from tambridge.frontend.orb.features import FrameFeatures, OrbExtractor
from tambridge.frontend.orb.pose_estimation import solve_pnp_ransac
from tambridge.rolling_shutter import camera_twist_per_s, keypoints_at_frame_time
from tambridge.frontend.orb.slam_map import Keyframe, SlamMap
from tambridge.frontend.contract import FrontendResult, KeyframeEvent, MapPointObservations, TrackResult, empty_timings
from tambridge.frontend.orb.config import DenseDepthUse, OrbFrontendConfig, for_camera
from tambridge.frontend.orb.vocabulary import KeyframeDatabase, Vocabulary
from tambridge.geometry import interpolate_pose, inverse, poses_along, rotation_angle_deg, rotation_angles_deg
from tambridge.io.tum import Frame
from tambridge.trajectory import Trajectory

logger = logging.getLogger("tambridge.frontend.orb")

MIN_KEYPOINTS_WITH_DEPTH_TO_START = 50
LOST_FRAMES_BEFORE_NEW_SEGMENT = 3
JOIN_KEYFRAMES = 5  # an unjoined segment's newest keyframes tried against the placed map at the end
RELOCALISATION_CANDIDATES = 5
# Refinement from the motion prior is kept when at least this fraction of the matches stay inliers.
PRIOR_MIN_INLIER_FRACTION = 0.5


class KeyframeTrigger(enum.Enum):
    """Why tracking asks for a keyframe (:meth:`OrbFrontend._keyframe_trigger`)."""

    none = "none"
    coverage = "coverage"  # keyframe_min_frames frames since the last keyframe, or many close points untracked
    weak = "weak"  # under a quarter of the reference keyframe's points tracked
    requested = "requested"  # the mapper asked (request_keyframe)


@dataclasses.dataclass
class _FrameRecord:
    """A frame's pose relative to its reference keyframe (or absolute when there is none yet)."""

    frame_index: int
    timestamp_s: float
    reference_keyframe: int
    reference_from_camera: np.ndarray
    tracked: bool
    by_depth: bool = False  # tracked by its depth alone


class OrbFrontend:
    """Streaming ORB RGB-D frontend; see the module docstring and :class:`~tambridge.frontend.contract.Frontend`."""

    def __init__(
        self,
        camera: Camera,
        config: OrbFrontendConfig | None = None,
        world_from_first_camera: np.ndarray | None = None,
    ) -> None:
        self.camera = camera
        # A fresh default each time: the config dataclasses are mutable (``--set`` writes into them).
        self.config = for_camera(config if config is not None else OrbFrontendConfig(), camera)
        self.K = camera.K
        self.map = SlamMap()
        self.extractor = OrbExtractor(camera, self.config)
        self.vocabulary = Vocabulary.load(self.config.vocabulary_path)
        self.database = KeyframeDatabase(self.vocabulary.n_words)
        self.timings_s = empty_timings()
        self.frames_lost = 0
        self.frames_relocalised = 0
        self.loops_closed = 0
        self.keyframes_culled = 0
        self._world_from_first = np.eye(4) if world_from_first_camera is None else np.asarray(world_from_first_camera, float)
        self._records: list[_FrameRecord] = []
        # The last frame's pose, relative to its reference keyframe so that it follows keyframe corrections.
        self._last: _FrameRecord | None = None
        self._motion = np.eye(4)  # current_from_previous camera motion: the constant-velocity prior
        self._reference: Keyframe | None = None
        # The keyframe surface of the dense depth term: the last keyframe's, or after a relocalisation the relocalising
        # keyframe's bundle-adjustment surface until the next keyframe (None with dense_depth off, before the first
        # keyframe, or after a relocalisation with ba_dense_depth off).
        self._dense_reference: DenseReference | None = None
        self.frames_with_dense_depth = 0  # frames whose ORB tracking used the depth term (a retry counts once)
        self._dense_term_this_frame = False
        self._frames_since_keyframe = 0
        self._keyframe_requested = False
        self._lost_streak = 0
        self._segment = -1
        self._keyframes_since_loop = 1 << 30
        self._loop_consistency = LoopConsistency(self.config.loop_consistency)
        self._loop_closed_unreported = False
        self._lock = threading.RLock()
        self._timing_lock = threading.Lock()
        self._jobs: queue.Queue[Keyframe | None] = queue.Queue()
        self._mapping_idle = threading.Condition(self._lock)
        self._keyframe_fused = threading.Event()
        self._keyframe_fused.set()
        self._worker: threading.Thread | None = None
        self._worker_error: BaseException | None = None

    @contextmanager
    def _timed(self, stage: str):
        start = time.perf_counter()
        try:
            yield
        finally:
            with self._timing_lock:
                self.timings_s[stage] += time.perf_counter() - start

    def _camera_from_world_last(self) -> np.ndarray | None:
        last = self._last
        if last is None:
            return None
        if last.reference_keyframe < 0:
            return inverse(last.reference_from_camera)
        reference = self.map.keyframes[last.reference_keyframe]
        return inverse(reference.world_from_camera @ last.reference_from_camera)

    # ------------------------------------------------------------------ per frame
    def extract(self, frame: Frame) -> FrameFeatures:
        """The frame's ORB features, as ``track`` computes them. May run in another thread while ``track`` works
        on an earlier frame (:class:`~tambridge.io.prefetch.FramePrefetcher`), but in one thread at a time (the
        extractor holds one cv2 detector)."""
        with self._timed("features"):
            return self.extractor.extract(frame.rgb, frame.depth_m)

    def track(self, frame: Frame, features: FrameFeatures | None = None) -> TrackResult:
        """Localise one frame (frames must come in order); see :class:`~tambridge.frontend.contract.TrackResult`.

        ``features``: the frame's :meth:`extract`, computed ahead (the same result); None extracts them here.
        """
        if features is None:
            features = self.extract(frame)
        self._keyframe_fused.wait()
        self._raise_worker_error()  # after the wait: a fusion that failed is raised by the frame that waited for it
        with self._lock:
            self._dense_term_this_frame = False
            result = self._track_features(frame, features)
            self.frames_with_dense_depth += self._dense_term_this_frame
            if self._loop_closed_unreported:
                result.loop_closed, self._loop_closed_unreported = True, False
            return result

    def _track_features(self, frame: Frame, features: FrameFeatures) -> TrackResult:
        if self._reference is None:
            started = self._start_segment(frame, features)
            return started if started is not None else self._lost(frame, features, "no map to track against")
        camera_from_world_last, predicted = self._prior()
        frame, features = self._depth_at_colour_time(frame, features)
        grid = build_keypoint_grid(features.keypoints_px, self.camera.width, self.camera.height)
        radius_scale = 2.0 if self._lost_streak else 1.0
        fix, in_view, dense = self._track_local_map(features, grid, predicted, radius_scale, frame.depth_m)
        if not self._placed_by(fix) and self._jobs.unfinished_tasks and len(features) >= self.config.min_inliers // 2:
            # The mapping thread still holds keyframes: the local map without their point fusion and local BA is not
            # the one an inline run tracks against. Where that map fails, wait for the thread and try its map again.
            self._wait_for_mapping()
            self._raise_worker_error()
            camera_from_world_last, predicted = self._prior()
            fix, in_view, dense = self._track_local_map(features, grid, predicted, radius_scale, frame.depth_m)
        relocalised = False
        if not self._placed_by(fix):
            relocalisation = self._relocalise(features, grid, frame.depth_m)
            if relocalisation is None:
                by_depth = self._track_by_depth(frame, predicted, camera_from_world_last)
                if by_depth is not None:
                    return by_depth
                if self._lost_streak >= LOST_FRAMES_BEFORE_NEW_SEGMENT:
                    started = self._start_segment(frame, features)
                    if started is not None:
                        return started
                inliers = 0 if fix is None else fix.inlier_count
                return self._lost(frame, features, f"{inliers} inliers, relocalisation failed")
            fix, in_view = relocalisation
            relocalised = True
        if self._lost_streak or relocalised:
            self.frames_relocalised += 1
            logger.info("frame %d (t=%.6f): tracking recovered after %d lost frame(s), %d inliers%s",
                        frame.index, frame.timestamp_s, self._lost_streak, fix.inlier_count,
                        " (relocalised against keyframes)" if relocalised else "")
        if relocalised:
            # The jump to a relocalised pose is no velocity (ORB-SLAM clears its motion model here too).
            self._motion = np.eye(4)
            if self._reference.segment != self._segment:
                # Placed in an earlier segment's map: the frame is in that segment's world, and so are the keyframes it
                # makes (local BA, point fusion and the choice of reference keyframe work within one segment).
                logger.info("frame %d (t=%.6f): back in map segment %d (relocalised against keyframe %d)",
                            frame.index, frame.timestamp_s, self._reference.segment, self._reference.id)
                self._segment = self._reference.segment
        elif not self._lost_streak:
            # After lost frames the last pose was a prediction: keep the velocity from before the loss.
            features, fix = self._refined_at_frame_time(frame, features, fix, camera_from_world_last, dense)
            self._motion = fix.camera_from_world @ inverse(camera_from_world_last)
        self._lost_streak = 0
        points = self.map.points
        points.visible[in_view] += 1
        points.found[fix.point_ids] += 1
        self._reference = self._best_reference(fix)
        self._frames_since_keyframe += 1
        keyframe_event = None
        camera_from_world = fix.camera_from_world
        trigger = self._keyframe_trigger(features, fix)
        # Only coverage gives way to a revisit: weak tracking and the mapper's requests still make keyframes.
        revisited = trigger is KeyframeTrigger.coverage and self._revisited_keyframe(fix.camera_from_world) is not None
        if trigger is not KeyframeTrigger.none and not revisited:
            self._wait_for_mapping()
            keyframe = self._insert_keyframe(frame, features, fix)
            keyframe_event = self._keyframe_event(keyframe)
            camera_from_world = keyframe.camera_from_world  # after local BA when mapping runs inline
        self._record(frame, camera_from_world, tracked=True)
        return TrackResult(
            frame_index=frame.index,
            timestamp_s=frame.timestamp_s,
            world_from_camera=inverse(camera_from_world),
            tracked=True,
            is_keyframe=keyframe_event is not None,
            inlier_count=fix.inlier_count,
            relocalised=relocalised,
            keyframe=keyframe_event,
        )

    def _prior(self) -> tuple[np.ndarray, np.ndarray]:
        """``(camera_from_world_last, predicted)``: the last frame's pose and the constant-velocity prediction from it,
        with the map as it is now. A reference keyframe the mapping thread culled since the last frame is first
        replaced by its parent."""
        if self._reference.culled:
            self._reference = self.map.keyframes[self._reference.parent]
        camera_from_world_last = self._camera_from_world_last()
        return camera_from_world_last, self._motion @ camera_from_world_last

    def _placed_by(self, fix: PoseFix | None) -> bool:
        """The local map's fix has the inliers of a tracked frame (``min_inliers``)."""
        return fix is not None and fix.inlier_count >= self.config.min_inliers

    @property
    def _velocity_measured(self) -> bool:
        """The constant-velocity prior is a measured motion, not the identity a relocalisation or a new segment
        leaves."""
        return not np.array_equal(self._motion, np.eye(4))

    def _depth_at_colour_time(self, frame: Frame, features: FrameFeatures) -> tuple[Frame, FrameFeatures]:
        """The frame and its features with the depth moved to the colour time (``depth_time_compensation``) by the
        motion prior, the camera's motion from the last frame to this one; as given where the depth has no time of
        its own or the prior is still."""
        delay_s, interval_s = frame.depth_delay_s, frame.timestamp_s - self._last.timestamp_s
        if (not self.config.depth_time_compensation or delay_s == 0.0 or not interval_s > 0.0
                or not self._velocity_measured):
            return frame, features
        with self._timed("features"):
            colour_from_depth = colour_from_depth_motion(self._motion, interval_s, delay_s)
            depth_m = depth_at_colour_time(frame.depth_m, self.K, colour_from_depth)
            moved = self.extractor.lift(features.keypoints_px, features.octaves, features.descriptors, frame.rgb, depth_m)
        return dataclasses.replace(frame, depth_m=depth_m, depth_timestamp_s=None), moved

    def _refined_at_frame_time(self, frame: Frame, features: FrameFeatures, fix: PoseFix,
                               camera_from_world_last: np.ndarray, dense: DenseTerm | None) -> tuple[FrameFeatures, PoseFix]:
        """With a rolling shutter (``rolling_shutter_s``), the keypoints moved from their rows' times to the frame's
        (:mod:`~tambridge.rolling_shutter`) by the frame's own motion from the last frame to ``fix``,
        their depth and colour read again there, and the pose refined once more from ``fix`` on its inliers (with
        the same ``dense`` term). As given with a global shutter or a still camera."""
        current_from_last = fix.camera_from_world @ inverse(camera_from_world_last)
        readout_s, interval_s = self.config.rolling_shutter_s, frame.timestamp_s - self._last.timestamp_s
        if readout_s == 0.0 or not interval_s > 0.0 or np.array_equal(current_from_last, np.eye(4)):
            return features, fix
        with self._timed("features"):
            twist = camera_twist_per_s(current_from_last, interval_s)
            moved = keypoints_at_frame_time(features.keypoints_px, features.depth_m, self.camera, twist, readout_s)
            moved = self.extractor.lift(moved, features.octaves, features.descriptors, frame.rgb, frame.depth_m)
        with self._timed("pnp"):
            return moved, refine_with_matches(fix.camera_from_world, moved, fix.keypoint_indices, fix.point_ids,
                                              self.map, self.K, self.config, dense)

    def _dense_term(self, depth_m: np.ndarray, matches: int) -> DenseTerm | None:
        """The point-to-plane depth term against the keyframe surface (``_dense_reference``), where ``dense_depth``
        asks for it (auto: fewer than ``dense_auto_max_matches`` matches or a motion prior turning fast); else None."""
        config = self.config
        if config.dense_depth == DenseDepthUse.never or self._dense_reference is None:
            return None
        if config.dense_depth == DenseDepthUse.auto:
            if matches >= config.dense_auto_max_matches and rotation_angle_deg(self._motion) <= config.dense_auto_min_rotation_deg:
                return None
        self._dense_term_this_frame = True
        return self._dense_term_of(depth_m)

    def _dense_term_of(self, depth_m: np.ndarray) -> DenseTerm:
        """The depth term of ``depth_m`` (H, W) against the keyframe surface (there must be one)."""
        config = self.config
        reference = self._dense_reference
        with self._timed("pnp"):
            samples = dense_samples(depth_m, self.K, config.dense_sample_stride_px, config.min_depth_m, config.max_depth_m)
        return DenseTerm(reference, self.map.keyframes[reference.keyframe_id].camera_from_world, samples, self.K,
                         config.dense_depth_weight, config.dense_depth_noise_per_m, config.dense_depth_huber_sigmas,
                         config.dense_depth_max_distance_m)

    def _track_by_depth(self, frame: Frame, predicted: np.ndarray, camera_from_world_last: np.ndarray) -> TrackResult | None:
        """The frame tracked by the depth term alone (:func:`align_depth` from the motion prior ``predicted``) against
        the keyframe surface (``_dense_reference``), where ORB could not place it and ``depth_only_tracking`` allows:
        right after a tracked frame with a measured velocity (the prior is a tracked pose moved by a tracked
        motion; not after a relocalisation, which clears the velocity), and only where the pose found keeps
        ``depth_only_min_share`` of the frame's depth on the surface and the surface holds every motion
        (``depth_only_min_conditioning``); else None. Such a frame brings no map points, so it never becomes a
        keyframe."""
        config = self.config
        # No keyframe depth is kept with dense_depth never: the reference is None then. A motion prior cleared by a
        # relocalisation is the last pose itself: for a moving camera that can lie outside the term's basin, where a
        # surface such as a desk lets it slide into a wrong pose that still fits.
        if (not config.depth_only_tracking or self._dense_reference is None or self._lost_streak
                or not self._velocity_measured):
            return None
        term = self._dense_term_of(frame.depth_m)
        if len(term.samples_camera_m) == 0:
            return None
        with self._timed("pnp"):
            alignment = align_depth(predicted, term)
        if alignment.associated_share < config.depth_only_min_share or alignment.conditioning < config.depth_only_min_conditioning:
            return None
        logger.info("frame %d (t=%.6f): tracked by its depth alone (too few ORB matches; %.0f %% of its depth on the "
                    "keyframe's surface)", frame.index, frame.timestamp_s, 100 * alignment.associated_share)
        self._motion = alignment.camera_from_world @ inverse(camera_from_world_last)
        self._frames_since_keyframe += 1
        self._record(frame, alignment.camera_from_world, tracked=True, by_depth=True)
        return TrackResult(frame_index=frame.index, timestamp_s=frame.timestamp_s,
                           world_from_camera=inverse(alignment.camera_from_world), tracked=True, is_keyframe=False,
                           inlier_count=0, relocalised=False, keyframe=None)

    def _track_local_map(
        self, features: FrameFeatures, grid, predicted: np.ndarray, radius_scale: float, depth_m: np.ndarray,
    ) -> tuple[PoseFix | None, np.ndarray, DenseTerm | None]:
        """Two projection searches of the local map (wide with the prior, tight with the refined pose), each
        followed by motion-only refinement (with the dense depth term of ``depth_m`` where it is used)."""
        config = self.config
        local = self.map.local_keyframes(self._reference, config.local_map_keyframes)
        point_ids = self.map.points_of(local)
        with self._timed("matching"):
            keypoints, ids, _ = match_map_points(self.map, point_ids, predicted, features, grid, self.camera, config,
                                                 radius_scale * config.search_radius_px)
        if len(ids) < config.min_inliers // 2:
            return None, np.zeros(0, np.int64), None
        dense = self._dense_term(depth_m, len(ids))
        with self._timed("pnp"):
            # As ORB-SLAM's TrackWithMotionModel: refine from the prior; PnP-RANSAC (about a third of the
            # tracking time) only when the prior leaves too many matches as outliers.
            fix = refine_with_matches(predicted, features, keypoints, ids, self.map, self.K, config, dense)
            if fix.inlier_count < max(config.min_inliers, PRIOR_MIN_INLIER_FRACTION * len(ids)):
                camera_from_world, _ = solve_pnp_ransac(self.map.points.positions_m[ids], features.keypoints_px[keypoints],
                                                        self.K, predicted, config.pnp_reprojection_px, config.pnp_iterations)
                if camera_from_world is not None:
                    ransac_fix = refine_with_matches(camera_from_world, features, keypoints, ids, self.map, self.K, config,
                                                     dense)
                    fix = ransac_fix if ransac_fix.inlier_count > fix.inlier_count else fix
        with self._timed("matching"):
            keypoints, ids, in_view = match_map_points(self.map, point_ids, fix.camera_from_world, features, grid,
                                                       self.camera, config, config.refine_radius_px)
        if len(ids) < config.min_inliers // 2:
            return fix, in_view, dense
        with self._timed("pnp"):
            refined = refine_with_matches(fix.camera_from_world, features, keypoints, ids, self.map, self.K, config, dense)
        return refined, in_view, dense

    def _relocalise(self, features: FrameFeatures, grid, depth_m: np.ndarray) -> tuple[PoseFix, np.ndarray] | None:
        """Bag-of-words candidates, each verified by :func:`localise`; then the local map around the winner, with the
        dense depth term of ``depth_m`` (H, W) metres as in tracking. Candidates are keyframes of the current
        segment or of one in the first keyframe's world: a segment that began at a predicted pose and was never
        joined would move tracking into that prediction's error."""
        if len(features) < self.config.relocalisation_min_inliers:
            return None
        with self._timed("loop"):
            words, weights = self.vocabulary.transform(features.descriptors)
            candidates, _ = self.database.query(words, weights)
            reachable = self._placed_segments() | {self._segment}
            candidates = [int(i) for i in candidates if self.map.keyframes[int(i)].segment in reachable]
        with self._timed("pnp"):
            for keyframe_id in candidates[:RELOCALISATION_CANDIDATES]:
                keyframe = self.map.keyframes[keyframe_id]
                group = [keyframe] + [self.map.keyframes[i] for i in keyframe.best_covisible(5)]
                fix = localise(self.map, features, grid, self.map.points_of(group), self.camera, self.config,
                               self.config.relocalisation_min_inliers, self.config.relocalisation_ransac_min_inliers)
                if fix is not None:
                    self._reference = keyframe
                    if self.config.dense_depth != DenseDepthUse.never:
                        # The last keyframe's surface would pull the frame towards where that keyframe is, which after a
                        # loss may be another place or a segment's guessed pose; this keyframe's is where the frame is.
                        self._dense_reference = keyframe.depth_reference
                    tracked, in_view, _ = self._track_local_map(features, grid, fix.camera_from_world, 1.0, depth_m)
                    if tracked is not None and tracked.inlier_count >= fix.inlier_count:
                        return tracked, in_view
                    return fix, np.zeros(0, np.int64)
        return None

    def _join_unplaced_segments(self) -> None:
        """At the end of the run, every map segment not in the first keyframe's world tries once more to join it: its
        newest live keyframes (at most ``JOIN_KEYFRAMES``) are localised against every point of the placed segments
        with relocalisation's two bars (:func:`localise`), and the first that localises closes a loop to the placed
        keyframe that sees most of its inliers. During the run a segment meets the placed map only through the
        keyframe database's few candidates and consecutive-query checks; the whole map often has the place from
        another view. A segment that joins is moved into the first keyframe's world (pose graph, then global BA),
        its frames with it. One pass, in segment order: a segment that could only localise against one joined after
        it stays unjoined."""
        config = self.config
        if not config.loop_closure:
            return
        for segment in sorted({k.segment for k in self.map.keyframes} - self._placed_segments()):
            placed = self._placed_segments()
            if segment in placed:
                continue
            placed_keyframes = [k for k in self.map.keyframes if k.segment in placed and not k.culled]
            point_ids = self.map.points_of(placed_keyframes)
            tried = [k for k in reversed(self.map.keyframes) if k.segment == segment and not k.culled][:JOIN_KEYFRAMES]
            with self._timed("loop"):
                for keyframe in tried:
                    fix = localise(self.map, keyframe.features, keyframe.keypoint_grid, point_ids, self.camera, config,
                                   config.relocalisation_min_inliers, config.relocalisation_ransac_min_inliers)
                    if fix is None:
                        continue
                    seen = [int(np.isin(fix.point_ids, k.point_ids).sum()) for k in placed_keyframes]
                    candidate = placed_keyframes[int(np.argmax(seen))]
                    close_loop(self.map, keyframe, LoopDetection(candidate.id, fix), self.camera, config)
                    self.loops_closed += 1
                    logger.info("map segment %d joined to the first keyframe's world at the end: keyframe %d (frame %d) "
                                "localised against keyframe %d (frame %d), %d inliers", segment, keyframe.id,
                                keyframe.frame_index, candidate.id, candidate.frame_index, fix.inlier_count)
                    break

    def _frame_poses(self) -> np.ndarray:
        """(N, 4, 4) world_from_camera of every frame so far, from its reference keyframe's pose now."""
        keyframes = self.map.keyframes
        poses = [r.reference_from_camera if r.reference_keyframe < 0
                 else keyframes[r.reference_keyframe].world_from_camera @ r.reference_from_camera
                 for r in self._records]
        return np.stack(poses) if poses else np.zeros((0, 4, 4))

    def _place_unjoined_segments(self) -> None:
        """Move each map segment that nothing joined to the first keyframe's world, and that tracking left for frames
        of that world, to where the frames around it put it. Its start is the constant-velocity guess across the
        loss before it; the placed frames after it give a second guess of where its last frame is, continued back
        from their own motion. The segment moves rigidly (its keyframes, their points and frames, keeping the
        motion tracked inside it) to the mean of the two, each weighted by how close in time its guess was
        (the guess over the shorter gap is the better one). A segment without two placed frames before it and two
        after it keeps its start's guess."""
        placed = self._placed_segments()
        keyframes = self.map.keyframes
        records = self._records
        first_keyframes: dict[int, int] = {}
        for keyframe in keyframes:
            first_keyframes.setdefault(keyframe.segment, keyframe.frame_index)
        segment_starts = set(first_keyframes.values())
        segment_of = np.array([keyframes[r.reference_keyframe].segment if r.reference_keyframe >= 0 else -1
                               for r in records])
        localised = np.array([r.tracked or r.frame_index in segment_starts for r in records], bool)
        times_s = np.array([r.timestamp_s for r in records])
        anchors = np.flatnonzero(localised & np.isin(segment_of, sorted(placed)))
        poses = self._frame_poses()  # the placed frames' poses stay; each segment's own are read before it moves
        for segment in sorted(set(segment_of[localised]) - placed - {-1}):
            inside = np.flatnonzero(localised & (segment_of == segment))
            first, last = inside[0], inside[-1]
            before, after = anchors[anchors < first][-2:], anchors[anchors > last][:2]
            if len(before) < 2 or len(after) < 2:
                continue
            from_before = poses_along(times_s[before], poses[before], times_s[[first]])[0] @ inverse(poses[first])
            from_after = poses_along(times_s[after], poses[after], times_s[[last]])[0] @ inverse(poses[last])
            gap_before_s, gap_after_s = times_s[first] - times_s[before[-1]], times_s[after[0]] - times_s[last]
            world_from_segment = interpolate_pose(from_before, from_after, gap_before_s / (gap_before_s + gap_after_s))
            keyframe_poses_before = np.stack([k.world_from_camera for k in keyframes])
            for keyframe in keyframes:
                if keyframe.segment == segment:
                    keyframe.world_from_camera = world_from_segment @ keyframe.world_from_camera
            self.map.move_points_with_keyframes(keyframe_poses_before)
            moved_m = np.linalg.norm((world_from_segment @ poses[first])[:3, 3] - poses[first][:3, 3])
            logger.info("map segment %d (frames %d-%d), which no loop joined, placed between the frames around it: "
                        "its first frame moved %.3f m", segment, records[first].frame_index, records[last].frame_index,
                        moved_m)

    def _placed_segments(self) -> set[int]:
        """The map segments in the first keyframe's world: its own, and those a loop edge ties to a placed one. The
        others began at a predicted pose and were never joined: their poses keep that prediction's error (until
        :meth:`_place_unjoined_segments` at the end)."""
        keyframes = self.map.keyframes
        placed = {keyframes[0].segment} if keyframes else set()
        ties = [(keyframes[a].segment, keyframes[b].segment) for a, b, _ in self.map.loop_edges]
        grown = True
        while grown:
            grown = False
            for a, b in ties:
                if (a in placed) != (b in placed):
                    placed |= {a, b}
                    grown = True
        return placed

    def _lost(self, frame: Frame, features: FrameFeatures, reason: str) -> TrackResult:
        """Count and report a frame that could not be localised; its pose is the constant-velocity prediction (before
        any map, the pose the first map will start at)."""
        self.frames_lost += 1
        self._lost_streak += 1
        camera_from_world_last = self._camera_from_world_last()
        if camera_from_world_last is None:
            predicted = inverse(self._world_from_first)
        else:
            predicted = self._motion @ camera_from_world_last
        logger.warning(
            "frame %d (t=%.6f): tracking lost (%s; %d keypoints); its pose is %s%s",
            frame.index, frame.timestamp_s, reason, len(features),
            # Before the first map there is nothing to predict from: the frame that starts the map has this pose too.
            "the first map's origin" if camera_from_world_last is None else "the constant-velocity prediction",
            "; a new map segment starts at the next frame with depth" if self._lost_streak >= LOST_FRAMES_BEFORE_NEW_SEGMENT else "",
        )
        self._record(frame, predicted, tracked=False)
        return TrackResult(frame.index, frame.timestamp_s, inverse(predicted), tracked=False, is_keyframe=False, inlier_count=0)

    def _start_segment(self, frame: Frame, features: FrameFeatures) -> TrackResult | None:
        """First keyframe of a map segment from the frame's depth (None if it has too little depth)."""
        if int(features.has_depth.sum()) < MIN_KEYPOINTS_WITH_DEPTH_TO_START:
            return None
        # The keyframe changes the map, which the mapping thread reads without the lock: wait for it first.
        self._wait_for_mapping()
        previous = self.map.keyframes[-1] if self.map.keyframes else None
        camera_from_world_last = self._camera_from_world_last()
        if camera_from_world_last is None:
            camera_from_world = inverse(self._world_from_first)
        else:
            camera_from_world = self._motion @ camera_from_world_last
        self._segment = 1 + max((k.segment for k in self.map.keyframes), default=-1)
        fix = PoseFix(camera_from_world, np.zeros(0, np.int64), np.zeros(0, np.int64))
        keyframe = self._insert_keyframe(frame, features, fix, run_mapping=False)
        if previous is not None:
            self.map.segment_links.append((previous.id, keyframe.id, camera_from_world @ previous.world_from_camera))
            logger.warning(
                "frame %d (t=%.6f): starting map segment %d at the predicted pose after %d lost frames; "
                "it joins the earlier map at the next loop closure",
                frame.index, frame.timestamp_s, self._segment, self._lost_streak,
            )
        self._lost_streak = 0
        self._motion = np.eye(4)
        self._record(frame, camera_from_world, tracked=previous is None)
        return TrackResult(frame.index, frame.timestamp_s, inverse(camera_from_world), tracked=previous is None,
                           is_keyframe=True, inlier_count=0, keyframe=self._keyframe_event(keyframe))

    # ------------------------------------------------------------------ keyframes
    def _best_reference(self, fix: PoseFix) -> Keyframe:
        """The keyframe whose points the frame matched most (ORB-SLAM's reference keyframe)."""
        if fix.inlier_count == 0:
            return self._reference
        votes = np.bincount(self.map.points.reference_keyframe[fix.point_ids])
        best = self.map.keyframes[int(np.argmax(votes))]
        return best if best.segment == self._segment else self._reference

    def _keyframe_trigger(self, features: FrameFeatures, fix: PoseFix) -> KeyframeTrigger:
        """ORB-SLAM2's NeedNewKeyFrame for RGB-D, without its dependence on whether local mapping is idle (see
        the module docstring): enough frames since the last keyframe, many close points untracked or weak tracking,
        and fewer points tracked than ``keyframe_tracked_ratio`` of the reference keyframe's (or many close points
        untracked); then why (:class:`KeyframeTrigger`)."""
        config = self.config
        points = self.map.points
        reference_ids = self.map.good_point_ids(self._reference)
        # ORB-SLAM counts an observation with depth twice and asks for 3 (2 with few keyframes): 2 keyframes (1).
        min_observations = 2 if len(self.map.keyframes) > 2 else 1
        reference_tracked = int((points.observations[reference_ids] >= min_observations).sum())
        matched = np.zeros(len(features), bool)
        matched[fix.keypoint_indices] = True
        close = features.has_depth & (features.depth_m < config.close_depth_m)
        need_close = (int((close & matched).sum()) < config.keyframe_close_tracked
                      and int((close & ~matched).sum()) > config.keyframe_close_untracked)
        ratio = 0.4 if len(self.map.keyframes) < 2 else config.keyframe_tracked_ratio
        inliers = fix.inlier_count
        c1b = self._frames_since_keyframe >= config.keyframe_min_frames
        weak = inliers < 0.25 * reference_tracked  # with need_close, ORB-SLAM's c1c
        c2 = (inliers < ratio * reference_tracked or need_close) and inliers > 15
        # A keyframe asked for by the mapper (request_keyframe) needs c2's inlier floor only.
        if self._keyframe_requested and inliers > 15:
            return KeyframeTrigger.requested
        if not c2:
            return KeyframeTrigger.none
        if weak:
            return KeyframeTrigger.weak
        return KeyframeTrigger.coverage if c1b or need_close else KeyframeTrigger.none

    def _revisited_keyframe(self, camera_from_world: np.ndarray) -> Keyframe | None:
        """The nearest live keyframe of the frame's map segment within ``keyframe_revisit_distance_m`` and
        ``keyframe_revisit_angle_deg`` of the pose ``camera_from_world`` (4, 4), where a keyframe would repeat it;
        None where there is none or the rule is off. All of the segment's keyframes, not the local map's: on a
        revisit the nearest is often not covisible with the reference keyframe."""
        config = self.config
        if config.keyframe_revisit_distance_m <= 0:
            return None
        candidates = [k for k in self.map.keyframes if not k.culled and k.segment == self._segment]
        camera_from_keyframes = camera_from_world @ np.stack([k.world_from_camera for k in candidates])
        distances_m = np.linalg.norm(camera_from_keyframes[:, :3, 3], axis=1)
        angles_deg = rotation_angles_deg(camera_from_keyframes)
        near = (distances_m <= config.keyframe_revisit_distance_m) & (angles_deg <= config.keyframe_revisit_angle_deg)
        if not near.any():
            return None
        return candidates[int(np.flatnonzero(near)[np.argmin(distances_m[near])])]

    def _insert_keyframe(self, frame: Frame, features: FrameFeatures, fix: PoseFix, run_mapping: bool = True) -> Keyframe:
        """Make the frame a keyframe with its tracked points and new points from depth, then hand it to local
        mapping (the thread, or inline). Called with the map lock held."""
        keyframe = Keyframe(
            id=len(self.map.keyframes),
            frame_index=frame.index,
            timestamp_s=frame.timestamp_s,
            world_from_camera=inverse(fix.camera_from_world),
            features=features,
            point_ids=np.full(len(features), -1, np.int64),
            segment=self._segment,
            keypoint_grid=build_keypoint_grid(features.keypoints_px, self.camera.width, self.camera.height),
        )
        # Matched points may have gone bad (culled or merged) while tracking waited for the mapping thread.
        good = self.map.points.good(fix.point_ids)
        keyframe.point_ids[fix.keypoint_indices[good]] = fix.point_ids[good]
        self.map.keyframes.append(keyframe)
        self.map.points.observations[fix.point_ids[good]] += 1
        create_points_from_depth(self.map, keyframe, self.config)
        if self.config.dense_depth != DenseDepthUse.never:
            with self._timed("pnp"):
                self._dense_reference = dense_reference(keyframe.id, frame.depth_m, self.K, self.config.dense_reference_stride_px,
                                                        self.config.min_depth_m, self.config.max_depth_m)
        if self.config.ba_dense_depth:
            with self._timed("pnp"):
                config = self.config
                keyframe.depth_reference = dense_reference(keyframe.id, frame.depth_m, self.K,
                                                           config.ba_dense_reference_stride_px, config.min_depth_m,
                                                           config.max_depth_m)
                keyframe.depth_samples_m = dense_samples(frame.depth_m, self.K, config.dense_sample_stride_px,
                                                         config.min_depth_m, config.max_depth_m)
        self.map.update_covisibility([keyframe], self.config.covisibility_min_shared)
        self._reference = keyframe
        self._frames_since_keyframe = 0
        self._keyframe_requested = False
        if not self.config.mapping_thread:
            self._map_keyframe(keyframe, run_mapping)
        elif run_mapping:
            self._start_worker()
            self._keyframe_fused.clear()
            self._jobs.put(keyframe)
        else:
            self._map_keyframe(keyframe, run_mapping=False)
        return keyframe

    def _map_keyframe(self, keyframe: Keyframe, run_mapping: bool = True) -> None:
        """Local mapping and loop closing for a new keyframe (ORB-SLAM's LocalMapping and LoopClosing)."""
        config = self.config
        with self._timed("loop"):
            words, weights = self.vocabulary.transform(keyframe.features.descriptors)
        with self._lock:
            keyframe.bow_words, keyframe.bow_weights = words, weights
        if run_mapping:
            # Tracking, the one other thread, holds the lock for each frame and, while keyframes are mapped, changes
            # only the points' visible / found counters (it waits for this thread before it adds a keyframe): so
            # this thread reads the map without the lock, those counters apart (culling reads them), and takes it
            # for its changes, and tracking goes on meanwhile.
            with self._lock:
                cull_recent_points(self.map, keyframe)
            with self._timed("matching"):
                fuse_with_neighbours(self.map, keyframe, self.camera, config, self._lock)
            self._keyframe_fused.set()
            with self._timed("local_ba"):
                local_bundle_adjustment(self.map, keyframe, self.K, config, self._lock)
            if config.keyframe_culling:
                with self._timed("local_ba"), self._lock:
                    culled = cull_redundant_keyframes(self.map, keyframe, config)
                    for keyframe_id in culled:
                        self.database.redirect(keyframe_id, self.map.keyframes[keyframe_id].parent)
                    self.keyframes_culled += len(culled)
            if config.loop_closure and self._keyframes_since_loop >= config.loop_cooldown_keyframes:
                with self._timed("loop"):
                    loop = detect_loop(self.map, keyframe, self.database, self.camera, config, self._loop_consistency)
                if loop is not None:
                    with self._timed("loop"), self._lock:
                        close_loop(self.map, keyframe, loop, self.camera, config)
                        self.loops_closed += 1
                        self._keyframes_since_loop = 0
                        self._loop_closed_unreported = True
        with self._timed("loop"), self._lock:
            self._keyframes_since_loop += 1
            self.database.add(keyframe.id, keyframe.bow_words, keyframe.bow_weights)

    def _start_worker(self) -> None:
        if self._worker is None:
            self._worker = threading.Thread(target=self._work, name="tambridge-local-mapping", daemon=True)
            self._worker.start()

    def _work(self) -> None:
        while True:
            keyframe = self._jobs.get()
            try:
                if keyframe is None:
                    return
                if self._worker_error is None:
                    self._map_keyframe(keyframe)
            except BaseException as error:  # noqa: BLE001 - re-raised in the caller's thread by _raise_worker_error
                self._worker_error = error
            finally:
                self._keyframe_fused.set()  # also where the keyframe failed: the next frame raises its error
                self._jobs.task_done()
                with self._mapping_idle:
                    self._mapping_idle.notify_all()

    def _wait_for_mapping(self) -> None:
        """Block until the mapping thread has finished its keyframes; the map lock is released meanwhile (the
        condition's wait releases the re-entrant lock fully), so the thread can finish."""
        if self._worker is not None:
            self._mapping_idle.wait_for(lambda: self._jobs.unfinished_tasks == 0)

    def _raise_worker_error(self) -> None:
        if self._worker_error is not None:
            raise RuntimeError("the ORB frontend's mapping thread failed") from self._worker_error

    def _keyframe_event(self, keyframe: Keyframe) -> KeyframeEvent:
        """What the Fusion Bridge gets: the view-selection counts over all the keyframe's map points, and for the
        reprojection term only the points that earlier keyframes made. A point lifted from this keyframe's own
        keypoint sits exactly on its ray: its reprojection error is zero at the frontend pose and its gradient
        undefined there, and with hundreds of them the refinement could not move the pose at all."""
        good = self.map.points.good(keyframe.point_ids)
        ids = keyframe.point_ids[good]
        shared, previous_total = 0, 0
        if keyframe.id > 0:
            previous_ids = self.map.good_point_ids(self.map.keyframes[keyframe.id - 1])
            shared = int(np.intersect1d(ids, previous_ids).size)
            previous_total = int(previous_ids.size)
        made_earlier = self.map.points.first_keyframe[ids] != keyframe.id
        return KeyframeEvent(
            keyframe_id=keyframe.id,
            frame_index=keyframe.frame_index,
            timestamp_s=keyframe.timestamp_s,
            world_from_camera=keyframe.world_from_camera.copy(),
            points_world_m=self.map.points.positions_m[ids[made_earlier]].copy(),
            keypoints_px=keyframe.features.keypoints_px[good][made_earlier].copy(),
            map_point_ids=ids[made_earlier].astype(np.int64),
            shared_with_previous=shared,
            previous_total=previous_total,
        )

    def _record(self, frame: Frame, camera_from_world: np.ndarray, tracked: bool, by_depth: bool = False) -> None:
        reference = self._reference
        if reference is None:
            record = _FrameRecord(frame.index, frame.timestamp_s, -1, inverse(camera_from_world), tracked, by_depth)
        else:
            record = _FrameRecord(frame.index, frame.timestamp_s, reference.id,
                                  reference.camera_from_world @ inverse(camera_from_world), tracked, by_depth)
        self._records.append(record)
        self._last = record

    def request_keyframe(self) -> None:
        """Make the next frame a keyframe if it is tracked (by more than 15 inliers, as every keyframe)."""
        self._keyframe_requested = True

    # ------------------------------------------------------------------ results
    def keyframe_poses(self) -> dict[int, np.ndarray]:
        """Keyframe id -> ``world_from_camera`` (4, 4) after every correction so far, for every keyframe announced
        (culled ones at their parent's pose times their relative pose)."""
        with self._lock:
            return {k.id: k.world_from_camera.copy() for k in self.map.keyframes}

    def finish(self) -> FrontendResult:
        """Wait for local mapping, try to join unjoined map segments, run global BA (if configured), place the segments
        still unjoined, return the final trajectories; call once."""
        if self._worker is not None:
            self._jobs.join()
            self._jobs.put(None)
            self._worker.join()
            self._worker = None
        self._raise_worker_error()
        self._join_unplaced_segments()
        if self.config.global_ba and len(self.map.keyframes) > 1:
            with self._timed("global_ba"):
                global_bundle_adjustment(self.map, self.K, self.config)
        self._place_unjoined_segments()
        keyframes = self.map.keyframes
        trajectory = Trajectory(np.array([r.timestamp_s for r in self._records]), self._frame_poses())
        # A lost frame's pose was predicted from the frames before it alone; the frames after it place it better. The
        # first keyframe of a segment that no loop joined was such a prediction too (its keyframe pose keeps the
        # segment's placement); a joined one has its pose from the map. Frames tracked in an unjoined segment move
        # with it (_place_unjoined_segments).
        placed = self._placed_segments()
        placed_keyframe_frames = {k.frame_index for k in keyframes if k.segment in placed}
        trajectory = trajectory.bridged(np.array([r.tracked or r.frame_index in placed_keyframe_frames
                                                  for r in self._records], bool))
        points = self.map.points
        good = np.flatnonzero(~points.bad[: points.count] & (points.observations[: points.count] > 0))
        return FrontendResult(
            trajectory=trajectory,
            tracked=np.array([r.tracked for r in self._records], bool),
            keyframe_trajectory=Trajectory(np.array([k.timestamp_s for k in keyframes]),
                                           np.stack([k.world_from_camera for k in keyframes]) if keyframes else np.zeros((0, 4, 4))),
            keyframe_poses=self.keyframe_poses(),
            keyframe_frame_indices={k.id: k.frame_index for k in keyframes},
            map_points_world_m=points.positions_m[good].copy(),
            map_point_colours=points.colours[good].copy(),
            map_point_ids=good,
            timings_s=dict(self.timings_s),
            frames_lost=self.frames_lost,
            frames_relocalised=self.frames_relocalised,
            tracked_by_depth=np.array([r.by_depth for r in self._records], bool),
            loops_closed=self.loops_closed,
            keyframes_culled=self.keyframes_culled,
            map_point_observations=map_point_observations(self.map, good),
        )

    # ------------------------------------------------------------------ checkpoints
    _TRANSIENT = ("camera", "config", "K", "extractor", "vocabulary", "_lock", "_timing_lock", "_mapping_idle",
                  "_keyframe_fused", "_jobs", "_worker", "_worker_error")
    """Attributes a checkpoint leaves out: given to or rebuilt by the constructor, or threads and locks."""

    def state_dict(self) -> dict:
        """Everything a resumed run needs (sparse map, keyframe database, motion model, frame records, counters),
        once the mapping thread has finished its queued keyframes. The values are the frontend's own objects:
        encode them (:func:`~tambridge.checkpoint.save_checkpoint`) before the next ``track``."""
        self._jobs.join()
        self._raise_worker_error()
        with self._lock:
            return attribute_state(self, self._TRANSIENT)

    def load_state_dict(self, state: dict) -> None:
        """Continue from :meth:`state_dict` (on a frontend built with the same camera and config)."""
        restore_attributes(self, state)


def map_point_observations(slam_map: SlamMap, point_ids: np.ndarray) -> MapPointObservations:
    """The observations of map points ``point_ids`` (P,) in the keyframes, their rows being positions in ``point_ids``."""
    selected = np.zeros(slam_map.points.count, bool)
    selected[point_ids] = True
    row_of_point = np.full(slam_map.points.count, -1, np.int64)
    row_of_point[point_ids] = np.arange(len(point_ids))
    seen = slam_map.observers(selected)
    if not seen:
        return MapPointObservations.empty()
    return MapPointObservations(
        point_rows=np.concatenate([row_of_point[slam_map.keyframes[k].point_ids[i]] for k, i in seen.items()]),
        keyframe_ids=np.concatenate([np.full(len(i), k, np.int64) for k, i in seen.items()]),
        keypoints_px=np.concatenate([slam_map.keyframes[k].features.keypoints_px[i] for k, i in seen.items()]).reshape(-1, 2),
    )
