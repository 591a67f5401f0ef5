"""Rasteriser speed and memory: the numba CPU kernel against the torch reference, on Gaussians from a real scene.

    python benchmarks/rasterizer.py                       # 320x240 and 640x480, 50k/200k/500k Gaussians
    python benchmarks/rasterizer.py --counts 200000 --resolutions 640x480 --repeats 3

Gaussians are back-projected from frames of 7-Scenes redkitchen (every valid depth pixel, through the ground-truth
pose, one-pixel radius r = d / f as the mapper initialises them, opacity 0.5), a random subset of each size, and
rendered from the first frame's pose. "forward" renders without autograd; "forward+backward" renders with every
field requiring gradients and back-propagates an L1 loss on colour and depth against the frame.

Each (size, backend) runs in its own process, so its peak memory is its own: the growth of the process's peak RSS
(VmHWM, reset after the scene is built) over its RSS just before the first render. Wall time is the median over repeats after one warm-up;
cpu_s is the process CPU time of the same calls (wall x cores used, when the machine is not shared). For the CPU
kernel, every row also has the wall and CPU time per stage (projection, its backward, binning, forward compositing,
reverse pass, per-Gaussian gradient sum, and the rest: conversions, the loss, autograd); the CPU times are the
figures to compare when other processes share the cores. The CPU kernel projects in numba, forward and backward (a
render with no pose twist, as the mapper's); the rows ``cpu_torch_projection`` (forward+backward only) project in
torch instead, as a render whose pose is optimised does: the numba projection's twin, its backward inside "the rest".
The torch reference is :func:`tambridge.gaussians.reference.composite_reference` tiled by 16 px (per-tile
culling is exact; the untiled form would need an N x H x W tensor: 15 GB and more at these sizes).

The table goes to stdout, everything to benchmarks/results/rasterizer.json.
"""

from __future__ import annotations

import argparse
import datetime
import functools
import gc
import json
import multiprocessing
import os
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.machine import describe_machine  # noqa: E402

DEFAULT_DATA = ROOT.parent / "shared" / "data" / "7scenes_redkitchen_0-699"
SOURCE_FRAMES = (0, 10, 20)


def parse_resolution(text: str) -> tuple[int, int]:
    width, height = text.lower().split("x")
    return int(width), int(height)


def status_mb(field: str) -> float:
    """A memory field of /proc/self/status (VmRSS, VmHWM: the peak RSS), in MiB."""
    with open("/proc/self/status") as status:
        for line in status:
            if line.startswith(field + ":"):
                return int(line.split()[1]) / 1024
    raise KeyError(field)


def reset_peak_rss() -> None:
    """Make VmHWM restart from the current RSS (Linux >= 4.0), so the scene building does not count."""
    with open("/proc/self/clear_refs", "w") as clear_refs:
        clear_refs.write("5")


def build_scene(data: Path, count: int, width: int, seed: int = 0):
    """(GaussianTensors, camera, world_from_camera, target rgb (H, W, 3), target depth (H, W)) for one benchmark case."""
    import cv2
    import numpy as np
    import torch

    from tambridge.gaussians import GaussianTensors
    from tambridge.io import open_sequence

    sequence = open_sequence(data)
    camera = sequence.camera
    points, colours, radii = [], [], []
    for index in SOURCE_FRAMES:
        frame = sequence[index]
        world_from_camera = sequence.ground_truth.world_from_camera[index]
        rows, cols = np.nonzero(frame.depth_m > 0)
        depth = frame.depth_m[rows, cols].astype(np.float64)
        points_cam = camera.backproject(np.stack([cols, rows], 1), depth)
        points.append(points_cam @ world_from_camera[:3, :3].T + world_from_camera[:3, 3])
        colours.append(frame.rgb[rows, cols] / 255.0)
        radii.append(depth / camera.mean_focal_px)
    points, colours, radii = np.concatenate(points), np.concatenate(colours), np.concatenate(radii)
    if count > len(points):
        raise SystemExit(f"{count} Gaussians asked, frames {SOURCE_FRAMES} give {len(points)}")
    chosen = np.random.default_rng(seed).choice(len(points), count, replace=False)
    gaussians = GaussianTensors(
        means_m=torch.tensor(points[chosen], dtype=torch.float32),
        rgb=torch.tensor(colours[chosen], dtype=torch.float32),
        log_radii_m=torch.log(torch.tensor(radii[chosen], dtype=torch.float32)),
        opacity_logits=torch.zeros(count),
    )
    view = sequence[SOURCE_FRAMES[0]]
    scale = width / camera.width
    render_camera = camera if scale == 1 else camera.scaled(scale)
    size = (render_camera.width, render_camera.height)
    target_rgb = torch.from_numpy(cv2.resize(view.rgb, size, interpolation=cv2.INTER_AREA) / 255.0).float()
    target_depth = torch.from_numpy(cv2.resize(view.depth_m, size, interpolation=cv2.INTER_NEAREST)).float()
    return gaussians, render_camera, sequence.ground_truth.world_from_camera[SOURCE_FRAMES[0]], target_rgb, target_depth


