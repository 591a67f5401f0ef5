"""Fuzzed sequence folders: every malformed input gives a tambridge error naming the file, never a traceback."""

import cv2
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from tambridge.errors import TambridgeError
from tambridge.io.tum import open_sequence
from tambridge.trajectory import parse_tum_trajectory

CAMERA = "width 8\nheight 6\nfx 10\nfy 10\ncx 3.5\ncy 2.5\ndepth_scale 5000\n"

token = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True).map(repr),
    st.sampled_from(["rgb/1.png", "depth/1.png", "nan", "inf", "-", "", "#", "1e400", "0x10", "1,5"]),
    st.text(alphabet="abc123./ \t#", max_size=8),
)
line = st.lists(token, min_size=0, max_size=4).map(" ".join)


@pytest.fixture(scope="module")
def image_folder(tmp_path_factory):
    folder = tmp_path_factory.mktemp("fuzz")
    (folder / "rgb").mkdir()
    (folder / "depth").mkdir()
    cv2.imwrite(str(folder / "rgb/1.png"), np.full((6, 8, 3), 90, np.uint8))
    cv2.imwrite(str(folder / "depth/1.png"), np.full((6, 8), 9000, np.uint16))
    (folder / "camera.txt").write_text(CAMERA)
    return folder


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(rgb_lines=st.lists(line, max_size=5), depth_lines=st.lists(line, max_size=5))
def test_garbage_index_files_give_errors_naming_the_file(image_folder, rgb_lines, depth_lines):
    (image_folder / "rgb.txt").write_text("\n".join(["1.0 rgb/1.png", *rgb_lines]) + "\n")
    (image_folder / "depth.txt").write_text("\n".join(["1.001 depth/1.png", *depth_lines]) + "\n")
    try:
        sequence = open_sequence(image_folder)
        for index in range(len(sequence)):
            sequence[index]
    except TambridgeError as error:
        assert "rgb.txt" in str(error) or "depth.txt" in str(error) or ".png" in str(error) or "camera" in str(error)


@settings(max_examples=200, deadline=None)
@given(lines=st.lists(line, max_size=6))
def test_garbage_trajectory_text_gives_a_format_error(lines):
    try:
        trajectory = parse_tum_trajectory("\n".join(lines), "gt.txt")
    except TambridgeError as error:
        assert str(error).startswith("gt.txt")
    else:
        assert np.all(np.diff(trajectory.timestamps_s) > 0)
        assert np.all(np.isfinite(trajectory.world_from_camera))


@pytest.mark.parametrize("fraction", [0.0, 0.3, 0.8, 0.97])
@pytest.mark.parametrize("kind", ["rgb.png", "rgb.jpg", "depth.png"])
def test_truncated_images_are_named(tmp_path, kind, fraction):
    folder = tmp_path / "seq"
    (folder / "rgb").mkdir(parents=True)
    (folder / "depth").mkdir()
    rng = np.random.default_rng(0)
    rgb_name = "rgb/1.jpg" if kind == "rgb.jpg" else "rgb/1.png"
    cv2.imwrite(str(folder / rgb_name), rng.integers(0, 255, (6, 8, 3), dtype=np.uint8))
    cv2.imwrite(str(folder / "depth/1.png"), rng.integers(4000, 20000, (6, 8)).astype(np.uint16))
    (folder / "camera.txt").write_text(CAMERA)
    (folder / "rgb.txt").write_text(f"1.0 {rgb_name}\n")
    (folder / "depth.txt").write_text("1.0 depth/1.png\n")
    damaged = folder / (rgb_name if kind.startswith("rgb") else "depth/1.png")
    data = damaged.read_bytes()
    damaged.write_bytes(data[: int(len(data) * fraction)])
    with pytest.raises(TambridgeError, match=str(damaged.name).replace(".", r"\.")):
        open_sequence(folder)[0]
