"""Training of the ORB bag-of-words vocabulary that tambridge ships (not used at run time).

``python -m tambridge.frontend.orb.vocabulary_training OUT.npz [TUM_FOLDER ...]`` regenerates
``tambridge/frontend/orb/data/orb_vocabulary.npz`` from synthetic room renders and frames of the given folders.
"""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

import numpy as np

from tambridge.frontend.orb.matching import hamming_matrix
from tambridge.frontend.orb.vocabulary import Vocabulary

logger = logging.getLogger("tambridge.frontend.orb.vocabulary_training")


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


def _training_descriptors(folders: list[Path], frames_per_folder: int, synthetic_views: int) -> list[np.ndarray]:
    """ORB descriptors of synthetic room renders (several seeds) and of frames of the given TUM folders."""
    from tambridge.frontend.orb.features import OrbExtractor
    from tambridge.frontend.orb.config import OrbFrontendConfig
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