def measure(data: str, count: int, resolution: tuple[int, int], backend: str, mode: str, repeats: int) -> dict:
    """Run one case in this (fresh) process; returns timings, peak memory and, for the CPU kernel, a breakdown."""
    import numba
    import numpy as np
    import torch

    from tambridge.gaussians import GaussianTensors, cpu_kernel, rasterizer, render
    from tambridge.gaussians.reference import composite_reference

    gaussians, camera, world_from_camera, target_rgb, target_depth = build_scene(Path(data), count, resolution[0])
    background = torch.zeros(3)
    stage_s: dict[str, float] = {}
    stage_cpu_s: dict[str, float] = {}
    if backend in ("cpu", "cpu_torch_projection"):
        # Python-level entry points of each phase, looked up at call time by their callers, so wrapping them here
        # times them inside render(): projection (numba; in torch its forward only, its backward is in
        # torch_and_glue), binning, compositing, the reverse pass and the per-Gaussian gradient reduction.
        stages = [(rasterizer, "camera_frame_means", "projection"), (rasterizer, "project_to_screen", "projection")]
        stages += [(cpu_kernel, "project", "projection"), (cpu_kernel, "project_backward", "projection_backward")]
        stages += [(cpu_kernel, "bin_tiles", "binning"), (cpu_kernel, "composite_forward", "forward")]
        stages += [(cpu_kernel, "_backward", "backward"), (cpu_kernel, "_sum_entries", "gradient_sum")]
        for module, name, stage in stages:
            original = getattr(module, name)

            @functools.wraps(original)
            def timed(*args, _original=original, _stage=stage, **kwargs):
                start, start_cpu = time.perf_counter(), time.process_time()
                result = _original(*args, **kwargs)
                stage_s[_stage] = stage_s.get(_stage, 0.0) + time.perf_counter() - start
                stage_cpu_s[_stage] = stage_cpu_s.get(_stage, 0.0) + time.process_time() - start_cpu
                return result

            setattr(module, name, timed)

    def render_once(splats: GaussianTensors):
        if backend == "cpu":
            return render(splats, camera, world_from_camera, background_rgb=(0.0, 0.0, 0.0), backend="cpu")
        # Through the module's names, which the stage timers wrap.
        screen = rasterizer.project_to_screen(splats, rasterizer.camera_frame_means(splats, torch.from_numpy(world_from_camera)), camera)
        if backend == "cpu_torch_projection":
            return rasterizer.composite_cpu(screen, camera.width, camera.height, background)
        return composite_reference(screen, camera.width, camera.height, background, tile_px=16)

    def step(splats: GaussianTensors):
        if mode == "forward":
            with torch.no_grad():
                render_once(splats)
            return
        for name in ("means_m", "rgb", "log_radii_m", "opacity_logits"):
            getattr(splats, name).grad = None
            getattr(splats, name).requires_grad_(True)
        out = render_once(splats)
        loss = (out.rgb - target_rgb).abs().mean() + (out.depth_m - target_depth).abs().mean()
        loss.backward()

    # Load the compiled numba code and torch's kernels on a tiny scene first: a one-off cost, not a render's memory.
    step(GaussianTensors(*(getattr(gaussians, name).detach()[:1000].clone() for name in ("means_m", "rgb", "log_radii_m", "opacity_logits"))))
    gc.collect()
    reset_peak_rss()
    baseline_mb = status_mb("VmRSS")
    if backend != "reference":
        step(gaussians)  # warm-up at full size (allocator pools); the torch reference takes seconds, once is enough
    stage_s.clear()
    stage_cpu_s.clear()
    walls, cpus = [], []
    for _ in range(repeats):
        wall, cpu = time.perf_counter(), time.process_time()
        step(gaussians)
        walls.append(time.perf_counter() - wall)
        cpus.append(time.process_time() - cpu)
    peak_mb = status_mb("VmHWM")
    result = {
        "resolution": f"{camera.width}x{camera.height}",
        "gaussians": count,
        "backend": backend,
        "mode": mode,
        "repeats": repeats,
        "wall_s_median": float(np.median(walls)),
        "wall_s_min": float(np.min(walls)),
        "cpu_s_median": float(np.median(cpus)),
        "peak_memory_mb": peak_mb - baseline_mb,
        "threads": {"numba": numba.get_num_threads(), "torch": torch.get_num_threads()},
    }
    if stage_s:
        # The rest: the projection's backward in torch, packing, conversions, the loss, autograd.
        result["stage_s_mean"] = {name: seconds / repeats for name, seconds in stage_s.items()}
        result["stage_s_mean"]["torch_and_glue"] = float(np.mean(walls)) - sum(stage_s.values()) / repeats
        result["stage_cpu_s_mean"] = {name: seconds / repeats for name, seconds in stage_cpu_s.items()}
        result["stage_cpu_s_mean"]["torch_and_glue"] = float(np.mean(cpus)) - sum(stage_cpu_s.values()) / repeats
    return result


