"""Inputs that used to pass silently or with a traceback: each is refused with one line naming the file and the fix."""

from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from tambridge.camera import load_sensor_file
from tambridge.errors import CameraConfigError, SequenceFormatError, TrajectoryFormatError
from tambridge.io.tum import DEPTH_CHECK_FRAMES, open_sequence, read_file_list
from tambridge.trajectory import read_tum_trajectory

CONFIGS = Path(__file__).resolve().parents[1] / "configs"
CAMERA = {"width": 8, "height": 6, "fx": 10.0, "fy": 10.0, "cx": 3.5, "cy": 2.5, "depth_scale": 5000.0}


def write_sequence(folder, depth_frames, camera=CAMERA):
    """A TUM-layout folder with one colour image per depth frame ((H, W) uint16 raw depth each)."""
    (folder / "rgb").mkdir(parents=True)
    (folder / "depth").mkdir()
    rgb_lines, depth_lines = [], []
    for index, raw in enumerate(depth_frames):
        cv2.imwrite(str(folder / f"rgb/{index}.png"), np.full((*raw.shape, 3), 100, np.uint8))
        cv2.imwrite(str(folder / f"depth/{index}.png"), raw)
        rgb_lines.append(f"{index}.0 rgb/{index}.png")
        depth_lines.append(f"{index}.0 depth/{index}.png")
    (folder / "rgb.txt").write_text("\n".join(rgb_lines) + "\n")
    (folder / "depth.txt").write_text("\n".join(depth_lines) + "\n")
    (folder / "camera.yaml").write_text(yaml.safe_dump(camera))
    return folder


def depth(value):
    return np.full((6, 8), value, np.uint16)


def test_a_camera_file_without_depth_scale_is_refused(tmp_path):
    values = {key: value for key, value in CAMERA.items() if key != "depth_scale"}
    path = tmp_path / "camera.yaml"
    path.write_text(yaml.safe_dump(values))
    with pytest.raises(CameraConfigError, match=r"camera\.yaml: missing depth_scale"):
        load_sensor_file(path)


@pytest.mark.parametrize("suffix", [".yaml", ".txt"])
def test_a_misspelt_camera_key_is_refused_by_name(tmp_path, suffix):
    # exposure_sec would otherwise leave exposure_s unset, and blur modelling off, without a word.
    values = {**CAMERA, "exposure_sec": 0.03}
    path = tmp_path / f"camera{suffix}"
    path.write_text(yaml.safe_dump(values) if suffix == ".yaml" else "".join(f"{k} {v}\n" for k, v in values.items()))
    with pytest.raises(CameraConfigError, match=rf"camera\{suffix}: unknown key exposure_sec; a camera file takes .*exposure_s"):
        load_sensor_file(path)
    path.write_text(path.read_text().replace("exposure_sec", "exposure_s"))
    assert load_sensor_file(path).exposure_s == pytest.approx(0.03)


@pytest.mark.parametrize("key", ["depth_scale", "fx", "cy"])
@pytest.mark.parametrize("value", [".nan", ".inf", "-.inf"])
def test_nan_or_inf_in_a_camera_key_is_refused_by_name(tmp_path, key, value):
    path = tmp_path / "camera.yaml"
    path.write_text(yaml.safe_dump(CAMERA).replace(f"{key}: {CAMERA[key]}", f"{key}: {value}"))
    with pytest.raises(CameraConfigError, match=rf"camera\.yaml: {key} is .*finite"):
        load_sensor_file(path)


@pytest.mark.parametrize("key, value, expected", [("fx", "[1, 2]", "a number"), ("depth_scale", "millimetres", "a number"),
                                                  ("distortion", "[0.1, fast, 0, 0, 0]", "a list of numbers"),
                                                  ("fx", "yes", "a number"), ("distortion", "[0, 0, 0, 0, true]", "a list of numbers"),
                                                  ("width", "160.5", "a whole number of pixels")])
def test_a_camera_key_that_is_not_a_number_is_refused_by_name(tmp_path, key, value, expected):
    path = tmp_path / "camera.yaml"
    path.write_text(yaml.safe_dump({**CAMERA, key: 0}).replace(f"{key}: 0", f"{key}: {value}"))
    with pytest.raises(CameraConfigError, match=rf"camera\.yaml: {key} is .*; expected {expected}$"):
        load_sensor_file(path)


