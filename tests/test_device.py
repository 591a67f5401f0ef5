"""The device setting: resolving it, where the mapping stage's tensors live, what metrics.json records, run_all --gpu.

CUDA itself is not here: the one test that needs it is skipped without a GPU and gsplat.
"""

import dataclasses
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml
from click.testing import CliRunner

import tambridge.device
from cli import main
from tambridge.mapping.stage import MappingStage
from pipelines.reconstruct import reconstruct
from tambridge.camera import Camera
from tambridge.config import Config, load_config
from tambridge.errors import ConfigError
from tambridge.device import resolve_device
from tambridge.evaluation.metrics import read_metrics
from tambridge.frontend.contract import KeyframeEvent
from tambridge.gaussians.gsplat_backend import gsplat_available
from tambridge.threads import TORCH_THREADS, compute_threads
from tambridge.gaussians.model import GaussianTensors
from tambridge.gaussians.rasterizer import render
from tambridge.io.tum import open_sequence
from tambridge.runlog import RunLog

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture
def no_gpu(monkeypatch):
    """As on this machine and in CI, also where a GPU exists."""
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)


def test_cpu_and_auto_without_a_gpu_resolve_to_the_cpu(no_gpu):
    assert resolve_device("cpu") == torch.device("cpu")
    assert resolve_device(" CPU ") == torch.device("cpu")
    assert resolve_device("auto") == torch.device("cpu")
    assert resolve_device(Config().device) == torch.device("cpu")  # the default ships the CPU path


@pytest.mark.parametrize("requested", ["cuda", "cuda:0"])
def test_cuda_without_a_gpu_is_a_config_error_naming_the_fix(no_gpu, requested):
    with pytest.raises(ConfigError, match="sees no CUDA GPU") as raised:
        resolve_device(requested)
    assert "--device cpu" in str(raised.value) and "gsplat" in str(raised.value)