def run_isolated(*args) -> dict:
    """``measure`` in a fresh spawned process (its own ru_maxrss)."""
    with multiprocessing.get_context("spawn").Pool(1, maxtasksperchild=1) as pool:
        return pool.apply(measure, args)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path, default=DEFAULT_DATA)
    parser.add_argument("--counts", type=lambda s: [int(c) for c in s.split(",")], default=[50_000, 200_000, 500_000])
    parser.add_argument("--resolutions", type=lambda s: [parse_resolution(r) for r in s.split(",")], default=[(320, 240), (640, 480)])
    parser.add_argument("--repeats", type=int, default=5, help="timed runs of the CPU kernel per case (after a warm-up)")
    parser.add_argument("--reference-repeats", type=int, default=1)
    parser.add_argument("--reference-max-gaussians", type=int, default=200_000,
                        help="skip the torch reference above this many Gaussians (at 500k it takes minutes per call)")
    parser.add_argument(
        "--omp-wait-policy", choices=("passive", "active"), default="passive",
        help="OpenMP workers' idle policy in the measuring processes (default passive: on a machine shared with other "
        "work, spinning torch workers take the cores the numba kernels need; ~10x on the torch part, 2 loaded cores)",
    )
    parser.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "results" / "rasterizer.json")
    args = parser.parse_args()

    from tambridge.files import atomic_write_text

    os.environ["OMP_WAIT_POLICY"] = args.omp_wait_policy.upper()  # read by the spawned processes' OpenMP runtimes
    started = datetime.datetime.now().isoformat(timespec="seconds")
    load_before = os.getloadavg()
    rows, skipped = [], []
    for width, height in args.resolutions:
        for count in args.counts:
            for mode in ("forward", "forward+backward"):
                fast = run_isolated(str(args.data), count, (width, height), "cpu", mode, args.repeats)
                rows.append(fast)
                if mode == "forward+backward":
                    twin = run_isolated(str(args.data), count, (width, height), "cpu_torch_projection", mode, args.repeats)
                    twin["speedup_of_cpu_kernel"] = twin["wall_s_median"] / fast["wall_s_median"]
                    rows.append(twin)
                if count > args.reference_max_gaussians:
                    skipped.append({"resolution": f"{width}x{height}", "gaussians": count, "mode": mode,
                                    "reason": f"torch reference skipped above {args.reference_max_gaussians} Gaussians"})
                    continue
                reference = run_isolated(str(args.data), count, (width, height), "reference", mode, args.reference_repeats)
                reference["speedup_of_cpu_kernel"] = reference["wall_s_median"] / fast["wall_s_median"]
                rows.append(reference)
                print(
                    f"{width}x{height} {count:>7} {mode:<16} cpu {fast['wall_s_median']:.4f} s  "
                    f"reference {reference['wall_s_median']:.3f} s  x{reference['speedup_of_cpu_kernel']:.1f}",
                    flush=True,
                )

    header = f"{'resolution':<10} {'gaussians':>9} {'mode':<16} {'backend':<9} {'wall s':>8} {'cpu s':>8} {'fps':>7} {'peak MB':>8} {'vs ref':>7}"
    print("\n" + header + "\n" + "-" * len(header))
    for row in rows:
        speedup = ""
        if row["backend"] != "cpu":
            speedup = f"x{row['speedup_of_cpu_kernel']:.2f}"
        print(
            f"{row['resolution']:<10} {row['gaussians']:>9} {row['mode']:<16} {row['backend']:<9} "
            f"{row['wall_s_median']:>8.4f} {row['cpu_s_median']:>8.3f} {1 / row['wall_s_median']:>7.1f} "
            f"{row['peak_memory_mb']:>8.0f} {speedup:>7}"
        )
    stages = ("projection", "projection_backward", "binning", "forward", "backward", "gradient_sum", "torch_and_glue")
    header = f"{'resolution':<10} {'gaussians':>9} {'mode':<16} {'projection':<10} " + " ".join(f"{stage:>14}" for stage in stages)
    print("\nCPU kernel, CPU time per stage (ms; wall time per stage is in the JSON)\n" + header + "\n" + "-" * len(header))
    for row in rows:
        if row["backend"] != "reference":
            times = row["stage_cpu_s_mean"]
            cells = " ".join(f"{1000 * times[stage]:>14.1f}" if stage in times else f"{'-':>14}" for stage in stages)
            projection = "torch" if row["backend"] == "cpu_torch_projection" else "numba"
            print(f"{row['resolution']:<10} {row['gaussians']:>9} {row['mode']:<16} {projection:<10} {cells}")
    for row in skipped:
        print(f"skipped: {row['resolution']} {row['gaussians']} {row['mode']}: {row['reason']}")
    print("dense (untiled) reference: skipped at every size, an N x H x W float32 tensor is >= 15 GB at 50k / 320x240")
    targets = {("320x240", 200_000, "forward"): "forward at >= 30 fps", ("640x480", 200_000, "forward+backward"): "forward+backward in <= 0.25 s"}
    for row in rows:
        target = targets.get((row["resolution"], row["gaussians"], row["mode"]))
        if target and row["backend"] == "cpu":  # issue 5's targets, on 2 cores
            print(f"target {row['resolution']}/{row['gaussians']} {target}: {row['wall_s_median']:.4f} s, {1 / row['wall_s_median']:.1f} fps")

    report = {
        "started": started,
        "machine": describe_machine(),
        "load_average_before": load_before,
        "load_average_after": os.getloadavg(),
        "OMP_WAIT_POLICY": os.environ.get("OMP_WAIT_POLICY"),
        "data": str(args.data),
        "source_frames": SOURCE_FRAMES,
        "rows": rows,
        "skipped": skipped,
    }
    atomic_write_text(args.out, json.dumps(report, indent=2) + "\n")
    print(f"written {args.out}")


if __name__ == "__main__":
    main()