@pytest.mark.parametrize("extra, message", [
    ({"distortion": 0.1}, "distortion is 0.1; expected a list of numbers"),
    ({"distortion": []}, "distortion is an empty list; give its numbers, or leave the key out"),
    ({"distortion": [0.1, 0, 0, 0, 0], "d0": 0.2}, "gives distortion and d0; give the coefficients one way"),
    ({"depth_invalid": 1.5}, "depth_invalid is 1.5; expected the raw 16-bit value (an integer 0-65535)"),
    ({"depth_invalid": 70000}, "depth_invalid is 70000; expected the raw 16-bit value"),
    ({"colour_width": 320}, "has colour_width but not colour_fx, colour_fy, colour_cx, colour_cy, colour_from_depth"),
])
def test_a_camera_value_that_would_be_dropped_or_misread_is_refused(tmp_path, extra, message):
    path = tmp_path / "camera.yaml"
    path.write_text(yaml.safe_dump({**CAMERA, **extra}))
    with pytest.raises(CameraConfigError) as refused:
        load_sensor_file(path)
    assert str(refused.value).startswith(f"{path}: {message}")


def test_a_camera_key_given_twice_is_refused_with_its_line(tmp_path):
    path = tmp_path / "camera.yaml"
    path.write_text(yaml.safe_dump(CAMERA) + "fx: 12.0\n")
    with pytest.raises(CameraConfigError, match=r"camera\.yaml: not valid YAML \(key 'fx' is given twice at line 8, column 1\)"):
        load_sensor_file(path)


def test_a_camera_txt_key_given_twice_is_refused_with_its_line(tmp_path):
    path = tmp_path / "camera.txt"
    path.write_text("".join(f"{key} {value}\n" for key, value in CAMERA.items()) + "fx 12\n")
    with pytest.raises(CameraConfigError, match=r"camera\.txt line 8: fx is given twice; keep one of its lines"):
        load_sensor_file(path)


def test_null_camera_keys_are_unset(tmp_path):
    path = tmp_path / "camera.yaml"
    path.write_text(yaml.safe_dump({**CAMERA, "distortion": None, "d0": 0.1, "colour_distortion": None}))
    sensor = load_sensor_file(path)
    assert sensor.camera.distortion == (0.1, 0.0, 0.0, 0.0, 0.0) and sensor.colour_camera is None


def test_a_camera_named_by_its_checkout_name_is_found_from_any_folder(tmp_path, monkeypatch):
    from tambridge.camera import find_sensor

    monkeypatch.chdir(tmp_path)
    named, kinect = find_sensor(tmp_path, Path("7scenes_kinect")), load_sensor_file(CONFIGS / "cameras" / "7scenes_kinect.yaml")
    assert repr(named) == repr(kinect) and named.colour_camera is not None


def test_a_camera_path_that_is_a_folder_is_refused_as_such(tmp_path):
    with pytest.raises(CameraConfigError, match=r": is a folder; pass --camera the camera file \(camera\.yaml\) itself$"):
        load_sensor_file(tmp_path)


def test_principal_point_outside_the_image_is_refused(tmp_path):
    path = tmp_path / "camera.yaml"
    path.write_text(yaml.safe_dump({**CAMERA, "cx": 80.0}))
    with pytest.raises(CameraConfigError, match=r"principal point cx=80"):
        load_sensor_file(path)


@pytest.mark.parametrize("count, accepted", [(3, False), (4, True), (5, True), (6, False), (8, True), (14, True)])
def test_distortion_has_an_opencv_length(tmp_path, count, accepted):
    path = tmp_path / "camera.yaml"
    path.write_text(yaml.safe_dump({**CAMERA, "distortion": [0.0] * count}))
    if accepted:
        assert len(load_sensor_file(path).camera.distortion) == count
    else:
        with pytest.raises(CameraConfigError, match=rf"distortion has {count} coefficients"):
            load_sensor_file(path)


def test_millimetre_depth_read_with_the_tum_scale_is_refused(tmp_path):
    # 400 mm read at TUM's 5000 units per metre is 8 cm: closer than any RGB-D sensor sees.
    folder = write_sequence(tmp_path / "seq", [depth(400)] * 3)
    with pytest.raises(SequenceFormatError, match=r"depth/0\.png: median depth is 0\.08 m .*depth_scale"):
        open_sequence(folder)


def test_the_depth_scale_is_checked_on_the_first_frame_with_depth(tmp_path):
    # Blank first frames no longer skip the check: frame 3 has millimetre depth read at TUM's scale.
    folder = write_sequence(tmp_path / "seq", [depth(0)] * 3 + [depth(400)] * 2)
    with pytest.raises(SequenceFormatError, match=r"depth/3\.png: median depth"):
        open_sequence(folder)
    plausible = write_sequence(tmp_path / "ok", [depth(0)] * 3 + [depth(10000)] * 2)
    assert len(open_sequence(plausible)) == 5


