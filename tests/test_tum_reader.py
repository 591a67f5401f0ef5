
import re
import subprocess

import cv2
import numpy as np
import pytest

from tambridge.camera import TUM_PRESETS, find_sensor
from tambridge.errors import CameraConfigError, SequenceFormatError
from tambridge.io.tum import associate, inscribed_rectangle, open_sequence


def test_association_matches_nearest_stamps_within_20_ms():
    rgb = np.array([1.000, 1.033, 1.066, 1.100, 1.200])
    depth = np.array([0.990, 1.040, 1.045, 1.070, 1.300])
    # 1.000-0.990 (10 ms), 1.033-1.040 (7 ms; 1.045 is 12 ms), 1.066-1.070 (4 ms); 1.100 and 1.200 have no partner.
    assert associate(rgb, depth) == [(0, 0), (1, 1), (2, 3)]


def test_association_uses_each_stamp_once():
    # Both colour stamps are nearest to depth 1.010; the closer pair (2 ms) wins and 1.000 takes 1.015 (15 ms).
    assert associate(np.array([1.000, 1.012]), np.array([1.010, 1.015])) == [(0, 1), (1, 0)]
    assert associate(np.array([1.000, 1.012]), np.array([1.010])) == [(1, 0)]


def _write_sequence(folder, depth_raw, camera_text=None, rgb_stamps=(1.0, 2.0), depth_stamps=(1.005, 2.005)):
    (folder / "rgb").mkdir(parents=True)
    (folder / "depth").mkdir()
    rgb_lines, depth_lines = [], []
    for stamp in rgb_stamps:
        cv2.imwrite(str(folder / f"rgb/{stamp}.png"), np.full((depth_raw.shape[0], depth_raw.shape[1], 3), 100, np.uint8))
        rgb_lines.append(f"{stamp} rgb/{stamp}.png")
    for stamp in depth_stamps:
        cv2.imwrite(str(folder / f"depth/{stamp}.png"), depth_raw)
        depth_lines.append(f"{stamp} depth/{stamp}.png")
    (folder / "rgb.txt").write_text("# colour\n" + "\n".join(rgb_lines) + "\n")
    (folder / "depth.txt").write_text("# depth\n" + "\n".join(depth_lines) + "\n")
    if camera_text is not None:
        (folder / "camera.txt").write_text(camera_text)


CAMERA_8x6 = "width 8\nheight 6\nfx 10\nfy 10\ncx 3.5\ncy 2.5\ndepth_scale 5000\n"


def test_colour_images_without_depth_are_left_out_and_counted(tmp_path):
    _write_sequence(tmp_path / "seq", np.full((6, 8), 10000, np.uint16), CAMERA_8x6, rgb_stamps=(1.0, 1.5, 2.0, 3.0))
    sequence = open_sequence(tmp_path / "seq", max_frames=1)
    assert len(sequence) == 1 and sequence.colour_images_without_depth == 2


def test_tum_depth_is_scaled_by_5000(tmp_path):
    raw = np.full((6, 8), 10000, np.uint16)
    raw[0, 0] = 0
    _write_sequence(tmp_path / "seq", raw, CAMERA_8x6)
    frame = open_sequence(tmp_path / "seq")[0]
    assert frame.depth_m.dtype == np.float32
    assert frame.depth_m[1, 1] == pytest.approx(2.0)
    assert frame.depth_m[0, 0] == 0.0
    assert frame.rgb.shape == (6, 8, 3) and frame.rgb.dtype == np.uint8


def test_millimetre_depth_with_invalid_value_from_camera_txt(tmp_path):
    raw = np.full((6, 8), 1500, np.uint16)
    raw[2, 3] = 65535
    _write_sequence(tmp_path / "seq", raw, CAMERA_8x6.replace("depth_scale 5000", "depth_scale 1000") + "depth_invalid 65535\n")
    frame = open_sequence(tmp_path / "seq")[0]
    assert frame.depth_m[0, 0] == pytest.approx(1.5)
    assert frame.depth_m[2, 3] == 0.0


def test_stride_and_max_frames(synthetic_sequence_dir):
    sequence = open_sequence(synthetic_sequence_dir, stride=3, max_frames=4)
    assert len(sequence) == 4
    np.testing.assert_allclose(sequence.timestamps_s, np.arange(0, 12, 3) / 30.0)


