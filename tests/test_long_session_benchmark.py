"""benchmarks/long_session.py's sequence of laps: each lap the source's frames again, later by one offset, its
ground truth re-stamped alike, and the reader pairing laps x the source's frames."""

import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.long_session import build_laps  # noqa: E402
from tambridge.io.synthetic import SynthOptions, write_synthetic_sequence  # noqa: E402
from tambridge.io.tum import open_sequence  # noqa: E402


def test_three_laps_are_the_source_three_times_one_offset_apart(tmp_path):
    source = tmp_path / "room"
    write_synthetic_sequence(source, SynthOptions(frame_count=8, width=32, height=24))
    layout = build_laps(source, tmp_path / "room_laps3", 3)
    original, lapped = open_sequence(source), open_sequence(tmp_path / "room_laps3")
    assert len(lapped) == layout["frames"] == 3 * len(original)
    interval_s = float(np.median(np.diff(original.timestamps_s)))
    # The next lap's first frame follows the last one as the recording's next frame would.
    assert abs(layout["offset_s"] - (original.timestamps_s[-1] - original.timestamps_s[0] + interval_s)) < 1e-6
    for lap in range(3):
        frames = slice(lap * len(original), (lap + 1) * len(original))
        np.testing.assert_allclose(lapped.timestamps_s[frames], original.timestamps_s + lap * layout["offset_s"], atol=1e-6)
        assert [path.resolve() for path in lapped.rgb_paths[frames]] == [path.resolve() for path in original.rgb_paths]
        truth = lapped.ground_truth.nearest(lapped.timestamps_s[frames])
        np.testing.assert_allclose(truth.world_from_camera, original.ground_truth.nearest(original.timestamps_s).world_from_camera,
                                   atol=1e-9)
        np.testing.assert_allclose(truth.timestamps_s, lapped.timestamps_s[frames], atol=1e-6)
