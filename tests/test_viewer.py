"""The rerun live view: a short recording saved to .rrd and read back with rerun's own API holds the trajectory."""

import numpy as np
import pytest

from tambridge.io.synthetic import default_camera, loop_path
from tambridge.viewer import RerunViewer, ViewerError, parse_viewer_spec

rr = pytest.importorskip("rerun", reason="rerun-sdk is not installed (pip install rerun-sdk)")


def _read_chunks(path):
    try:
        from rerun.chunk import RrdReader
    except ImportError:
        pytest.skip(f"rerun-sdk {rr.__version__} cannot read recordings back (rerun.chunk.RrdReader is 0.41+)")
    chunks = {}
    for chunk in RrdReader(path).stream().collect().stream():
        chunks.setdefault(chunk.entity_path, []).append(chunk.to_record_batch())
    return chunks


def _column(batches, name):
    return [value for batch in batches if name in batch.schema.names for value in batch.column(name).to_pylist()]


def test_recording_holds_the_trajectory(tmp_path):
    camera = default_camera(32, 24)
    poses = loop_path(6)
    viewer = RerunViewer(f"rerun:{tmp_path / 'run.rrd'}", camera)
    rng = np.random.default_rng(0)
    for index, pose in enumerate(poses):
        rgb = rng.integers(0, 255, (24, 32, 3), np.uint8)
        viewer.log_frame(index, index / 30.0, pose, rgb, np.full((24, 32), 1.5, np.float32), is_keyframe=index % 2 == 0)
    viewer.log_sparse_map(5, 5 / 30.0, rng.normal(size=(20, 3)), rng.integers(0, 255, (20, 3), np.uint8))
    viewer.log_gaussians(5, 5 / 30.0, rng.normal(size=(30, 3)), rng.uniform(size=(30, 3)), np.full(30, 0.01))
    viewer.log_render(5, 5 / 30.0, rng.integers(0, 255, (24, 32, 3), np.uint8))
    viewer.close()

    chunks = _read_chunks(tmp_path / "run.rrd")
    translations = np.array([row[0] for row in _column(chunks["/world/camera"], "Transform3D:translation")])
    frames = _column(chunks["/world/camera"], "frame")
    np.testing.assert_allclose(translations[np.argsort(frames)], poses[:, :3, 3], atol=1e-6)
    strips = _column(chunks["/world/trajectory"], "LineStrips3D:strips")
    longest = max(strips, key=lambda strip: len(strip[0]))[0]
    np.testing.assert_allclose(np.array(longest), poses[:, :3, 3], atol=1e-6)
    keyframes = _column(chunks["/world/keyframes"], "Points3D:positions")
    np.testing.assert_allclose(np.array(max(keyframes, key=len)), poses[::2, :3, 3], atol=1e-6)
    for entity in ("/world/camera/image", "/world/camera/depth", "/world/map_points", "/world/gaussians", "/render"):
        assert entity in chunks, entity
    assert len(_column(chunks["/world/gaussians"], "Points3D:positions")[0]) == 30


def test_viewer_spec():
    assert parse_viewer_spec("rerun") is None
    assert str(parse_viewer_spec("rerun:out/run.rrd")) == "out/run.rrd"
    for bad in ("rerun:", "open3d", "rerun.rrd"):
        with pytest.raises(ViewerError, match="expected 'rerun'"):
            parse_viewer_spec(bad)
