"""The sparse map the ORB frontend keeps across frames: keyframes, map points, covisibility.

Map points live in growable arrays indexed by point id (``MapPoints``); a keyframe records, per keypoint, the
id of the map point it observes (-1 for none), which is the one place observations are stored. Point-centric
questions ("who sees these points") loop over keyframes, never over points. Bad points are flagged, not
deleted, and skipped wherever ids are read. Culled keyframes likewise stay in the list (a keyframe's id is its
position, and the pipeline anchors Gaussians to it) but lose their observations and covisibility; each keeps its
pose relative to a live ``parent`` keyframe, as ORB-SLAM's culled keyframes do, and
:meth:`SlamMap.update_culled_poses` carries them along when their parents move.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from tambridge.frontend.orb.dense_depth import DenseReference
from tambridge.frontend.orb.matching import KeypointGrid, distinctive_indices
from tambridge.frontend.orb.features import FrameFeatures
from tambridge.geometry import inverse


@dataclasses.dataclass
class Keyframe:
    """A keyframe: its features, the map point id per keypoint (N,) int64 (-1 none), the map segment it belongs to,
    its keypoints indexed for radius searches (fusion and loop closing search each keyframe many times),
    bag-of-words vector and covisibility weights (other keyframe id -> shared points).

    A culled keyframe has ``parent`` >= 0, the live keyframe it follows, and ``parent_from_camera`` (4, 4); its
    ``point_ids`` are all -1 and its ``covisibility`` is empty.
    """

    id: int
    frame_index: int
    timestamp_s: float
    world_from_camera: np.ndarray
    features: FrameFeatures
    point_ids: np.ndarray
    segment: int
    keypoint_grid: KeypointGrid
    bow_words: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(0, np.int64))
    bow_weights: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(0))
    covisibility: dict[int, int] = dataclasses.field(default_factory=dict)
    parent: int = -1
    parent_from_camera: np.ndarray | None = None
    # Its depth for bundle adjustment's depth edges (None where they are off, or once culled).
    depth_reference: DenseReference | None = None
    depth_samples_m: np.ndarray | None = None

    @property
    def culled(self) -> bool:
        return self.parent >= 0

    @property
    def camera_from_world(self) -> np.ndarray:
        return inverse(self.world_from_camera)

    @property
    def centre_m(self) -> np.ndarray:
        return self.world_from_camera[:3, 3]

    def best_covisible(self, count: int, min_weight: int = 1) -> list[int]:
        """Ids of up to ``count`` keyframes sharing the most points with this one (at least ``min_weight``)."""
        ranked = sorted(((w, k) for k, w in self.covisibility.items() if w >= min_weight), reverse=True)
        return [k for _, k in ranked[:count]]


class MapPoints:
    """Growable arrays of map point attributes, indexed by point id.

    ``positions_m`` (N, 3) world; ``descriptors`` (N, 32); ``normals`` (N, 3) unit mean viewing direction;
    ``max_distance_m``/``min_distance_m`` (N,) the scale-invariance range of ORB; ``colours`` (N, 3) uint8;
    ``observations`` (N,) keyframes that see the point; ``visible``/``found`` (N,) frames where it was in the
    frustum / matched; ``first_keyframe`` (N,) and ``reference_keyframe`` (N,) ids; ``bad`` (N,) bool.
    """

    def __init__(self, capacity: int = 4096) -> None:
        self.count = 0
        self.positions_m = np.zeros((capacity, 3))
        self.descriptors = np.zeros((capacity, 32), np.uint8)
        self.normals = np.zeros((capacity, 3))
        self.max_distance_m = np.zeros(capacity)
        self.min_distance_m = np.zeros(capacity)
        self.colours = np.zeros((capacity, 3), np.uint8)
        self.observations = np.zeros(capacity, np.int64)
        self.visible = np.zeros(capacity, np.int64)
        self.found = np.zeros(capacity, np.int64)
        self.first_keyframe = np.zeros(capacity, np.int64)
        self.reference_keyframe = np.zeros(capacity, np.int64)
        self.bad = np.zeros(capacity, bool)

    _FIELDS = ("positions_m", "descriptors", "normals", "max_distance_m", "min_distance_m", "colours", "observations",
               "visible", "found", "first_keyframe", "reference_keyframe", "bad")

    def _grow(self, needed: int) -> None:
        capacity = len(self.bad)
        if needed <= capacity:
            return
        new_capacity = max(needed, 2 * capacity)
        for name in self._FIELDS:
            old = getattr(self, name)
            grown = np.zeros((new_capacity,) + old.shape[1:], old.dtype)
            grown[: self.count] = old[: self.count]
            setattr(self, name, grown)

    def add(
        self,
        positions_m: np.ndarray,
        descriptors: np.ndarray,
        colours: np.ndarray,
        camera_centre_m: np.ndarray,
        octaves: np.ndarray,
        keyframe_id: int,
        scale_factor: float,
        n_levels: int,
    ) -> np.ndarray:
        """Append points (K, 3) seen from ``camera_centre_m`` at keypoint ``octaves`` (K,); returns their ids (K,)."""
        k = len(positions_m)
        self._grow(self.count + k)
        ids = np.arange(self.count, self.count + k)
        offsets = positions_m - camera_centre_m
        distance = np.linalg.norm(offsets, axis=1)
        self.positions_m[ids] = positions_m
        self.descriptors[ids] = descriptors
        self.colours[ids] = colours
        self.normals[ids] = offsets / np.maximum(distance, 1e-9)[:, None]
        # ORB-SLAM: a point seen at octave o at distance d is matchable from d*s^o/s^(L-1) to d*s^o.
        self.max_distance_m[ids] = distance * scale_factor ** octaves
        self.min_distance_m[ids] = self.max_distance_m[ids] / scale_factor ** (n_levels - 1)
        self.observations[ids] = 1
        self.visible[ids] = 1
        self.found[ids] = 1
        self.first_keyframe[ids] = keyframe_id
        self.reference_keyframe[ids] = keyframe_id
        self.bad[ids] = False
        self.count += k
        return ids

    def good(self, ids: np.ndarray) -> np.ndarray:
        """Mask (K,) of ids that are valid (>= 0) and not bad."""
        ids = np.asarray(ids)
        valid = ids >= 0
        out = np.zeros(len(ids), bool)
        out[valid] = ~self.bad[ids[valid]]
        return out


class SlamMap:
    """Keyframes (in insertion order, id = position) and map points, with covisibility bookkeeping."""

    def __init__(self) -> None:
        self.keyframes: list[Keyframe] = []
        self.points = MapPoints()
        # (id_a, id_b, b_from_a measured) loop constraints found so far, kept for later pose graphs.
        self.loop_edges: list[tuple[int, int, np.ndarray]] = []
        # (last keyframe before a tracking loss, first keyframe of the new segment, guessed relative pose).
        self.segment_links: list[tuple[int, int, np.ndarray]] = []

    def good_point_ids(self, keyframe: Keyframe) -> np.ndarray:
        """Good map point ids observed by a keyframe (K,)."""
        ids = keyframe.point_ids
        return ids[self.points.good(ids)]

    def observers(self, point_mask: np.ndarray) -> dict[int, np.ndarray]:
        """Keyframe id -> keypoint indices whose point is selected by ``point_mask`` (n_points,) bool."""
        out = {}
        for keyframe in self.keyframes:
            ids = keyframe.point_ids
            valid = ids >= 0
            hit = np.zeros(len(ids), bool)
            hit[valid] = point_mask[ids[valid]]
            if hit.any():
                out[keyframe.id] = np.flatnonzero(hit)
        return out

    def distinctive_descriptors(self, point_ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The most distinctive descriptor among each point's observations (ORB-SLAM's
        ComputeDistinctiveDescriptors), so that matching compares against a typical view, not the first one:
        ``(ids (J,), descriptors (J, 32))`` for the good ones of ``point_ids`` (K,) that a keyframe observes."""
        mask = np.zeros(self.points.count, bool)
        mask[point_ids[self.points.good(point_ids)]] = True
        seen = self.observers(mask)
        if not seen:
            return np.zeros(0, np.int64), np.zeros((0, self.points.descriptors.shape[1]), self.points.descriptors.dtype)
        observed = np.concatenate([self.keyframes[k].point_ids[i] for k, i in seen.items()])
        descriptors = np.concatenate([self.keyframes[k].features.descriptors[i] for k, i in seen.items()])
        order = np.argsort(observed, kind="stable")
        observed, descriptors = observed[order], descriptors[order]
        ids, group_start = np.unique(observed, return_index=True)
        return ids, descriptors[distinctive_indices(descriptors, np.append(group_start, len(observed)))]

    def update_covisibility(self, keyframes: list[Keyframe], min_shared: int) -> None:
        """For each of ``keyframes`` in turn, recount the points it shares with every other keyframe; keep pairs with
        >= ``min_shared`` (or the single best pair if none reaches it, so the graph stays connected). The map's
        observations are gathered once for all of them: fusion and local BA recount ten keyframes or more."""
        if len(self.keyframes) < 2:
            for keyframe in keyframes:
                keyframe.covisibility = {}
            return
        owner = np.repeat(np.arange(len(self.keyframes)), [len(other.point_ids) for other in self.keyframes])
        observed = np.concatenate([other.point_ids for other in self.keyframes])
        for keyframe in keyframes:
            mask = np.zeros(self.points.count + 1, bool)  # the last entry stands for "no point" (id -1)
            mask[self.good_point_ids(keyframe)] = True
            shared = np.bincount(owner[mask[observed]], minlength=len(self.keyframes))
            shared[keyframe.id] = 0
            # Pairs are kept both ways, so the keyframes that hold this one's old pair are its old partners.
            for other_id in keyframe.covisibility:
                self.keyframes[other_id].covisibility.pop(keyframe.id, None)
            partners = np.flatnonzero(shared)
            counts = dict(zip(partners.tolist(), shared[partners].tolist()))
            kept = {k: w for k, w in counts.items() if w >= min_shared}
            if not kept and counts:
                best = max(counts, key=counts.get)
                kept = {best: counts[best]}
            keyframe.covisibility = kept
            for other_id, weight in kept.items():
                self.keyframes[other_id].covisibility[keyframe.id] = weight

    @staticmethod
    def drop_duplicate_observations(keyframe: Keyframe) -> None:
        """A keyframe sees a point at most once: keep the first keypoint of each repeated id."""
        valid = np.flatnonzero(keyframe.point_ids >= 0)
        _, first = np.unique(keyframe.point_ids[valid], return_index=True)
        duplicate = np.ones(valid.size, bool)
        duplicate[first] = False
        keyframe.point_ids[valid[duplicate]] = -1

    def recount_observations(self) -> None:
        """Observation count of every point from the keyframes' point ids (after merges and removals)."""
        all_ids = np.concatenate([k.point_ids[k.point_ids >= 0] for k in self.keyframes]) if self.keyframes else np.zeros(0, np.int64)
        self.points.observations[: self.points.count] = np.bincount(all_ids, minlength=self.points.count)[: self.points.count]

    def replace_points(self, old_ids: np.ndarray, new_ids: np.ndarray) -> None:
        """Merge duplicates: every observation of ``old_ids[i]`` becomes one of ``new_ids[i]``; old points go bad.
        Always recounts observations, also when nothing merges (fusion attaches observations first).

        A keyframe that ends up seeing the same point at two keypoints keeps the first.
        """
        keep = old_ids != new_ids
        old_ids, new_ids = old_ids[keep], new_ids[keep]
        if len(old_ids):
            remap = np.arange(self.points.count)
            remap[old_ids] = new_ids
            # Follow chains (a -> b -> c) so that every id lands on a point that is not replaced.
            for _ in range(8):
                remap = remap[remap]
            for keyframe in self.keyframes:
                ids = keyframe.point_ids
                valid = np.flatnonzero(ids >= 0)
                merged = remap[ids[valid]]
                # Only a keyframe that saw a replaced point can now see a point twice.
                if (merged != ids[valid]).any():
                    ids[valid] = merged
                    self.drop_duplicate_observations(keyframe)
            self.points.bad[old_ids] = True
        self.recount_observations()

    def cull_keyframe(self, keyframe: Keyframe, parent: Keyframe) -> None:
        """Take a redundant keyframe out of the map (ORB-SLAM's KeyFrame::SetBadFlag): it drops its observations
        and covisibility links and from now on follows ``parent`` (live) rigidly, as do the keyframes culled
        earlier with it as their parent. Points it alone saw go bad; points it was the reference of move to
        another observer (or go bad when no keyframe sees them)."""
        assert not parent.culled and parent.id != keyframe.id
        keyframe.parent_from_camera = parent.camera_from_world @ keyframe.world_from_camera
        keyframe.parent = parent.id
        for child in self.keyframes:
            if child.parent == keyframe.id:
                child.parent_from_camera = keyframe.parent_from_camera @ child.parent_from_camera
                child.parent = parent.id
        for other in keyframe.covisibility:
            self.keyframes[other].covisibility.pop(keyframe.id, None)
        keyframe.covisibility = {}
        seen = keyframe.point_ids[keyframe.point_ids >= 0]
        keyframe.point_ids[:] = -1
        keyframe.depth_reference = keyframe.depth_samples_m = None
        self.recount_observations()
        points = self.points
        points.bad[seen[points.observations[seen] == 0]] = True
        n = points.count
        moving = np.flatnonzero(~points.bad[:n] & (points.reference_keyframe[:n] == keyframe.id))
        if moving.size:
            # The most recent keyframe observing the point becomes its reference; a point nobody sees goes bad.
            latest = np.full(n, -1, np.int64)
            for other in self.keyframes:
                latest[other.point_ids[other.point_ids >= 0]] = other.id
            points.reference_keyframe[moving] = np.maximum(latest[moving], 0)
            points.bad[moving[latest[moving] < 0]] = True

    def update_culled_poses(self) -> None:
        """Put every culled keyframe back at its parent's pose times its relative pose (after poses changed)."""
        for keyframe in self.keyframes:
            if keyframe.culled:
                keyframe.world_from_camera = self.keyframes[keyframe.parent].world_from_camera @ keyframe.parent_from_camera

    def move_points_with_keyframes(self, world_from_camera_before: np.ndarray) -> None:
        """After keyframe poses changed, carry each good point with its reference keyframe.

        ``world_from_camera_before`` (K, 4, 4) are the keyframe poses before the change (index = keyframe id).
        """
        n = self.points.count
        if n == 0:
            return
        after = np.stack([k.world_from_camera for k in self.keyframes])
        correction = np.einsum("kij,kjl->kil", after, np.stack([inverse(p) for p in world_from_camera_before]))
        reference = self.points.reference_keyframe[:n]
        positions = self.points.positions_m[:n]
        moved = np.einsum("nij,nj->ni", correction[reference, :3, :3], positions) + correction[reference, :3, 3]
        self.points.normals[:n] = np.einsum("nij,nj->ni", correction[reference, :3, :3], self.points.normals[:n])
        self.points.positions_m[:n] = moved

    def local_keyframes(self, reference: Keyframe, count: int) -> list[Keyframe]:
        """The reference keyframe, its best covisible keyframes and, while fewer than ``count``, theirs (ORB-SLAM's
        local map: keyframes seen together with the reference, never merely recent ones, so that a revisited
        place is left to loop closing)."""
        chosen = [reference.id] + reference.best_covisible(count)
        for neighbour in list(chosen[1:]):
            if len(chosen) > count:
                break
            chosen += [k for k in self.keyframes[neighbour].best_covisible(count) if k not in chosen][: count + 1 - len(chosen)]
        return [self.keyframes[i] for i in chosen[: count + 1]]

    def points_of(self, keyframes: list[Keyframe]) -> np.ndarray:
        """Sorted unique good point ids seen by any of the keyframes."""
        # A mask over all points rather than np.unique: this runs twice per tracked frame, and sorting the
        # local map's observations took longer than marking them.
        seen = np.zeros(self.points.count, bool)
        for keyframe in keyframes:
            seen[keyframe.point_ids[keyframe.point_ids >= 0]] = True
        return np.flatnonzero(seen & ~self.points.bad[: self.points.count])
