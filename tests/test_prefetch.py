"""Frames read (and ORB features extracted) ahead in worker threads: same frames, same results."""

import pickle
import threading

import numpy as np
import pytest

from pipelines.reconstruct import RunCounters, track_frames
from tambridge.frontend.open3d.odometry import FrameToFrameOdometry
from tambridge.frontend.orb.frontend import OrbFrontend
from tambridge.frontend.orb.config import OrbFrontendConfig
from tambridge.io.prefetch import FRAMES_AHEAD, FramePrefetcher, ReadAhead
from tambridge.io.tum import Frame, open_sequence
from tambridge.runlog import RunLog

INLINE = OrbFrontendConfig(mapping_thread=False)
RESUME_AT = 13


class _Frames:
    """A stand-in sequence of ``count`` tiny frames; reading frame ``broken`` raises; records the reading threads."""

    def __init__(self, count: int, broken: int = -1) -> None:
        self.count, self.broken = count, broken
        self.readers: list[str] = []

    def __len__(self) -> int:
        return self.count

    def __getitem__(self, index: int) -> Frame:
        self.readers.append(threading.current_thread().name)
        if index == self.broken:
            raise ValueError(f"frame {index} is corrupt")
        return Frame(index, 0.1 * index, np.full((2, 2, 3), index, np.uint8), np.full((2, 2), index, np.float32))


def _prefetch_threads() -> list[threading.Thread]:
    return [t for t in threading.enumerate() if t.name.startswith("tambridge-prefetch")]


@pytest.mark.parametrize("start", [0, 3, 7])
def test_frames_come_in_order_from_the_start_with_what_prepare_made(start):
    frames = _Frames(7)
    prepare = lambda frame: (frame.index * 10, threading.current_thread().name)  # noqa: E731
    with FramePrefetcher(frames, start, prepare=prepare) as prefetcher:
        got = list(prefetcher)
    assert [frame.index for frame, _ in got] == list(range(start, 7))
    assert [prepared for _, (prepared, _) in got] == [10 * i for i in range(start, 7)]
    # Prepared in its own worker thread, beside the reader's.
    assert all(thread.startswith("tambridge-prefetch-prepare") for _, (_, thread) in got)
    assert all(frame.rgb[0, 0, 0] == frame.index for frame, _ in got)
    # Every frame read once, all of them in the worker thread.
    assert len(frames.readers) == 7 - start
    assert all(name.startswith("tambridge-prefetch") for name in frames.readers)
    assert not _prefetch_threads()


def test_without_prepare_frames_are_only_read_ahead():
    frames = _Frames(3)
    with FramePrefetcher(frames) as prefetcher:
        assert [(frame.index, prepared) for frame, prepared in prefetcher] == [(0, None), (1, None), (2, None)]
        # Nothing to prepare: no preparer thread.
        assert [thread.name.rsplit("_", 1)[0] for thread in _prefetch_threads()] == ["tambridge-prefetch-read"]


def test_without_read_ahead_frames_are_read_and_prepared_in_the_callers_thread():
    frames = _Frames(4)
    with FramePrefetcher(frames, 1, prepare=lambda frame: threading.current_thread().name, read_ahead=False) as prefetcher:
        got = [(frame.index, prepared) for frame, prepared in prefetcher]
    here = threading.current_thread().name
    assert got == [(1, here), (2, here), (3, here)]
    assert frames.readers == [here] * 3


def test_a_broken_frame_raises_when_reached_and_the_worker_stops():
    frames = _Frames(6, broken=3)
    seen = []
    with pytest.raises(ValueError, match="frame 3 is corrupt"):
        with FramePrefetcher(frames) as prefetcher:
            for frame, _ in prefetcher:
                seen.append(frame.index)
    assert seen == [0, 1, 2]
    assert not _prefetch_threads()


def test_leaving_early_drops_the_frame_read_ahead():
    frames = _Frames(10)
    with FramePrefetcher(frames) as prefetcher:
        for frame, _ in prefetcher:
            if frame.index == 2:
                break
    # Frames 0-2 were used and the next FRAMES_AHEAD queued to be read ahead (each read unless cancelled first);
    # nothing further, and no thread is left.
    assert 3 <= len(frames.readers) <= 3 + FRAMES_AHEAD < len(frames)
    assert not _prefetch_threads()