def test_tum_preset_from_folder_name_and_undistortion(tmp_path):
    assert find_sensor(tmp_path / "rgbd_dataset_freiburg2_xyz") is TUM_PRESETS["fr2"]
    assert find_sensor(tmp_path / "tum_fr3_office") is TUM_PRESETS["fr3"]
    # Only a word of its own names a TUM camera: these name none, and want a camera file.
    for name in ("fr10_garden", "afr1x", "freiburg12"):
        with pytest.raises(CameraConfigError, match="the folder name names no TUM camera"):
            find_sensor(tmp_path / name)
    folder = tmp_path / "rgbd_dataset_freiburg1_test"
    raw = np.full((480, 640), 10000, np.uint16)
    _write_sequence(folder, raw)
    image = np.zeros((480, 640, 3), np.uint8)
    image[:, ::40] = 255  # vertical lines: distortion bends the ones near the border
    cv2.imwrite(str(folder / "rgb/1.0.png"), image)
    sequence = open_sequence(folder)
    assert sequence.camera.distortion == (0.0,) * 5 and sequence.sensor.camera.has_distortion
    undistorted = sequence[0].rgb
    assert not np.array_equal(undistorted[:, :, 0] > 128, image[:, :, 0] > 128)
    # The principal point moves least: the line through the centre column stays within a pixel.
    assert undistorted[255, 319:322, 0].max() > 100
    # Undistortion leaves a border without data; the valid region excludes all of it and little else.
    cv2.imwrite(str(folder / "rgb/1.0.png"), np.full((480, 640, 3), 200, np.uint8))
    top, bottom, left, right = sequence.valid_region
    filled = sequence[0].rgb[:, :, 0] > 0
    assert filled[top:bottom, left:right].all()
    assert not filled.all() and 0.8 < (bottom - top) * (right - left) / filled.size < filled.mean()


def test_inscribed_rectangle_of_a_disc_holds_only_valid_pixels():
    rows, columns = np.mgrid[0:60, 0:80]
    disc = (rows - 30) ** 2 + (columns - 40) ** 2 <= 28**2
    top, bottom, left, right = inscribed_rectangle(disc)
    assert disc[top:bottom, left:right].all()
    # The largest square in a disc of radius 28 has side 28 sqrt(2) = 39.6 px; the greedy box comes close.
    assert (bottom - top) * (right - left) >= 0.85 * 39.6**2
    assert inscribed_rectangle(np.ones((6, 8), bool)) == (0, 6, 0, 8)


def test_seven_scenes_style_folder_loads_without_flags(tmp_path):
    raw = np.full((6, 8), 2000, np.uint16)
    _write_sequence(tmp_path / "kitchen", raw, CAMERA_8x6.replace("depth_scale 5000", "depth_scale 1000.0") + "depth_invalid 65535\n",
                    rgb_stamps=(0.0, 0.033333), depth_stamps=(0.0, 0.033333))
    sequence = open_sequence(tmp_path / "kitchen")
    assert len(sequence) == 2 and sequence.sensor.depth_scale == 1000.0
    assert sequence[1].depth_m[0, 0] == pytest.approx(2.0)


# ---- bad input: one clear error each, naming the file ----


def test_missing_rgb_txt(tmp_path):
    _write_sequence(tmp_path / "seq", np.full((6, 8), 10000, np.uint16), CAMERA_8x6)
    (tmp_path / "seq" / "rgb.txt").unlink()
    with pytest.raises(SequenceFormatError, match=r"rgb\.txt: not found"):
        open_sequence(tmp_path / "seq")


def test_timestamps_with_no_match(tmp_path):
    _write_sequence(tmp_path / "seq", np.full((6, 8), 10000, np.uint16), CAMERA_8x6, depth_stamps=(5.0, 6.0))
    with pytest.raises(SequenceFormatError, match=r"rgb\.txt: no colour timestamp lies within 0\.02 s"):
        open_sequence(tmp_path / "seq")


@pytest.mark.parametrize("content, message", [(b"", "empty file"), (b"\x89PNG\r\n\x1a\nnot really", "PNG has no IEND chunk")])
def test_empty_or_truncated_png_is_refused_on_opening(tmp_path, content, message):
    # Checked for every frame before any is read, so that a run stops before its work and its outputs start.
    _write_sequence(tmp_path / "seq", np.full((6, 8), 10000, np.uint16), CAMERA_8x6)
    (tmp_path / "seq" / "depth" / "2.005.png").write_bytes(content)
    with pytest.raises(SequenceFormatError, match=rf"2\.005\.png: {message}"):
        open_sequence(tmp_path / "seq")


