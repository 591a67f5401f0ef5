"""Bag of binary words over ORB descriptors (DBoW2's scheme) and the keyframe database that queries it.

The vocabulary is a tree of k-majority cluster centres (k-means with Hamming distance and bitwise-majority
centres), ``branching`` children per node, ``depth`` levels; a descriptor's word is the leaf reached by
descending to the nearest child at each level. Words carry idf weights; an image's vector is its
tf-idf histogram, L1-normalised, and two vectors score ``1 - |a - b|_1 / 2`` in [0, 1] (Nister & Stewenius 2006;
Galvez-Lopez & Tardos 2012). The project trains its own vocabulary (:mod:`~tambridge.frontend.orb.vocabulary_training`) and ships it
in ``tambridge/frontend/orb/data/orb_vocabulary.npz``; nothing is downloaded.

Regenerate the shipped file with ``python -m tambridge.frontend.orb.vocabulary_training OUT.npz [TUM_FOLDER ...]``.
"""

from __future__ import annotations

import dataclasses
import logging
from pathlib import Path

import numba
import numpy as np

from tambridge.frontend.orb.matching import _hamming, as_words

logger = logging.getLogger("tambridge.frontend.orb.vocabulary")

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
        from tambridge.files import atomic_path

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
                "'python -m tambridge.frontend.orb.vocabulary_training OUT.npz', or reinstall tambridge (it ships one)"
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