@pytest.fixture(scope="module")
def sequential(synthetic_sequence_dir):
    """The synthetic loop tracked one frame after the other (inline mapping: deterministic)."""
    sequence = open_sequence(synthetic_sequence_dir)
    frontend = OrbFrontend(sequence.camera, INLINE)
    results = [frontend.track(frame) for frame in sequence]
    return sequence, results, frontend.finish()


def _track_prefetched(sequence, frontend, tmp_path, start_frame=0):
    run_log = RunLog(tmp_path / "run.log")
    counters = RunCounters()
    try:
        final = track_frames(sequence, frontend, None, counters, run_log, start_frame=start_frame, prefetch=True)
    finally:
        run_log.close()
    return counters, final, run_log


def test_orb_tracking_with_prefetched_features_is_identical_to_sequential(sequential, tmp_path):
    sequence, expected_results, expected = sequential
    counters, final, run_log = _track_prefetched(sequence, OrbFrontend(sequence.camera, INLINE), tmp_path)
    assert final.keyframe_frame_indices == expected.keyframe_frame_indices
    assert counters.keyframes == sum(r.is_keyframe for r in expected_results) > 2
    np.testing.assert_array_equal(final.trajectory.world_from_camera, expected.trajectory.world_from_camera)
    np.testing.assert_array_equal(final.map_points_world_m, expected.map_points_world_m)
    assert final.frames_lost == expected.frames_lost == 0
    assert final.timings_s["features"] > 0
    assert run_log.stage_seconds["tracking"] > 0 and run_log.stage_seconds["frame_reading"] > 0


def test_resumed_prefetched_tracking_continues_to_the_sequential_result(sequential, tmp_path):
    """A resumed run (checkpoint state, then ``start_frame``) prefetches from the frame it resumes at."""
    sequence, _, expected = sequential
    first = OrbFrontend(sequence.camera, INLINE)
    for index in range(RESUME_AT):
        first.track(sequence[index])
    second = OrbFrontend(sequence.camera, INLINE)
    # A checkpoint pickles the state: the resumed frontend shares nothing with the first.
    second.load_state_dict(pickle.loads(pickle.dumps(first.state_dict())))
    _, final, run_log = _track_prefetched(sequence, second, tmp_path, start_frame=RESUME_AT)
    np.testing.assert_array_equal(final.trajectory.world_from_camera, expected.trajectory.world_from_camera)
    assert final.keyframe_frame_indices == expected.keyframe_frame_indices


def test_a_frontend_without_extract_tracks_prefetched_frames_as_without(synthetic_sequence_dir, tmp_path):
    """The Open3D frontends have nothing to extract ahead (``extract`` None): frames are only read ahead."""
    sequence = open_sequence(synthetic_sequence_dir, max_frames=6)
    plain = FrameToFrameOdometry(sequence.camera)
    expected = np.stack([plain.track(frame).world_from_camera for frame in sequence])
    assert FrameToFrameOdometry.extract is None
    _, final, _ = _track_prefetched(sequence, FrameToFrameOdometry(sequence.camera), tmp_path)
    # Open3D's odometry runs in several threads: its poses agree to round-off, not bit for bit.
    np.testing.assert_allclose(final.trajectory.world_from_camera, expected, atol=1e-9)
    assert not _prefetch_threads()


@pytest.mark.parametrize("ahead", [0, 1, 3])
def test_read_ahead_gives_each_read_in_order(ahead):
    frames = _Frames(10)
    order = [7, 2, 2, 9, 0, 5]
    with ReadAhead(order, frames.__getitem__, ahead) as reading:
        assert [frame.index for frame in reading] == order
    here = threading.current_thread().name
    assert all((name == here) == (ahead == 0) for name in frames.readers)
    assert not _prefetch_threads()


def test_read_ahead_raises_a_broken_read_when_reached_and_holds_at_most_ahead_plus_one():
    frames = _Frames(10, broken=4)
    seen = []
    with pytest.raises(ValueError, match="frame 4 is corrupt"):
        with ReadAhead(list(range(10)), frames.__getitem__, ahead=2) as reading:
            for frame in reading:
                # While the caller has item i, items i+1 and i+2 at most have been read.
                assert len(frames.readers) <= frame.index + 3
                seen.append(frame.index)
    assert seen == [0, 1, 2, 3]
    assert not _prefetch_threads()