def test_cuda_without_gsplat_is_a_config_error_and_auto_stays_on_the_cpu(monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(tambridge.device, "gsplat_available", lambda: False)
    with pytest.raises(ConfigError, match="pip install gsplat"):
        resolve_device("cuda")
    assert resolve_device("auto") == torch.device("cpu")


@pytest.mark.parametrize("requested", ["gpu", "cuda:x", "mps", ""])
def test_unknown_devices_are_config_errors(requested):
    with pytest.raises(ConfigError, match="expected one of auto, cpu, cuda"):
        resolve_device(requested)


def test_cli_device_cuda_without_a_gpu_stops_before_any_output(synthetic_sequence_dir, tmp_path, no_gpu):
    out = tmp_path / "out"
    result = CliRunner().invoke(main, ["reconstruct", str(synthetic_sequence_dir), "-o", str(out), "--device", "cuda"])
    assert result.exit_code == 2
    assert result.output.startswith("error: device='cuda'") and len(result.output.strip().splitlines()) == 1
    assert not out.exists()


def test_reconstruct_with_device_cpu_records_it(synthetic_sequence_dir, tmp_path):
    out = tmp_path / "out"
    result = CliRunner().invoke(main, ["reconstruct", str(synthetic_sequence_dir), "-o", str(out), "--quiet", "--device",
                                       "cpu", "--max-frames", "8", "--set", "frontend.kind=open3d_f2f", "--set",
                                       "mesh.enabled=false", "--set", "mapper.iterations=5"])
    assert result.exit_code == 0, result.output
    assert "gsplat_version" not in json.loads((out / "metrics.json").read_text())
    metrics = read_metrics(out / "metrics.json")
    assert metrics.device.device == "cpu" and metrics.device.gsplat_version is None and metrics.map.gaussians > 0
    assert yaml.safe_load((out / "config.yaml").read_text())["device"] == "cpu"


def _keyframe(keyframe_id, frame_index, pose):
    return KeyframeEvent(keyframe_id, frame_index, 0.0, pose, np.zeros((0, 3)), np.zeros((0, 2)), np.zeros(0, np.int64), 0, 0)


def test_mapping_state_is_saved_on_the_cpu_and_loads_onto_the_stage_device(synthetic_sequence_dir, tmp_path):
    # "meta" tensors have a device but no data: enough to see where every tensor of a loaded stage goes.
    sequence = open_sequence(synthetic_sequence_dir, max_frames=4)
    config = load_config(None, ["bridge.enabled=false", "mapper.iterations=4", "mapper.resolution_scale=0.5"])
    run_log = RunLog(tmp_path / "run.log")
    try:
        with compute_threads(TORCH_THREADS, 1):
            stage = MappingStage(sequence, config.mapper, config.bridge, run_log, seed=config.seed)
            poses = {}
            for keyframe_id, index in enumerate((0, 3)):
                poses[keyframe_id] = sequence.ground_truth.world_from_camera[index]
                stage.on_keyframe(_keyframe(keyframe_id, index, poses[keyframe_id]), sequence[index], dict(poses))
        state = stage.state_dict()
        moved = MappingStage(sequence, config.mapper, config.bridge, run_log, torch.device("meta"), config.seed)
        moved.load_state_dict(state)
    finally:
        run_log.close()

    exposure = stage.views[1].exposure
    assert not exposure.frozen and exposure._optimiser.state, "the second view's exposure was optimised"
    cpu_tensors = _tensors_of(state)
    assert len(cpu_tensors) > 20 and {tensor.device.type for tensor in cpu_tensors} == {"cpu"}
    for field in ("_params", "_exp_avg", "_exp_avg_sq"):
        assert all(value.device.type == "meta" for value in getattr(moved.map, field).values()), field
    assert moved.map._world_from_anchor.device.type == "meta" and len(moved.map) == len(stage.map) > 0
    assert moved._cache and all(images.rgb.device.type == images.depth_m.device.type == "meta" for images in moved._cache.values())
    for view in moved.views:
        assert view.exposure.parameters.device.type == "meta"
    moments = moved.views[1].exposure._optimiser.state[moved.views[1].exposure.parameters]
    assert moments["exp_avg"].device.type == moments["exp_avg_sq"].device.type == "meta"
    # Saving and loading left the running stage as it was.
    assert stage.views[1].exposure is exposure and exposure.parameters.device.type == "cpu"


def _tensors_of(value) -> list[torch.Tensor]:
    """Every tensor in a state dict, through dicts, lists, dataclasses and the exposures' Adam state."""
    if isinstance(value, torch.Tensor):
        return [value]
    if isinstance(value, dict):
        return [tensor for item in value.values() for tensor in _tensors_of(item)]
    if isinstance(value, (list, tuple)):
        return [tensor for item in value for tensor in _tensors_of(item)]
    if hasattr(value, "__dict__") and not isinstance(value, type):
        tensors = _tensors_of(vars(value))
        if isinstance(value, torch.optim.Optimizer):
            tensors += _tensors_of(list(value.state.values()))
        return tensors
    return []


@pytest.mark.slow
@pytest.mark.skipif(torch.cuda.is_available(), reason="on a GPU machine --gpu would run the whole benchmark")
def test_run_all_gpu_without_a_gpu_stops_at_once(tmp_path):
    results = ROOT / "benchmarks" / "results" / "run_all.json"
    before = results.read_bytes() if results.exists() else None
    child = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "run_all.py"), "--gpu", "--data", str(tmp_path)],
                           cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert child.returncode == 2
    assert "run_all.py --gpu" in child.stderr and "sees no CUDA GPU" in child.stderr
    assert "running" not in child.stdout
    assert (results.read_bytes() if results.exists() else None) == before


CUDA_RUN = ("frontend.orb.mapping_thread=false", "mesh.enabled=false", "input.max_frames=15", "mapper.iterations=10",
            "bridge.refine_poses=true", "bridge.iterations=5", "mapper.final_iterations_per_view=1")


