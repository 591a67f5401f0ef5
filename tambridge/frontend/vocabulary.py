"""Bag of binary words over ORB descriptors (DBoW2's scheme) and the keyframe database that queries it.

The vocabulary is a tree of k-majority cluster centres (k-means with Hamming distance and bitwise-majority
centres), ``branching`` children per node, ``depth`` levels; a descriptor's word is the leaf reached by
descending to the nearest child at each level. Words carry idf weights; an image's vector is its
tf-idf histogram, L1-normalised, and two vectors score ``1 - |a - b|_1 / 2`` in [0, 1] (Nister & Stewenius 2006;
Galvez-Lopez & Tardos 2012). The project trains its own vocabulary (:func:`train_vocabulary`) and ships it
in ``tambridge/frontend/data/orb_vocabulary.npz``; nothing is downloaded.

Regenerate the shipped file with ``python -m tambridge.frontend.vocabulary OUT.npz [TUM_FOLDER ...]``.
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
from pathlib import Path

import numba
import numpy as np

from tambridge.frontend.matching import _hamming, as_words, hamming_matrix

logger = logging.getLogger("tambridge.frontend.vocabulary")

DEFAULT_VOCABULARY_PATH = Path(__file__).parent / "data" / "orb_vocabulary.npz"


@dataclasses.dataclass
class Vocabulary:
    """``centres`` (n_nodes, 32) uint8 in breadth-first order (node i's children are ``i*k + 1 .. i*k + k``, root
    excluded: node 0 is the root's first child), ``idf`` (n_words,) float64 for the leaves of the last level."""

    branching: int
    depth: int
    centres: np.ndarray
    idf: np.ndarray

    @property
    def n_words(self) -> int:
        return self.branching**self.depth

    def words(self, descriptors: np.ndarray) -> np.ndarray:
        """Word index (N,) int64 of each descriptor (N, 32) uint8."""
        if len(descriptors) == 0:
            return np.zeros(0, np.int64)
        return _descend(as_words(self.centres), as_words(descriptors), self.branching, self.depth)

    def transform(self, descriptors: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Sparse tf-idf vector of an image: ``(word ids (W,) sorted, weights (W,) summing to 1)``."""
        words = self.words(descriptors)
        if words.size == 0:
            return np.zeros(0, np.int64), np.zeros(0)
        ids, counts = np.unique(words, return_counts=True)
        weights = counts / counts.sum() * self.idf[ids]
        total = weights.sum()
        return ids, (weights / total if total > 0 else weights)

    def save(self, path: Path) -> None:
        from tambridge.export.atomic import atomic_path

        with atomic_path(Path(path)) as temp:
            with open(temp, "wb") as handle:
                np.savez_compressed(handle, branching=self.branching, depth=self.depth, centres=self.centres, idf=self.idf)

    @staticmethod
    def load(path: Path | None = None) -> "Vocabulary":
        path = DEFAULT_VOCABULARY_PATH if path is None else Path(path)
        if not path.is_file():
            from tambridge.errors import TambridgeError

            raise TambridgeError(
                f"{path}: ORB vocabulary not found; set frontend vocabulary_path to a file made by "
                "'python -m tambridge.frontend.vocabulary OUT.npz', or reinstall tambridge (it ships one)"
            )
        with np.load(path) as data:
            return Vocabulary(int(data["branching"]), int(data["depth"]), data["centres"], data["idf"])


@numba.njit(cache=True, nogil=True)
def _descend(centre_words, descriptor_words, branching, depth):
    out = np.empty(descriptor_words.shape[0], np.int64)
    first_leaf = 0
    level_size = 1
    for _ in range(depth - 1):
        level_size *= branching
        first_leaf += level_size
    for n in range(descriptor_words.shape[0]):
        node = -1  # the root; its children are 0..k-1
        for _ in range(depth):
            first_child = (node + 1) * branching
            best, best_child = 1 << 30, first_child
            for child in range(first_child, first_child + branching):
                d = _hamming(centre_words[child], descriptor_words[n])
                if d < best:
                    best, best_child = d, child
            node = best_child
        out[n] = node - first_leaf
    return out


def _majority(descriptors: np.ndarray) -> np.ndarray:
    """Bitwise majority (1, 32) uint8 of descriptors (N, 32): the Hamming-space centre of a cluster."""
    bits = np.unpackbits(descriptors, axis=1)
    return np.packbits(bits.mean(axis=0) > 0.5)[None, :]


def _k_majority(descriptors: np.ndarray, k: int, rng: np.random.Generator, iterations: int) -> tuple[np.ndarray, np.ndarray]:
    """k centres (k, 32) and labels (N,) by k-majority with k-means++ seeding."""
    if len(descriptors) <= k:
        centres = np.concatenate([descriptors, np.repeat(descriptors[:1], k - len(descriptors), axis=0)]) if len(descriptors) else np.zeros((k, 32), np.uint8)
        return centres, np.arange(len(descriptors)) % k
    centres = [descriptors[rng.integers(len(descriptors))]]
    nearest = hamming_matrix(descriptors, centres[0][None]).ravel().astype(np.float64)
    for _ in range(1, k):
        probability = nearest**2 / max((nearest**2).sum(), 1e-12)
        centres.append(descriptors[rng.choice(len(descriptors), p=probability)])
        nearest = np.minimum(nearest, hamming_matrix(descriptors, centres[-1][None]).ravel())
    centres = np.stack(centres)
    labels = np.zeros(len(descriptors), np.int64)
    for _ in range(iterations):
        new_labels = hamming_matrix(descriptors, centres).argmin(axis=1)
        if np.array_equal(new_labels, labels) and _ > 0:
            break
        labels = new_labels
        for cluster in range(k):
            members = descriptors[labels == cluster]
            if len(members):
                centres[cluster] = _majority(members)[0]
    return centres, labels


def train_vocabulary(
    image_descriptors: list[np.ndarray], branching: int = 8, depth: int = 4, iterations: int = 10, seed: int = 0
) -> Vocabulary:
    """Train a vocabulary tree on the ORB descriptors of a set of images (list of (N_i, 32) uint8).

    idf(word) = log(images / images containing the word); unseen words get the largest idf.
    """
    rng = np.random.default_rng(seed)
    everything = np.concatenate(image_descriptors)
    centres = np.zeros((sum(branching**level for level in range(1, depth + 1)), 32), np.uint8)
    # Breadth-first: each node's descriptors are split among its k children.
    members = {-1: np.arange(len(everything))}
    for level in range(depth):
        next_members = {}
        for node, indices in members.items():
            first_child = (node + 1) * branching
            node_centres, labels = _k_majority(everything[indices], branching, rng, iterations)
            centres[first_child:first_child + branching] = node_centres
            for child in range(branching):
                next_members[first_child + child] = indices[labels == child]
        members = next_members
        logger.info("vocabulary level %d of %d trained", level + 1, depth)
    vocabulary = Vocabulary(branching, depth, centres, np.ones(branching**depth))
    containing = np.zeros(vocabulary.n_words)
    for descriptors in image_descriptors:
        containing[np.unique(vocabulary.words(descriptors))] += 1
    idf = np.log(len(image_descriptors) / np.maximum(containing, 1.0))
    idf[containing == 0] = np.log(len(image_descriptors))
    vocabulary.idf = idf
    return vocabulary


def bow_score(words_a: np.ndarray, weights_a: np.ndarray, words_b: np.ndarray, weights_b: np.ndarray) -> float:
    """L1 score of two L1-normalised bag-of-words vectors: ``sum over shared words of min(a, b)`` in [0, 1]."""
    _, index_a, index_b = np.intersect1d(words_a, words_b, assume_unique=True, return_indices=True)
    return float(np.minimum(weights_a[index_a], weights_b[index_b]).sum())


class KeyframeDatabase:
    """Inverted index of keyframe bag-of-words vectors; a query scores every keyframe sharing a word with it."""

    def __init__(self, n_words: int) -> None:
        self.n_words = n_words
        self._keyframe: list[np.ndarray] = []
        self._word: list[np.ndarray] = []
        self._weight: list[np.ndarray] = []
        self._tables: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
        # Keyframe id -> the keyframe a match with it counts for (itself unless redirected).
        self._owner = np.zeros(0, np.int64)

    def add(self, keyframe_id: int, words: np.ndarray, weights: np.ndarray) -> None:
        if keyframe_id >= len(self._owner):
            self._owner = np.append(self._owner, np.arange(len(self._owner), keyframe_id + 1))
        self._keyframe.append(np.full(len(words), keyframe_id, np.int64))
        self._word.append(words)
        self._weight.append(weights)
        self._tables = None

    def redirect(self, keyframe_id: int, to_keyframe_id: int) -> None:
        """From now on a match with ``keyframe_id`` (a culled keyframe), or with any keyframe redirected to it,
        counts for ``to_keyframe_id`` (its parent): the place it saw stays retrievable, through a live keyframe."""
        self._owner[self._owner == keyframe_id] = to_keyframe_id

    def query(self, words: np.ndarray, weights: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(keyframe ids (K,), scores (K,))`` of every keyframe with a score above zero, best first; a keyframe
        others are redirected to scores the best of its own score and theirs."""
        if not self._keyframe:
            return np.zeros(0, np.int64), np.zeros(0)
        if self._tables is None:
            self._tables = (np.concatenate(self._keyframe), np.concatenate(self._word), np.concatenate(self._weight))
        keyframes, table_words, table_weights = self._tables
        dense = np.zeros(self.n_words)
        dense[words] = weights
        contribution = np.minimum(table_weights, dense[table_words])
        scores = np.bincount(keyframes, weights=contribution)
        owner = self._owner[: len(scores)]
        if (owner != np.arange(len(scores))).any():
            owned = np.zeros(max(len(scores), int(owner.max()) + 1))
            np.maximum.at(owned, owner, scores)
            scores = owned
        ids = np.flatnonzero(scores > 0)
        order = np.argsort(-scores[ids], kind="stable")
        return ids[order], scores[ids][order]


def _training_descriptors(folders: list[Path], frames_per_folder: int, synthetic_views: int) -> list[np.ndarray]:
    """ORB descriptors of synthetic room renders (several seeds) and of frames of the given TUM folders."""
    from tambridge.frontend.orb_features import OrbExtractor
    from tambridge.frontend.types import OrbFrontendConfig
    from tambridge.io.synthetic import default_camera, loop_path, make_room_scene, render
    from tambridge.io.tum import open_sequence

    images = []
    camera = default_camera(640, 480)
    extractor = OrbExtractor(camera, OrbFrontendConfig())
    for seed in range(1, 4):
        scene = make_room_scene(seed)
        for world_from_camera in loop_path(synthetic_views):
            colour, depth_m = render(scene, camera, world_from_camera)
            images.append(extractor.extract((colour * 255).astype(np.uint8), depth_m).descriptors)
    for folder in folders:
        sequence = open_sequence(folder)
        extractor = OrbExtractor(sequence.camera, OrbFrontendConfig())
        for index in np.linspace(0, len(sequence) - 1, min(frames_per_folder, len(sequence))).astype(int):
            frame = sequence[int(index)]
            images.append(extractor.extract(frame.rgb, frame.depth_m).descriptors)
    return [d for d in images if len(d)]


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description="Train the ORB bag-of-words vocabulary tambridge ships.")
    parser.add_argument("output", type=Path)
    parser.add_argument("folders", type=Path, nargs="*", help="TUM-layout sequences to sample frames from")
    parser.add_argument("--frames-per-folder", type=int, default=40)
    parser.add_argument("--synthetic-views", type=int, default=12)
    parser.add_argument("--branching", type=int, default=8)
    parser.add_argument("--depth", type=int, default=4)
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO)
    descriptors = _training_descriptors(args.folders, args.frames_per_folder, args.synthetic_views)
    logger.info("training on %d images, %d descriptors", len(descriptors), sum(len(d) for d in descriptors))
    train_vocabulary(descriptors, args.branching, args.depth).save(args.output)


if __name__ == "__main__":
    main()
