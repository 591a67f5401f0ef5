"""Colour resampled into the depth camera for unregistered sensors: kernel against its twin, the reader against
a synthetic Kinect-v1-like sensor with exact colour, camera-file parsing, and a reconstruction end to end."""


import numpy as np
import pytest
import yaml
from click.testing import CliRunner

from cli import main
from tambridge.camera import Camera, load_sensor_file
from tambridge.errors import CameraConfigError
from tambridge.evaluation.metrics import read_metrics
from tambridge.io.registration import ColourToDepth, fill_missing_depth
from tambridge.io.synthetic import SynthOptions, make_room_scene, render, write_synthetic_sequence
from tambridge.io.tum import open_sequence

UNREGISTERED = SynthOptions(frame_count=30, width=160, height=120, colour_baseline_m=0.025, colour_focal_scale=0.9)


@pytest.fixture(scope="module")
def unregistered_dir(tmp_path_factory):
    folder = tmp_path_factory.mktemp("unregistered") / "room"
    write_synthetic_sequence(folder, UNREGISTERED)
    return folder


def test_kernel_matches_the_numpy_twin_with_distortion_holes_and_border():
    rng = np.random.default_rng(3)
    depth_camera = Camera(96, 72, 80.0, 82.0, 47.5, 35.5)
    colour_camera = Camera(100, 80, 100.0, 101.0, 50.0, 41.0, (0.1, -0.05, 0.002, -0.001, 0.01))
    angle = np.deg2rad(2.0)
    colour_from_depth = np.eye(4)
    colour_from_depth[:3, :3] = [[np.cos(angle), 0, np.sin(angle)], [0, 1, 0], [-np.sin(angle), 0, np.cos(angle)]]
    colour_from_depth[:3, 3] = [-0.03, 0.004, 0.002]
    registration = ColourToDepth(depth_camera, colour_camera, colour_from_depth)
    colour = rng.integers(0, 256, (80, 100, 3), dtype=np.uint8)
    depth_m = rng.uniform(0.3, 4.0, (72, 96)).astype(np.float32)
    depth_m[rng.random(depth_m.shape) < 0.2] = 0.0  # holes: looked up with the filled depth
    fast = registration.colour_in_depth_camera(colour, depth_m)
    slow = registration.colour_in_depth_camera_reference(colour, depth_m)
    difference = np.abs(fast.astype(int) - slow)
    assert difference.max() <= 1 and (difference > 0).mean() < 0.01  # float32 rounding of the last bit only
    assert (slow == 0).all(axis=2).any(), "the colour camera sees less than the depth camera: border pixels are black"


def test_fill_missing_depth_takes_the_farthest_valid_depth_of_the_block():
    depth_m = np.zeros((32, 32), np.float32)
    depth_m[:16, :16] = 1.0
    depth_m[2, 3] = 3.0
    depth_m[:16, :16][5, 5] = 0.0
    depth_m[16:, 16:] = 2.0
    filled = fill_missing_depth(depth_m, block_px=16)
    assert filled[5, 5] == 3.0 and filled[2, 3] == 3.0 and filled[0, 0] == 1.0
    # Blocks with no valid depth at all take the median of the other blocks' largest depths (3 and 2).
    assert filled[0, 20] == 2.5 and filled[20, 0] == 2.5


def test_reader_puts_colour_in_the_depth_camera(unregistered_dir):
    sequence = open_sequence(unregistered_dir)
    assert sequence.camera.fx == pytest.approx(0.82 * 160)  # the depth camera is the frames' camera
    scene = make_room_scene(UNREGISTERED.seed)
    top, bottom, left, right = sequence.valid_region
    registered_errors, raw_errors = [], []
    for index in (0, 11, 23):
        truth = render(scene, sequence.camera, sequence.ground_truth.world_from_camera[index])[0]
        frame = sequence[index]
        raw = sequence.read_rgb(sequence.rgb_paths[index])
        registered_errors.append(np.abs(frame.rgb / 255.0 - truth)[top:bottom, left:right].mean())
        raw_errors.append(np.abs(raw / 255.0 - truth)[top:bottom, left:right].mean())
    # What is left is resampling (bilinear of an aliased texture); taken pixel for pixel, colour is 5x further off.
    assert max(registered_errors) < 0.03 and min(raw_errors) > 0.08, (registered_errors, raw_errors)