def test_a_phone_jpeg_turned_by_its_exif_orientation_fits_the_camera_and_32_bit_depth_does_not(tmp_path):
    """Stored 6x8 with EXIF orientation 6 (turn a quarter): cv2 decodes it 8x6, as the camera is; the header check
    must read it so too. A 32-bit TIFF depth image (Pillow mode I, as Pillow 9 opens 16-bit PNGs) is refused."""
    import PIL.Image

    _write_sequence(tmp_path / "seq", np.full((6, 8), 10000, np.uint16), CAMERA_8x6)
    folder = tmp_path / "seq"
    exif = PIL.Image.Exif()
    exif[0x0112] = 6
    PIL.Image.fromarray(np.full((8, 6, 3), 100, np.uint8)).save(folder / "rgb/2.0.jpg", exif=exif)
    (folder / "rgb.txt").write_text((folder / "rgb.txt").read_text().replace("rgb/2.0.png", "rgb/2.0.jpg"))
    sequence = open_sequence(folder)
    assert sequence[1].rgb.shape == (6, 8, 3)
    PIL.Image.fromarray(np.full((6, 8), 10000, np.int32)).save(folder / "depth/2.005.tif")
    (folder / "depth.txt").write_text((folder / "depth.txt").read_text().replace("depth/2.005.png", "depth/2.005.tif"))
    with pytest.raises(SequenceFormatError, match=r"2\.005\.tif: depth must be a single-channel 16-bit PNG, got Pillow mode I;"):
        open_sequence(folder)


def test_png_that_ends_right_but_does_not_decode_is_named_on_opening_or_reading(tmp_path):
    _write_sequence(tmp_path / "seq", np.full((6, 8), 10000, np.uint16), CAMERA_8x6)
    broken = tmp_path / "seq" / "depth" / "2.005.png"
    # Bytes that are no chunk between the signature and IEND: refused on opening.
    broken.write_bytes(b"\x89PNG\r\n\x1a\nnot really\0\0\0\0IEND\xaeB`\x82")
    with pytest.raises(SequenceFormatError, match=r"2\.005\.png: PNG chunk 'real' is cut short \(truncated\)"):
        open_sequence(tmp_path / "seq")
    # Whole chunks with right checksums but no image header: named when the frame is read.
    broken.write_bytes(b"\x89PNG\r\n\x1a\n\0\0\0\0IEND\xaeB`\x82")
    sequence = open_sequence(tmp_path / "seq")
    with pytest.raises(SequenceFormatError, match=r"2\.005\.png: cannot decode image"):
        sequence[1]


def test_eight_bit_depth(tmp_path):
    _write_sequence(tmp_path / "seq", np.full((6, 8), 100, np.uint8), CAMERA_8x6)
    with pytest.raises(SequenceFormatError, match=r"1\.005\.png: depth must be a single-channel 16-bit PNG"):
        open_sequence(tmp_path / "seq")


def test_implausible_depth_scale(tmp_path):
    # A scale of 1 puts a 2 m wall (2000 mm) at 2 km.
    _write_sequence(tmp_path / "seq", np.full((6, 8), 2000, np.uint16), CAMERA_8x6.replace("depth_scale 5000", "depth_scale 1"))
    with pytest.raises(SequenceFormatError, match=r"1\.005\.png: median depth is 2e\+03 m .*set depth_scale"):
        open_sequence(tmp_path / "seq")


def test_folder_that_is_not_a_sequence(tmp_path):
    (tmp_path / "photos").mkdir()
    with pytest.raises(SequenceFormatError, match="not a sequence folder"):
        open_sequence(tmp_path / "photos")
    with pytest.raises(SequenceFormatError, match="not a folder"):
        open_sequence(tmp_path / "missing")


def test_an_associations_file_alone_is_named_with_commands_that_make_the_index_files(tmp_path):
    _write_sequence(tmp_path / "seq", np.full((6, 8), 10000, np.uint16), CAMERA_8x6)
    folder = tmp_path / "seq"
    expected = open_sequence(folder)
    rows = zip(*(open(folder / name).read().splitlines()[1:] for name in ("rgb.txt", "depth.txt")))
    (folder / "associations.txt").write_text("".join(f"{rgb} {depth}\n" for rgb, depth in rows))
    (folder / "rgb.txt").unlink()
    (folder / "depth.txt").unlink()
    with pytest.raises(SequenceFormatError, match="has associations.txt but no rgb.txt or depth.txt; write them") as refused:
        open_sequence(folder)
    # The message's own commands make a sequence of the same frames.
    commands = str(refused.value).split("lines: ", 1)[1].rstrip(")")
    subprocess.run(commands, shell=True, cwd=folder, check=True)
    made = open_sequence(folder)
    np.testing.assert_array_equal(made.timestamps_s, expected.timestamps_s)
    assert made.depth_paths == expected.depth_paths and made.rgb_paths == expected.rgb_paths


