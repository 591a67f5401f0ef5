"""Fuzzed sequence folders and trajectory text: each input gives either the right result or a tambridge error
naming the file, the line and what is wrong, never a traceback.

Each test states the reader's rules once, as an oracle (which line is the first bad one and why, which listed
image is read first), and checks the reader against it on every generated input.
"""

import math
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

from tambridge.errors import SequenceFormatError, TrajectoryFormatError
from tambridge.geometry import poses_from_tum
from tambridge.io.tum import MAX_FRAME_INTERVAL_S, associate, open_sequence
from tambridge.trajectory import QUATERNION_NORM_TOLERANCE, parse_tum_trajectory

CAMERA = "width 8\nheight 6\nfx 10\nfy 10\ncx 3.5\ncy 2.5\ndepth_scale 5000\n"
RGB_VALUE, DEPTH_RAW = 90, 9000  # the fixture's images: grey colour, depth 9000 / 5000 = 1.8 m

token = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True).map(repr),
    st.sampled_from(["rgb/1.png", "depth/1.png", "nan", "inf", "-", "", "#", "1e400", "0x10", "1,5"]),
    st.text(alphabet="abc123./ \t#", max_size=8),
)
line = st.lists(token, min_size=0, max_size=4).map(" ".join)
# Lines that parse: a timestamp on the fixture's association grid (1.0 and 1.001) or off it, and an existing image.
listed_image = st.tuples(st.sampled_from(["1.0", "1.001", "1.01", "1.03", "2.0"]),
                         st.sampled_from(["rgb/1.png", "depth/1.png", "rgb/2.png"])).map(" ".join)
index_line = st.one_of(line, listed_image)


@pytest.fixture(scope="module")
def image_folder(tmp_path_factory):
    folder = tmp_path_factory.mktemp("fuzz")
    (folder / "rgb").mkdir()
    (folder / "depth").mkdir()
    cv2.imwrite(str(folder / "rgb/1.png"), np.full((6, 8, 3), RGB_VALUE, np.uint8))
    cv2.imwrite(str(folder / "depth/1.png"), np.full((6, 8), DEPTH_RAW, np.uint16))
    (folder / "camera.txt").write_text(CAMERA)
    return folder


def first_bad_index_line(path: Path, text: str) -> tuple[str, list[tuple[float, str]]]:
    """``(error message start and phrase or "", entries sorted by time)`` for a ``timestamp filename`` list."""
    entries, first_line = [], {}
    for number, raw in enumerate(text.splitlines(), start=1):
        stripped = raw.strip()
        if not stripped or stripped.startswith("#"):
            continue
        parts = stripped.split()
        where = f"{path} line {number}: "
        if len(parts) < 2:
            return where + "|expected 'timestamp filename'", []
        try:
            timestamp = float(parts[0])
        except ValueError:
            return where + "|is not a number", []
        if not math.isfinite(timestamp):
            return where + "|is not finite", []
        if timestamp in first_line:
            return where + f"|is already listed on line {first_line[timestamp]}", []
        first_line[timestamp] = number
        entries.append((timestamp, parts[1]))
    return "", sorted(entries, key=lambda entry: entry[0])