def test_camera_file_keys_of_an_unregistered_sensor(tmp_path):
    text = tmp_path / "camera.txt"
    text.write_text(
        "width 64\nheight 48\nfx 60\nfy 60\ncx 32\ncy 24\ndepth_scale 1000\n"
        "colour_fx 50\ncolour_fy 51\ncolour_cx 31\ncolour_cy 25\ncolour_width 80\ncolour_height 60\n"
        "colour_from_depth 1 0 0 -0.025 0 1 0 0 0 0 1 0\n"
    )
    sensor = load_sensor_file(text)
    assert sensor.colour_camera == Camera(80, 60, 50.0, 51.0, 31.0, 25.0)
    assert sensor.camera == Camera(64, 48, 60.0, 60.0, 32.0, 24.0)
    np.testing.assert_array_equal(sensor.colour_from_depth[:, 3], [-0.025, 0, 0, 1])
    base = {"width": 64, "height": 48, "fx": 60, "fy": 60, "cx": 32, "cy": 24, "depth_scale": 1000}
    colour = {"colour_fx": 50, "colour_fy": 50, "colour_cx": 32, "colour_cy": 24, "colour_from_depth": np.eye(4).tolist()}
    for values, message in (
        ({**base, "colour_fx": 50}, "colour_from_depth"),
        ({**base, **colour, "colour_from_depth": [1, 0, 0]}, "3 numbers"),
        ({**base, **colour, "colour_from_depth": (2 * np.eye(4)).tolist()}, "not a rotation"),
        ({**base, **colour, "distortion": [0.1, 0, 0, 0, 0]}, "colour_distortion"),
    ):
        path = tmp_path / "camera.yaml"
        path.write_text(yaml.safe_dump(values))
        with pytest.raises(CameraConfigError, match=message) as error:
            load_sensor_file(path)
        assert str(path) in str(error.value)


@pytest.mark.slow
def test_reconstruct_of_an_unregistered_sensor_tracks_and_renders_better_registered(unregistered_dir, tmp_path):
    """The same frames read as if registered (the colour_* keys dropped, as before this reader existed) against
    the registered reading: the rendering of the map improves by more than 2 dB and the trajectory error drops
    (at 30 frames a loop moves 7 cm a frame, so neither reading tracks as well as a longer sequence would)."""
    sensor_values = yaml.safe_load((unregistered_dir / "camera.yaml").read_text())
    naive = tmp_path / "naive.yaml"
    naive.write_text(yaml.safe_dump({k: v for k, v in sensor_values.items() if not k.startswith("colour_")}))
    metrics = {}
    for name, camera in (("registered", unregistered_dir / "camera.yaml"), ("naive", naive)):
        output = tmp_path / name
        result = CliRunner().invoke(main, ["reconstruct", str(unregistered_dir), "-o", str(output), "--camera",
                                           str(camera), "--set", "frontend.orb.mapping_thread=false",
                                           "--set", "mesh.enabled=false"])
        assert result.exit_code == 0, result.output
        metrics[name] = read_metrics(output / "metrics.json")
    registered, naive_metrics = metrics["registered"], metrics["naive"]
    psnr = {name: m.map.rendering.novel_views.psnr_db for name, m in metrics.items()}
    # The run is deterministic (inline ORB mapping); the bounds keep most of what registering gains in it.
    assert psnr["registered"] > psnr["naive"] + 2.0, psnr
    assert registered.trajectory.ate_rmse_m < 0.5 * naive_metrics.trajectory.ate_rmse_m, metrics
