"""``tambridge index``: a folder of color/ and depth/ images (Open3D's recorder's layout) made a TUM-layout sequence
that reads back as the sequence it was made from; bad folders refused in one line before anything is written."""

import json
import re
import shutil

import numpy as np
import pytest
from click.testing import CliRunner

from cli import main
from tambridge.errors import CameraConfigError, SequenceFormatError
from tambridge.io.image_folders import camera_values_from_open3d, find_image_folders, write_tum_index
from tambridge.io.synthetic import SynthOptions, write_synthetic_sequence
from tambridge.io.tum import open_sequence

FRAMES = 12


@pytest.fixture(scope="module")
def tum_sequence(tmp_path_factory):
    folder = tmp_path_factory.mktemp("image_folders") / "room"
    write_synthetic_sequence(folder, SynthOptions(frame_count=FRAMES, width=64, height=48))
    return folder


def _open3d_layout(tum_sequence, folder, intrinsic=True):
    """The TUM sequence as Open3D's recorder would write it: color/0.png .. and depth/0.png .. (unpadded, so that
    name order is not text order), camera_intrinsic.json, no index files."""
    source = open_sequence(tum_sequence)
    (folder / "color").mkdir(parents=True)
    (folder / "depth").mkdir()
    for index, (rgb, depth) in enumerate(zip(source.rgb_paths, source.depth_paths)):
        shutil.copyfile(rgb, folder / "color" / f"{index}.png")
        shutil.copyfile(depth, folder / "depth" / f"{index}.png")
    camera = source.camera
    if intrinsic:
        (folder / "camera_intrinsic.json").write_text(json.dumps({
            "width": camera.width, "height": camera.height,
            "intrinsic_matrix": [camera.fx, 0, 0, 0, camera.fy, 0, camera.cx, camera.cy, 1]}))
    return source


def test_an_indexed_open3d_folder_reads_as_the_sequence_it_was_made_from(tum_sequence, tmp_path):
    folder = tmp_path / "recording"
    source = _open3d_layout(tum_sequence, folder)
    depth_scale = source.sensor.depth_scale
    result = CliRunner().invoke(main, ["index", str(folder), "--rate", "30", "--depth-scale", str(depth_scale)])
    assert result.exit_code == 0, result.output
    assert result.output == f"wrote rgb.txt and depth.txt of {FRAMES} frames, camera.yaml from camera_intrinsic.json to {folder}\n"
    indexed = open_sequence(folder)
    assert indexed.camera == source.camera and indexed.sensor.depth_scale == depth_scale
    np.testing.assert_allclose(indexed.timestamps_s, np.arange(FRAMES) / 30.0, atol=1e-6)
    # Frame order is the names' numbers (10 after 9), not their text order.
    assert [path.name for path in indexed.rgb_paths] == [f"{index}.png" for index in range(FRAMES)]
    for index in (0, 9, 10, FRAMES - 1):
        assert np.array_equal(indexed[index].rgb, source[index].rgb)
        assert np.array_equal(indexed[index].depth_m, source[index].depth_m)


def test_a_colour_image_without_depth_is_listed_in_rgb_txt_alone(tum_sequence, tmp_path):
    folder = tmp_path / "recording"
    _open3d_layout(tum_sequence, folder, intrinsic=False)
    (folder / "depth" / "5.png").unlink()
    shutil.copyfile(tum_sequence / "camera.yaml", folder / "camera.yaml")
    images = write_tum_index(folder, 15.0)
    assert images.rgb_only == ["color/5.png"] and len(images.rgb_names) == FRAMES - 1
    indexed = open_sequence(folder)
    assert len(indexed) == FRAMES - 1 and "5.png" not in [path.name for path in indexed.rgb_paths]
    rgb_lines = [line.split() for line in (folder / "rgb.txt").read_text().splitlines() if not line.startswith("#")]
    assert rgb_lines[5] == [f"{5 / 15.0:.6f}", "color/5.png"] and len(rgb_lines) == FRAMES


def test_a_folder_of_images_without_index_files_is_told_the_command_that_writes_them(tum_sequence, tmp_path):
    folder = tmp_path / "recording"
    _open3d_layout(tum_sequence, folder)
    with pytest.raises(SequenceFormatError, match=rf"^{folder}: has color/ and depth/ images but no rgb\.txt or depth\.txt; "
                                                  rf"write them with 'tambridge index {folder} --rate HZ --depth-scale 1000' "
                                                  r"\(HZ: your camera's frames per second, 1000: depth units per metre\)$"):
        open_sequence(folder)


