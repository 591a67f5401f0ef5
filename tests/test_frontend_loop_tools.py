"""Place recognition and pose graphs: the bag-of-words vocabulary and database, Open3D's pose-graph conventions."""

import numpy as np
import pytest

from tambridge.frontend.orb.loop_closing import LoopConsistency
from tambridge.frontend.pose_graph import PoseEdge, optimise_pose_graph
from tambridge.frontend.orb.vocabulary import DEFAULT_VOCABULARY_PATH, KeyframeDatabase, Vocabulary, bow_score
from tambridge.frontend.orb.vocabulary_training import train_vocabulary
from tambridge.geometry import exp_se3, inverse


def test_shipped_vocabulary_is_small_and_loads():
    assert DEFAULT_VOCABULARY_PATH.stat().st_size < 1_000_000
    vocabulary = Vocabulary.load()
    assert vocabulary.centres.shape == (sum(vocabulary.branching**d for d in range(1, vocabulary.depth + 1)), 32)
    assert vocabulary.idf.shape == (vocabulary.n_words,)
    # idf = log(N / n) with N training images and n in 1..N of them holding the word: the largest idf is log(N),
    # and N / exp(idf) is a whole number of images for every word.
    images = np.exp(vocabulary.idf.max())
    assert images == pytest.approx(round(images), abs=1e-9) and round(images) > 1
    containing = images / np.exp(vocabulary.idf)
    np.testing.assert_allclose(containing, np.round(containing), atol=1e-9)
    assert containing.max() <= images + 1e-9


def test_idf_is_the_log_of_the_image_count_over_the_images_holding_the_word():
    """Four far-apart descriptor clusters A-D (Hamming 128-256 between their patterns, 2 % bit noise within) in
    images holding AB, AB, AC and AD: word A is in all 4 images, B in 2, C and D in 1."""
    rng = np.random.default_rng(3)
    patterns = {name: np.full(32, byte, np.uint8) for name, byte in zip("ABCD", (0x00, 0xFF, 0x0F, 0xF0))}

    def noisy(name, count=10):
        return patterns[name] ^ np.packbits(rng.random((count, 256)) < 0.02, axis=1)

    images = [np.concatenate([noisy(name) for name in content]) for content in ("AB", "AB", "AC", "AD")]
    vocabulary = train_vocabulary(images, branching=4, depth=1, iterations=5)
    word = {name: vocabulary.words(noisy(name, 20)) for name in "ABCD"}
    assert all(len(set(words.tolist())) == 1 for words in word.values())  # each cluster is one word
    word = {name: int(words[0]) for name, words in word.items()}
    assert sorted(word.values()) == [0, 1, 2, 3]
    np.testing.assert_allclose([vocabulary.idf[word[name]] for name in "ABCD"],
                               [np.log(4 / 4), np.log(4 / 2), np.log(4 / 1), np.log(4 / 1)], atol=1e-12)
    # A word no training image reaches (a node with too few descriptors repeats its first centre) gets log(N).
    a1, a2, b = np.zeros(32, np.uint8), np.zeros(32, np.uint8), np.full(32, 0xFF, np.uint8)
    a2[0] = 0xFF  # 8 bits from a1: one branch of the first level, split at the second
    images = [np.stack([a1] * 5 + [b]), np.stack([a1] * 5 + [a2] * 5)]
    vocabulary = train_vocabulary(images, branching=2, depth=2, iterations=5)
    words = {name: int(vocabulary.words(d[None])[0]) for name, d in (("a1", a1), ("a2", a2), ("b", b))}
    assert len(set(words.values())) == 3
    unseen = ({0, 1, 2, 3} - set(words.values())).pop()
    np.testing.assert_allclose([vocabulary.idf[words["a1"]], vocabulary.idf[words["a2"]], vocabulary.idf[words["b"]],
                                vocabulary.idf[unseen]], [0.0, np.log(2), np.log(2), np.log(2)], atol=1e-12)