@pytest.mark.parametrize("stamps, unit, factor", [((1305031102175.0, 1305031102208.0), "milliseconds", "1000"),
                                                  ((1305031102175304000.0, 1305031102208564000.0), "nanoseconds", "1e+09"),
                                                  ((1305031102175304.0, 1305031102208564.0), "microseconds", "1e+06"),
                                                  ((1305031102175000000.0, 1305031102180000000.0), "nanoseconds", "1e+09")])
def test_stamps_in_another_unit_than_seconds_are_named(tmp_path, stamps, unit, factor):
    """A recorder's milli-, micro- or nanoseconds: a 30 Hz camera's frames would lie 33 units apart, half a minute;
    a 200 Hz camera's nanoseconds (5e6 apart) are named as such, not as a 0.2 Hz camera's microseconds."""
    _write_sequence(tmp_path / "seq", np.full((6, 8), 10000, np.uint16), CAMERA_8x6, rgb_stamps=stamps, depth_stamps=stamps)
    with pytest.raises(SequenceFormatError, match=rf"rgb\.txt: its frames lie .* apart \(median\); timestamps must be in "
                                                  rf"seconds, and these look like {unit}: divide them by {re.escape(factor)}$"):
        open_sequence(tmp_path / "seq")


def test_unknown_camera_without_camera_file(tmp_path):
    _write_sequence(tmp_path / "mycam", np.full((6, 8), 10000, np.uint16))
    with pytest.raises(CameraConfigError, match="pass --camera camera.yaml"):
        open_sequence(tmp_path / "mycam")


@pytest.mark.parametrize("name, image, message", [
    ("rgb/2.0.png", np.zeros((5, 8, 3), np.uint8),
     r"rgb/2\.0\.png: image is 8x5 but the camera is 8x6; fix width/height in camera\.yaml \(--camera\), or this image "
     r"if the sequence's others are 8x6$"),
    ("rgb/2.0.jpg", np.zeros((6, 9, 3), np.uint8), r"rgb/2\.0\.jpg: image is 9x6 but the camera is 8x6"),
    ("depth/2.005.png", np.full((6, 8), 100, np.uint8),
     r"depth/2\.005\.png: depth must be a single-channel 16-bit PNG, got an 8-bit grey image; 8-bit or colour depth "
     r"loses the range \(re-export depth as uint16\)$"),
    ("depth/2.005.png", np.full((6, 8, 3), 10000, np.uint16), r"depth/2\.005\.png: depth must be a single-channel 16-bit PNG, got"),
    ("depth/2.005.png", np.full((5, 8), 10000, np.uint16),
     r"depth/2\.005\.png: depth is 8x5 but its colour image 2\.0\.png is 8x6; colour and depth must be registered$"),
])
def test_an_odd_image_after_the_first_frame_is_refused_on_opening(tmp_path, name, image, message):
    """Every frame's sizes and depth format come from the images' headers before a run starts, not when it reaches
    them (the first frame is read whole)."""
    _write_sequence(tmp_path / "seq", np.full((6, 8), 10000, np.uint16), CAMERA_8x6)
    folder = tmp_path / "seq"
    cv2.imwrite(str(folder / name), image)
    if name.endswith(".jpg"):
        (folder / "rgb.txt").write_text((folder / "rgb.txt").read_text().replace("rgb/2.0.png", name))
    with pytest.raises(SequenceFormatError, match=message):
        open_sequence(folder)


def test_garbage_index_line_names_the_line(tmp_path):
    _write_sequence(tmp_path / "seq", np.full((6, 8), 10000, np.uint16), CAMERA_8x6)
    with open(tmp_path / "seq" / "rgb.txt", "a") as index:
        index.write("not-a-number rgb/x.png\n")
    with pytest.raises(SequenceFormatError, match=r"rgb\.txt line 4: timestamp 'not-a-number' is not a number"):
        open_sequence(tmp_path / "seq")