def test_camera_values_are_read_from_open3d_column_by_column(tmp_path):
    path = tmp_path / "camera_intrinsic.json"
    path.write_text(json.dumps({"width": 640, "height": 480, "intrinsic_matrix": [615.2, 0, 0, 0, 614.8, 0, 321.4, 238.9, 1]}))
    assert camera_values_from_open3d(path, 1000.0) == {"width": 640, "height": 480, "fx": 615.2, "fy": 614.8, "cx": 321.4,
                                                       "cy": 238.9, "depth_scale": 1000.0}
    # Row by row (cx in the third entry) is not Open3D's layout.
    path.write_text(json.dumps({"width": 640, "height": 480, "intrinsic_matrix": [615.2, 0, 321.4, 0, 614.8, 238.9, 0, 0, 1]}))
    with pytest.raises(CameraConfigError, match=r"intrinsic_matrix must hold the 9 entries of fx 0 0, 0 fy 0, cx cy 1"):
        camera_values_from_open3d(path, 1000.0)


@pytest.mark.parametrize("change, arguments, message", [
    ("none", ["--rate", "30"], r"camera_intrinsic\.json: holds no depth scale; pass --depth-scale \(depth units per metre"),
    ("none", ["--rate", "0", "--depth-scale", "1000"], r"--rate 0\.0: the camera's frames per second must be above 0"),
    ("none", ["--rate", "30", "--depth-scale", "-1000"], r"camera_intrinsic\.json: .*depth_scale"),
    ("no_intrinsic", ["--rate", "30", "--depth-scale", "1000"], r"--depth-scale goes into a camera\.yaml made from Open3D's"),
    ("rgb_txt", ["--rate", "30", "--depth-scale", "1000"], r"rgb\.txt: already there; remove it to write it again"),
    ("renamed", ["--rate", "30", "--depth-scale", "1000"], r"no colour image has a depth image of the same name in depth/"),
    ("no_depth", ["--rate", "30"], r"no colour image folder \(rgb, color, colour, image\) beside a depth/ folder"),
    ("a_file", ["--rate", "30"], r"color: not a folder; pass the folder that holds the color/ and depth/ folders"),
])
def test_bad_folders_are_refused_in_one_line_writing_nothing(tum_sequence, tmp_path, change, arguments, message):
    folder = tmp_path / "recording"
    _open3d_layout(tum_sequence, folder, intrinsic=change != "no_intrinsic")
    if change == "rgb_txt":
        (folder / "rgb.txt").write_text("# the user's own\n")
    elif change == "renamed":
        for path in (folder / "depth").iterdir():
            path.rename(path.with_name(f"d{path.name}"))
    elif change == "no_depth":
        shutil.rmtree(folder / "depth")
    target = folder
    if change == "a_file":  # the colour folder given, and a file at that
        target = folder / "color"
        shutil.rmtree(target)
        target.write_text("not images\n")
    before = sorted(path.name for path in folder.iterdir())
    result = CliRunner().invoke(main, ["index", str(target), *arguments])
    assert result.exit_code == 2, result.output
    lines = result.output.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: ") and re.search(message, lines[0]), lines
    assert sorted(path.name for path in folder.iterdir()) == before
    if change == "rgb_txt":
        assert (folder / "rgb.txt").read_text() == "# the user's own\n"
    assert not (folder / "camera.yaml").exists()


def test_a_folder_whose_images_do_not_pair_is_told_so(tum_sequence, tmp_path):
    folder = tmp_path / "recording"
    _open3d_layout(tum_sequence, folder)
    for path in (folder / "depth").iterdir():
        path.rename(path.with_name(f"depth_{path.name}"))
    with pytest.raises(SequenceFormatError, match=r"has color/ and depth/ folders but no rgb\.txt or depth\.txt, and no "
                                                  r"colour image has a depth image of the same name to pair with"):
        open_sequence(folder)


def test_the_folders_own_camera_yaml_is_kept_beside_open3ds_intrinsics(tum_sequence, tmp_path):
    folder = tmp_path / "recording"
    source = _open3d_layout(tum_sequence, folder)
    own = (tum_sequence / "camera.yaml").read_text()
    (folder / "camera.yaml").write_text(own)
    with pytest.raises(SequenceFormatError, match=rf"write them with 'tambridge index {folder} --rate HZ' \(HZ: your "
                                                  r"camera's frames per second\)$"):
        open_sequence(folder)
    images = write_tum_index(folder, 30.0)
    assert images.open3d_intrinsic is not None and (folder / "camera.yaml").read_text() == own
    assert open_sequence(folder).camera == source.camera


def test_names_with_the_same_number_keep_one_order(tmp_path):
    """``10.png`` and ``010.png`` hold the same number: the name decides, whatever the set's order."""
    (tmp_path / "color").mkdir()
    (tmp_path / "depth").mkdir()
    for name in ("9.png", "010.png", "10.png"):
        (tmp_path / "color" / name).write_bytes(b"")
        (tmp_path / "depth" / name).write_bytes(b"")
    assert find_image_folders(tmp_path).rgb_names == ["color/9.png", "color/010.png", "color/10.png"]