def test_depth_at_65535_without_depth_invalid_is_refused_naming_the_key(tmp_path):
    """A sensor that marks missing depth with 65535 (7-Scenes, some drivers) and a camera file without depth_invalid:
    those pixels would be map geometry 65.5 m away (millimetres)."""
    millimetres = {**CAMERA, "depth_scale": 1000.0}
    frame = depth(2000)
    frame[0, :2] = 65535  # 2 of 48 pixels
    folder = write_sequence(tmp_path / "seq", [frame] * 2, millimetres)
    with pytest.raises(SequenceFormatError, match=r"depth/0\.png: 4% of its pixels are 65535, the largest 16-bit value "
                                                  r"\(65\.5 m at depth_scale 1000\); if it marks pixels without depth, "
                                                  r"set depth_invalid: 65535 in camera\.yaml \(--camera\)$"):
        open_sequence(folder)
    marked = write_sequence(tmp_path / "marked", [frame] * 2, {**millimetres, "depth_invalid": 65535})
    assert open_sequence(marked)[0].depth_m[0, 0] == 0.0


def test_a_sequence_without_any_depth_is_refused(tmp_path):
    folder = write_sequence(tmp_path / "seq", [depth(0)] * (DEPTH_CHECK_FRAMES + 5))
    with pytest.raises(SequenceFormatError, match=r"depth\.txt: none of 30 depth images checked .* has valid depth"):
        open_sequence(folder)


@pytest.mark.parametrize("max_frames", [0, -1])
def test_max_frames_below_one_is_refused(tmp_path, max_frames):
    folder = write_sequence(tmp_path / "seq", [depth(10000)] * 3)
    with pytest.raises(SequenceFormatError, match=rf"max_frames must be >= 1 .* got {max_frames}"):
        open_sequence(folder, max_frames=max_frames)


def test_an_index_file_listing_a_frame_twice_is_refused(tmp_path):
    folder = write_sequence(tmp_path / "seq", [depth(10000)] * 2)
    lines = (folder / "rgb.txt").read_text().splitlines()
    (folder / "rgb.txt").write_text("\n".join(line for line in lines for _ in range(2)) + "\n")
    with pytest.raises(SequenceFormatError, match=r"rgb\.txt line 2: timestamp 0\.0 is already listed on line 1"):
        open_sequence(folder)


def test_index_file_encodings(tmp_path):
    folder = write_sequence(tmp_path / "seq", [depth(10000)] * 2)
    text = (folder / "rgb.txt").read_text()
    (folder / "rgb.txt").write_bytes(b"\xef\xbb\xbf" + text.encode())
    assert read_file_list(folder / "rgb.txt") == [(0.0, "rgb/0.png"), (1.0, "rgb/1.png")]
    (folder / "rgb.txt").write_bytes(text.encode("utf-16"))
    with pytest.raises(SequenceFormatError, match=r"rgb\.txt: is UTF-16 text; save it as UTF-8"):
        open_sequence(folder)
    (folder / "rgb.txt").write_bytes(text.encode() + b"1.5 rgb/\xe9.png\n")
    with pytest.raises(SequenceFormatError, match=r"rgb\.txt: is not UTF-8 text \(byte 0xe9"):
        open_sequence(folder)


def test_a_ground_truth_file_in_utf16_is_named(tmp_path):
    path = tmp_path / "groundtruth.txt"
    path.write_bytes("1.0 0 0 0 0 0 0 1\n".encode("utf-16"))
    with pytest.raises(TrajectoryFormatError, match=r"groundtruth\.txt: is UTF-16"):
        read_tum_trajectory(path)


def test_a_file_name_with_a_space_is_read(tmp_path):
    folder = write_sequence(tmp_path / "seq", [depth(10000)] * 2)
    (folder / "rgb/0.png").rename(folder / "rgb/frame 0.png")
    (folder / "rgb.txt").write_text("0.0 rgb/frame 0.png\n1.0 rgb/1.png\n")
    sequence = open_sequence(folder)
    assert sequence.rgb_paths[0] == folder / "rgb/frame 0.png"
    assert sequence[0].rgb.shape == (6, 8, 3)


def test_an_image_is_decoded_by_its_content_and_a_folder_is_named(tmp_path):
    folder = write_sequence(tmp_path / "seq", [depth(10000)] * 2)
    # A PNG named .jpg decodes (by content), where the JPEG end-marker check used to refuse it.
    (folder / "rgb/0.png").rename(folder / "rgb/0.jpg")
    (folder / "rgb.txt").write_text("0.0 rgb/0.jpg\n1.0 rgb/1.png\n")
    assert open_sequence(folder)[0].rgb.mean() == pytest.approx(100)
    # A truncated JPEG named .png is still caught by its missing end marker.
    ok, encoded = cv2.imencode(".jpg", np.full((6, 8, 3), 100, np.uint8))
    (folder / "rgb/1.png").write_bytes(encoded.tobytes()[:-2])
    with pytest.raises(SequenceFormatError, match=r"rgb/1\.png: JPEG has no end marker"):
        open_sequence(folder)[1]
    (folder / "rgb/1.png").unlink()
    (folder / "rgb/1.png").mkdir()
    with pytest.raises(SequenceFormatError, match=r"rgb/1\.png: listed in rgb\.txt but is a folder"):
        open_sequence(folder)[1]