def test_trained_vocabulary_retrieves_the_same_place():
    rng = np.random.default_rng(0)
    # Ten "places", each a set of 200 descriptors; a revisit sees the same descriptors with 5% bit noise.
    places = [rng.integers(0, 256, (200, 32), dtype=np.uint8) for _ in range(10)]
    vocabulary = train_vocabulary(places, branching=4, depth=3, iterations=5)
    assert vocabulary.words(places[0]).max() < vocabulary.n_words
    database = KeyframeDatabase(vocabulary.n_words)
    for place_id, descriptors in enumerate(places):
        database.add(place_id, *vocabulary.transform(descriptors))
    for place_id in (2, 7):
        noisy = places[place_id] ^ np.packbits(rng.random((200, 256)) < 0.05, axis=1)
        words, weights = vocabulary.transform(noisy)
        ids, scores = database.query(words, weights)
        assert ids[0] == place_id
        assert scores[0] == bow_score(words, weights, *vocabulary.transform(places[place_id]))
    words, weights = vocabulary.transform(places[3])
    assert abs(weights.sum() - 1.0) < 1e-12 and abs(bow_score(words, weights, words, weights) - 1.0) < 1e-12


def test_pose_graph_convention_and_loop_correction():
    rng = np.random.default_rng(1)
    truth = [np.eye(4)]
    for _ in range(7):
        truth.append(truth[-1] @ exp_se3(np.concatenate([rng.normal(0, 0.2, 3), rng.normal(0, 0.1, 3)])))
    truth = np.stack(truth)
    # Odometry edges with a small bias (drift), one exact loop edge from the last node back to the first.
    edges, drifted = [], [np.eye(4)]
    bias = exp_se3(np.array([0.01, 0.0, 0.0, 0.0, 0.0, 0.005]))
    for i in range(1, len(truth)):
        measured = inverse(truth[i]) @ truth[i - 1] @ bias  # target i from source i-1
        edges.append(PoseEdge(i - 1, i, measured, np.eye(6)))
        drifted.append(drifted[-1] @ inverse(measured))
    edges.append(PoseEdge(len(truth) - 1, 0, inverse(truth[0]) @ truth[-1], 100 * np.eye(6)))
    drifted = np.stack(drifted)
    optimised, _ = optimise_pose_graph(drifted, edges, reference_node=0)
    np.testing.assert_allclose(optimised[0], np.eye(4), atol=1e-9)
    error_before = np.linalg.norm(drifted[-1, :3, 3] - truth[-1, :3, 3])
    error_after = np.linalg.norm(optimised[-1, :3, 3] - truth[-1, :3, 3])
    assert error_after < 0.1 * error_before
    # Without the bias and with every edge exact, a perturbed graph returns to the truth.
    exact = [PoseEdge(i - 1, i, inverse(truth[i]) @ truth[i - 1], np.eye(6)) for i in range(1, len(truth))]
    perturbed = np.stack([truth[0]] + [t @ exp_se3(rng.normal(0, 0.02, 6)) for t in truth[1:]])
    optimised, _ = optimise_pose_graph(perturbed, exact, reference_node=0)
    np.testing.assert_allclose(optimised, truth, atol=1e-5)


def test_loop_candidate_needs_consecutive_consistent_groups():
    consistency = LoopConsistency(required=3)
    # Keyframe 40 revisits the place of keyframes 3-6: its candidate groups overlap from one query to the next.
    assert consistency.accept([(5, {4, 5, 6}), (20, {19, 20})]) == []
    assert consistency.accept([(6, {5, 6, 7})]) == []  # 1 consecutive
    assert consistency.accept([(4, {3, 4, 5}), (30, {30, 31})]) == []  # 2
    assert consistency.accept([(30, {29, 30}), (5, {4, 5})]) == [5]  # 3: accepted; 30 has only 1
    # A query without candidates breaks every chain.
    assert consistency.accept([]) == []
    assert consistency.accept([(5, {4, 5})]) == []
    # required=0 accepts every candidate at once, in the order given.
    assert LoopConsistency(required=0).accept([(9, {9}), (2, {2, 3})]) == [9, 2]