def image_kind(folder: Path, path: Path) -> str:
    """Which of the fixture's two images a listed path is, "folder", or "missing"."""
    if path.is_dir():
        return "folder"
    if not path.is_file():
        return "missing"
    for kind in ("rgb", "depth"):
        if path.resolve() == (folder / kind / "1.png").resolve():
            return kind
    raise AssertionError(f"{path}: the generated name hit a file outside the fixture")


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(rgb_lines=st.lists(index_line, max_size=5), depth_lines=st.lists(index_line, max_size=5))
@example(rgb_lines=["rgb/1.png"], depth_lines=[])  # one column
@example(rgb_lines=["0x10 rgb/1.png"], depth_lines=[])  # not a number
@example(rgb_lines=[], depth_lines=["1e400 depth/1.png"])  # not finite
@example(rgb_lines=["0.5 rgb/1.png"], depth_lines=["0.5 rgb/1.png"])  # first depth is a colour image
@example(rgb_lines=["2.0 rgb/2.png"], depth_lines=["2.0 depth/1.png"])  # a listed colour image is missing
@example(rgb_lines=["1.03 depth/1.png"], depth_lines=["1.03 depth/1.png", "# comment", ""])  # all readable
@example(rgb_lines=[], depth_lines=["1.001 rgb/1.png"])  # a frame listed twice
@example(rgb_lines=["0.0 0.0"], depth_lines=["0.0 /"])  # a folder listed as an image
def test_index_files_give_the_listed_frames_or_an_error_naming_file_and_line(image_folder, rgb_lines, depth_lines):
    rgb_txt, depth_txt = image_folder / "rgb.txt", image_folder / "depth.txt"
    rgb_txt.write_text("\n".join(["1.0 rgb/1.png", *rgb_lines]) + "\n")
    depth_txt.write_text("\n".join(["1.001 depth/1.png", *depth_lines]) + "\n")

    # The oracle. rgb.txt is read before depth.txt, each to its first bad line.
    rgb_error, rgb_entries = first_bad_index_line(rgb_txt, rgb_txt.read_text())
    depth_error, depth_entries = first_bad_index_line(depth_txt, depth_txt.read_text())
    expected_error = rgb_error or depth_error
    for path, entries in [] if expected_error else [(rgb_txt, rgb_entries), (depth_txt, depth_entries)]:
        # Frames 10 s or more apart (median) are taken for stamps in another unit than seconds.
        stamps = np.array([stamp for stamp, _ in entries])
        if len(stamps) > 1 and np.median(np.diff(stamps)) >= MAX_FRAME_INTERVAL_S:
            expected_error = f"{path}: |timestamps must be in seconds"
            break
    if not expected_error:
        # Both lists hold the fixture's own 1.0 / 1.001 pair, so association always finds a frame.
        pairs = associate(np.array([s for s, _ in rgb_entries]), np.array([s for s, _ in depth_entries]))
        rgb_paths = [image_folder / rgb_entries[i][1] for i, _ in pairs]
        depth_paths = [image_folder / depth_entries[j][1] for _, j in pairs]
        # Opening checks every frame's colour then depth file is there; then it reads the first frame's depth (the
        # depth-scale check), then each frame's colour and depth is decoded.
        listed = [item for pair in zip(rgb_paths, depth_paths) for item in (("rgb", pair[0]), ("depth", pair[1]))]
        for wanted, path in listed:
            kind = image_kind(image_folder, path)
            if kind == "folder":
                expected_error = f"{path}: |listed in {wanted}.txt but is a folder, not an image"
            elif kind == "missing":
                expected_error = f"{path}: |image listed in {wanted}.txt does not exist"
            if expected_error:
                break
        for wanted, path in [] if expected_error else [("depth", depth_paths[0])] + listed:
            if wanted == "depth" and image_kind(image_folder, path) == "rgb":
                expected_error = f"{path}: |depth must be a single-channel 16-bit PNG"
                break  # (a depth PNG read as colour is a valid 8-bit grey image)

    if expected_error:
        start, phrase = expected_error.split("|")
        with pytest.raises(SequenceFormatError) as raised:
            sequence = open_sequence(image_folder)
            for index in range(len(sequence)):
                sequence[index]
        message = str(raised.value)
        assert message.startswith(start) and phrase in message and "\n" not in message, (message, expected_error)
    else:
        sequence = open_sequence(image_folder)
        assert len(sequence) == len(pairs)
        np.testing.assert_array_equal(sequence.timestamps_s, [rgb_entries[i][0] for i, _ in pairs])
        for index, path in enumerate(rgb_paths):
            frame = sequence[index]
            # A depth PNG listed as colour reads as grey 8-bit: the high byte of the raw value.
            grey = RGB_VALUE if image_kind(image_folder, path) == "rgb" else DEPTH_RAW >> 8
            assert (frame.rgb == grey).all() and frame.rgb.shape == (6, 8, 3)
            np.testing.assert_allclose(frame.depth_m, DEPTH_RAW / 5000.0, rtol=1e-6)


pose_line = st.lists(st.floats(-10.0, 10.0, allow_subnormal=False).map(repr), min_size=8, max_size=8).map(" ".join)
unit_pose_line = st.tuples(
    st.sampled_from(["1", "2", "2.0", "3"]),  # times that repeat
    st.lists(st.sampled_from([0.0, -0.0, 1.5, -2.0]), min_size=3, max_size=3),
    st.sampled_from([(0.0, 0.0, 0.0, 1.0), (0.0, 0.0, 0.7071, 0.7071), (0.5, -0.5, 0.5, 0.5), (0.6, 0.0, 0.0, 0.8)]),
).map(lambda parts: " ".join([parts[0], *map(repr, parts[1]), *map(repr, parts[2])]))


def first_bad_trajectory_line(text: str, source: str) -> tuple[str, list[np.ndarray]]:
    """``(error message start and phrase or "", the values of every pose line)`` of TUM trajectory text."""
    rows = []
    for number, raw in enumerate(text.splitlines(), start=1):
        stripped = raw.strip()
        if not stripped or stripped.startswith("#"):
            continue
        parts = stripped.replace(",", " ").split()
        where = f"{source} line {number}: "
        if len(parts) != 8:
            return where + f"|expected 8 columns 'timestamp tx ty tz qx qy qz qw', got {len(parts)}", []
        try:
            values = np.array([float(part) for part in parts])
        except ValueError:
            return where + "|is not a number", []
        if not np.isfinite(values).all():
            return where + "|non-finite value", []
        largest = np.abs(values[4:]).max()  # |q| = largest * |q / largest|: no overflow for huge components
        norm = largest * np.linalg.norm(values[4:] / largest) if largest > 0.0 else 0.0
        if not abs(norm - 1.0) <= QUATERNION_NORM_TOLERANCE:
            return where + "|, not 1; the columns must be", []
        rows.append((number, values))
    if not rows:
        return f"{source}: |no poses", []
    # A time listed twice must repeat its pose: the earliest time with a line unlike the one before it with that time.
    before, conflicts = {}, []
    for number, values in rows:
        if values[0] in before and not np.array_equal(before[values[0]][1], values):
            conflicts.append((values[0], before[values[0]][0], number))
        before[values[0]] = (number, values)
    if conflicts:
        _, first, second = min(conflicts)
        return f"{source} line {second}: |is already on line {first} with another pose", []
    return "", [values for _, values in rows]