@pytest.mark.skipif(not gsplat_available(), reason="needs a CUDA GPU and gsplat")
def test_cuda_run_matches_the_cpu_run(synthetic_sequence_dir, tmp_path):
    # The frontend (deterministic with the ORB mapping inline) runs on the CPU either way, so the trajectory and its
    # ATE are the same; the map differs by gsplat's image model (EWA footprint, 1/255 alpha cut: see gsplat_backend).
    runs = {}
    for device in ("cpu", "cuda"):
        config = load_config(None, CUDA_RUN + (f"device={device}",))
        runs[device] = reconstruct(synthetic_sequence_dir, tmp_path / device, config, progress=False).metrics
    cpu, cuda = runs["cpu"], runs["cuda"]
    assert cpu.device.device == "cpu" and cuda.device.device.startswith("cuda:")
    assert cuda.device.gsplat_version and cuda.device.gpu and cuda.device.peak_gpu_memory_mb > 0
    assert cuda.trajectory.ate_rmse_m == cpu.trajectory.ate_rmse_m
    assert cuda.map.bridge.refined_views == cpu.map.bridge.refined_views > 0
    assert np.loadtxt(tmp_path / "cuda" / "trajectory.txt").tolist() == np.loadtxt(tmp_path / "cpu" / "trajectory.txt").tolist()
    for views in ("novel_views", "mapping_views"):
        cuda_psnr, cpu_psnr = (getattr(run.map.rendering, views).psnr_db for run in (cuda, cpu))
        assert abs(cuda_psnr - cpu_psnr) < 0.5, views


POSE_OFFSET = (0.01, -0.008, 0.0, 0.0, 0.012, 0.0)
"""A small camera motion (rho metres, phi radians) between the target render and the render being scored."""


def _pose_gradient(gaussians: GaussianTensors, camera: Camera, backend: str) -> torch.Tensor:
    """d(L1 of colour and depth against the render at POSE_OFFSET)/d(pose twist) at the identity, (6,) on the CPU."""
    device = gaussians.means_m.device
    target = render(gaussians, camera, np.eye(4), torch.tensor(POSE_OFFSET, dtype=torch.float64, device=device), backend=backend)
    pose_delta = torch.zeros(6, dtype=torch.float64, device=device, requires_grad=True)
    rendered = render(gaussians, camera, np.eye(4), pose_delta, backend=backend)
    loss = (rendered.rgb - target.rgb.detach()).abs().mean() + (rendered.depth_m - target.depth_m.detach()).abs().mean()
    loss.backward()
    return pose_delta.grad.cpu()


@pytest.mark.skipif(not gsplat_available(), reason="needs a CUDA GPU and gsplat")
def test_gsplat_gives_the_pose_gradient_of_the_cpu_kernel():
    # The bridge's d(loss)/d(pose) on CUDA: the means are moved by the pose in torch and gsplat gets an identity view
    # matrix, so the gradient reaches the twist through gsplat's gradient w.r.t. the (camera-frame) means.
    camera = Camera(64, 48, fx=60.0, fy=60.0, cx=31.5, cy=23.5)
    generator = torch.Generator().manual_seed(0)
    count = 600
    # A textured slab 1.5-1.8 m away filling the view, Gaussians of 1-2 px: gsplat's EWA footprint is nearly ours.
    means = torch.cat([(torch.rand(count, 2, generator=generator) - 0.5) * torch.tensor([1.8, 1.4]),
                       1.5 + 0.3 * torch.rand(count, 1, generator=generator)], dim=1)
    gaussians = GaussianTensors(means, torch.rand(count, 3, generator=generator), torch.full((count,), float(np.log(0.04))),
                                torch.full((count,), 2.0))
    on_cuda = GaussianTensors(*(tensor.cuda() for tensor in dataclasses.astuple(gaussians)))
    cpu, cuda = _pose_gradient(gaussians, camera, "cpu"), _pose_gradient(on_cuda, camera, "gsplat")
    assert torch.isfinite(cuda).all() and cuda.norm() > 0.1 * cpu.norm() > 0
    assert float(torch.nn.functional.cosine_similarity(cpu, cuda, dim=0)) > 0.9