@settings(max_examples=300, deadline=None)
@given(lines=st.lists(st.one_of(line, pose_line, unit_pose_line), max_size=6))
@example(lines=["1 0 0 0 0 0 0 0"])  # zero quaternion
@example(lines=["1 0 0 0 1e200 1e200 0 0"])  # a quaternion whose squared norm overflows
@example(lines=["2 1 2 3 0 0 0 1", "1 4 5 6 0 0 1 0", "2 7 8 9 1 0 0 0"])  # out of order, one time twice, other poses
@example(lines=["2 1 2 3 0 0 0 1", "1 4 5 6 0 0 1 0", "2.0 1 2 3 0 0 0 1.0"])  # one time twice with its pose
def test_trajectory_text_gives_the_sorted_poses_or_an_error_naming_file_and_line(lines):
    text = "\n".join(lines)
    expected_error, rows = first_bad_trajectory_line(text, "gt.txt")
    if expected_error:
        start, phrase = expected_error.split("|")
        with pytest.raises(TrajectoryFormatError) as raised:
            parse_tum_trajectory(text, "gt.txt")
        message = str(raised.value)
        assert message.startswith(start) and phrase in message and "\n" not in message, (message, expected_error)
        return
    trajectory = parse_tum_trajectory(text, "gt.txt")
    # Sorted by time; a time listed twice (with its pose) once.
    kept = {}
    for values in rows:
        kept.setdefault(values[0], values)
    stamps = sorted(kept)
    np.testing.assert_array_equal(trajectory.timestamps_s, stamps)
    for pose, stamp in zip(trajectory.world_from_camera, stamps):
        quaternion = kept[stamp][4:] / np.abs(kept[stamp][4:]).max()
        np.testing.assert_allclose(pose, poses_from_tum(kept[stamp][1:4], quaternion / np.linalg.norm(quaternion)),
                                   atol=1e-9)
        np.testing.assert_allclose(pose[:3, :3] @ pose[:3, :3].T, np.eye(3), atol=1e-9)


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
    # An empty file, a JPEG without its end marker, a PNG without its IEND chunk, or a PNG cut inside its last chunk:
    # each refused on opening, naming the damaged file.
    if fraction == 0.0:
        reason = "empty file"
    elif kind == "rgb.jpg":
        reason = "JPEG has no end marker"
    elif b"IEND" not in data[: int(len(data) * fraction)]:
        reason = "PNG has no IEND chunk"
    else:
        reason = "PNG chunk 'IEND' is cut short (truncated)"
    with pytest.raises(SequenceFormatError) as raised:
        open_sequence(folder)
    assert str(raised.value).startswith(f"{damaged}: {reason}"), str(raised.value)


@pytest.mark.parametrize("kind", ["rgb", "depth"])
@pytest.mark.parametrize("where", [0, 5, 0.1, 0.5, 0.9])
def test_a_flipped_bit_in_a_png_is_refused_on_opening(synthetic_sequence_dir, tmp_path, kind, where):
    """A PNG of the right length with one bit flipped (in its signature: byte 0 or 5; or at a fraction of the rest)
    is named before any frame is decoded."""
    folder = tmp_path / "seq"
    shutil.copytree(synthetic_sequence_dir, folder)
    sequence = open_sequence(folder)
    damaged = (sequence.rgb_paths if kind == "rgb" else sequence.depth_paths)[-1]
    data = bytearray(damaged.read_bytes())
    position = where if isinstance(where, int) else 8 + int((len(data) - 8) * where)
    data[position] ^= 0x10
    damaged.write_bytes(bytes(data))
    with pytest.raises(SequenceFormatError) as raised:
        open_sequence(folder)
    message = str(raised.value)
    assert message.startswith(f"{damaged}: PNG ") and message.endswith("; re-extract the sequence"), message
    assert any(reason in message for reason in ("fails its checksum (corrupt)", "(truncated)", "signature damaged")), message
    data[position] ^= 0x10
    damaged.write_bytes(bytes(data))
    assert len(open_sequence(folder)) == len(sequence)
