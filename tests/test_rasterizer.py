"""The CPU kernel against the dense torch reference and finite differences; known answers; gsplat on CUDA."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from tambridge.camera import Camera
from tambridge.geometry import exp_se3, look_at
from tambridge.gaussians import GaussianTensors, ScreenGaussians, cpu_kernel, render
from tambridge.gaussians.model import camera_frame_means, camera_from_world_tensor, jacobian_limits, project_to_screen
from tambridge.gaussians.rasterizer import composite_cpu
from tambridge.gaussians.reference import composite_reference

FIELDS = ("means_m", "rgb", "log_radii_m", "opacity_logits")
BACKGROUND = (0.2, 0.3, 0.4)


def random_gaussians(count: int, seed: int, dtype=torch.float32, opacity_logit_mean=0.0, radius_m=(0.01, 0.06)) -> GaussianTensors:
    """Gaussians in a box 1.5-2.5 m in front of an identity camera, some of them behind it (near-plane cull)."""
    generator = torch.Generator().manual_seed(seed)
    means = torch.rand(count, 3, generator=generator, dtype=dtype) * torch.tensor([2.0, 1.5, 1.0], dtype=dtype)
    means = means + torch.tensor([-1.0, -0.75, 1.5], dtype=dtype)
    means[: count // 20, 2] -= 2.0  # 5 % behind the camera
    radii = torch.rand(count, generator=generator, dtype=dtype) * (radius_m[1] - radius_m[0]) + radius_m[0]
    return GaussianTensors(
        means_m=means,
        rgb=torch.rand(count, 3, generator=generator, dtype=dtype),
        log_radii_m=torch.log(radii),
        opacity_logits=torch.randn(count, generator=generator, dtype=dtype) + opacity_logit_mean,
    )


def requiring_grad(gaussians: GaussianTensors) -> GaussianTensors:
    return GaussianTensors(**{name: getattr(gaussians, name).detach().clone().requires_grad_(True) for name in FIELDS})


def scalar_loss(gaussians, camera, world_from_camera, pose_delta, backend) -> torch.Tensor:
    return weighted_sum(render(gaussians, camera, world_from_camera, pose_delta, BACKGROUND, backend=backend))


def weighted_sum(out) -> torch.Tensor:
    """A loss of a render that weighs every output pixel and channel differently (so no gradient cancels by
    symmetry)."""
    height, width = out.depth_m.shape
    dtype = out.depth_m.dtype
    ramp = torch.linspace(0.5, 1.5, height * width, dtype=dtype).reshape(height, width)
    colour_weights = torch.stack([ramp, ramp.flip(0), ramp.flip(1)], dim=-1)
    return (out.rgb * colour_weights).sum() + 0.7 * (out.depth_m * ramp.T.reshape(height, width)).sum() - 1.3 * (out.silhouette * ramp).sum()


def camera_of(width: int, height: int) -> Camera:
    return Camera(width, height, fx=0.9 * width, fy=0.95 * width, cx=(width - 1) / 2 + 0.3, cy=(height - 1) / 2 - 0.2)


# (count, width, height, opacity logit mean, largest radius in metres): image sizes that are not tile multiples; the
# last case is opaque and deep enough that the alpha clamp and the early stop (T < 1e-4) happen at many pixels.
CASES = [(60, 16, 16, 0.0, 0.06), (400, 40, 30, 0.0, 0.06), pytest.param(2000, 70, 45, 0.0, 0.06, marks=pytest.mark.slow),
         (1500, 48, 36, 5.0, 0.2)]


@pytest.mark.parametrize("count,width,height,opacity_logit_mean,largest_radius_m", CASES)
def test_cpu_kernel_matches_reference(count, width, height, opacity_logit_mean, largest_radius_m):
    camera = camera_of(width, height)
    world_from_camera = look_at(np.array([0.1, -0.2, -0.3]), np.array([0.0, 0.0, 2.0]), up=np.array([0.0, -1.0, 0.0]))
    base = random_gaussians(count, seed=count, opacity_logit_mean=opacity_logit_mean, radius_m=(0.01, largest_radius_m))
    results = {}
    for backend in ("reference", "cpu"):
        gaussians = requiring_grad(base)
        pose_delta = torch.zeros(6, dtype=torch.float64, requires_grad=True)
        out = render(gaussians, camera, world_from_camera, pose_delta, BACKGROUND, backend=backend)
        loss = scalar_loss(gaussians, camera, world_from_camera, pose_delta, backend)
        grads = torch.autograd.grad(loss, [getattr(gaussians, name) for name in FIELDS] + [pose_delta])
        results[backend] = (out, grads)
    (reference, reference_grads), (fast, fast_grads) = results["reference"], results["cpu"]
    if opacity_logit_mean > 0:
        assert (fast.silhouette > 0.99).float().mean() > 0.3, "the opaque case should saturate many pixels"
    for name in ("rgb", "depth_m", "silhouette"):
        torch.testing.assert_close(getattr(fast, name), getattr(reference, name), atol=1e-5, rtol=0)
    for name, expected, actual in zip(FIELDS + ("pose_delta",), reference_grads, fast_grads):
        scale = expected.abs().max()
        assert scale > 0, name
        assert (actual - expected).abs().max() <= 1e-4 * scale, name


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("count,width,height,opacity_logit_mean,largest_radius_m", CASES[2:])
def test_untracked_render_matches_reference_and_tracked_render(count, width, height, opacity_logit_mean, largest_radius_m, dtype):
    """Without autograd the CPU backend projects in numba (cpu_kernel.project): same maps as the dense reference and
    as the tracked path (torch projection), and nothing differentiable."""
    camera = camera_of(width, height)
    world_from_camera = look_at(np.array([0.1, -0.2, -0.3]), np.array([0.0, 0.0, 2.0]), up=np.array([0.0, -1.0, 0.0]))
    gaussians = random_gaussians(count, seed=count, dtype=dtype, opacity_logit_mean=opacity_logit_mean, radius_m=(0.01, largest_radius_m))
    pose_delta = torch.tensor([0.01, -0.02, 0.015, 0.02, -0.01, 0.03], dtype=torch.float64)
    with torch.no_grad():
        untracked = render(gaussians, camera, world_from_camera, pose_delta, BACKGROUND, backend="cpu")
        reference = render(gaussians, camera, world_from_camera, pose_delta, BACKGROUND, backend="reference")
    tracked = render(requiring_grad(gaussians), camera, world_from_camera, pose_delta, BACKGROUND, backend="cpu")
    assert tracked.rgb.requires_grad
    for name in ("rgb", "depth_m", "silhouette"):
        image = getattr(untracked, name)
        assert image.dtype == dtype and image.grad_fn is None and not image.requires_grad
        torch.testing.assert_close(image, getattr(reference, name), atol=1e-5, rtol=0)
        torch.testing.assert_close(image, getattr(tracked, name).detach(), atol=1e-6, rtol=0)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_projection_kernel_matches_torch_projection(dtype):
    """cpu_kernel.project repeats torch's arithmetic: depths and means bit-identical (so the depth order, ties
    included, is the same), conic, bound and opacity within a few ulp (libm's exp and sqrt instead of torch's)."""
    camera = camera_of(70, 45)
    world_from_camera = look_at(np.array([0.1, -0.2, -0.3]), np.array([0.0, 0.0, 2.0]), up=np.array([0.0, -1.0, 0.0]))
    gaussians = random_gaussians(5000, seed=21, dtype=dtype)
    camera_from_world = camera_from_world_tensor(torch.from_numpy(world_from_camera), None)
    fields = [gaussians.means_m, gaussians.log_radii_m, gaussians.opacity_logits, gaussians.rgb]
    packed = cpu_kernel.project(*(field.numpy() for field in fields), camera_from_world.numpy(), camera)
    screen = project_to_screen(gaussians, camera_frame_means(gaussians, torch.from_numpy(world_from_camera)), camera)
    assert packed.dtype == gaussians.means_m.numpy().dtype
    assert (screen.depths_m <= 0.01).any()  # behind the near plane: the stand-in depth, no inf or NaN
    k = cpu_kernel
    np.testing.assert_array_equal(packed[:, k.DEPTH], screen.depths_m.numpy())
    np.testing.assert_array_equal(packed[:, k.U : k.V + 1], screen.means_px.numpy())
    np.testing.assert_array_equal(packed[:, k.RED : k.RED + 3], screen.rgb.numpy())
    # 16 ulp: the conic divides by a determinant whose rounding depends on whether LLVM fuses its multiply-adds on
    # the CPU at hand (4.6 ulp seen on one machine, under 4 on another).
    eps = torch.finfo(dtype).eps
    np.testing.assert_allclose(packed[:, k.CONIC_A : k.CONIC_C + 1], screen.conics_px.numpy(), rtol=16 * eps, atol=0)
    np.testing.assert_allclose(packed[:, k.BOUND], screen.bounds_px.numpy(), rtol=16 * eps, atol=0)
    np.testing.assert_allclose(packed[:, k.OPACITY], screen.opacity.numpy(), rtol=4 * eps, atol=0)


@pytest.mark.parametrize("backend,with_pose", [("cpu", True), ("reference", True), ("cpu", False)])
def test_gradients_match_finite_differences(backend, with_pose):
    """Directional derivatives along random directions, float64, every field and the pose twist; without a pose
    twist the CPU backend projects in numba (its own backward, cpu_kernel.project_backward)."""
    camera = camera_of(24, 18)
    world_from_camera = look_at(np.array([0.05, 0.1, -0.1]), np.array([0.0, 0.0, 2.0]), up=np.array([0.0, -1.0, 0.0]))
    gaussians = requiring_grad(random_gaussians(40, seed=7, dtype=torch.float64, radius_m=(0.05, 0.15)))
    pose_delta = torch.tensor([0.01, -0.02, 0.015, 0.02, -0.01, 0.03], dtype=torch.float64, requires_grad=True)
    if not with_pose:
        world_from_camera, pose_delta = world_from_camera @ exp_se3(pose_delta.detach().numpy()), None
    parameters = [getattr(gaussians, name) for name in FIELDS] + ([pose_delta] if with_pose else [])
    grads = torch.autograd.grad(scalar_loss(gaussians, camera, world_from_camera, pose_delta, backend), parameters)
    generator = torch.Generator().manual_seed(3)
    step = 1e-6
    for name, parameter, grad in zip(FIELDS + ("pose_delta",), parameters, grads):
        direction = torch.randn(parameter.shape, generator=generator, dtype=torch.float64)
        values = []
        for sign in (1.0, -1.0):
            with torch.no_grad():
                parameter += sign * step * direction
                values.append(scalar_loss(gaussians, camera, world_from_camera, pose_delta, backend).item())
                parameter -= sign * step * direction
        numeric = (values[0] - values[1]) / (2 * step)
        analytic = (grad * direction).sum().item()
        assert abs(numeric - analytic) <= 1e-5 * max(1.0, abs(numeric)), (name, numeric, analytic)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_numba_projection_gradients_match_torch_projection(dtype):
    """A render with no pose twist projects in numba under autograd (rasterizer._CpuProject): the same maps and the
    same gradients of every field as the torch projection (camera_frame_means, project_to_screen), its twin, to the
    dtype's rounding; Gaussians behind the near plane and beyond the EWA Jacobian's limits included."""
    camera = camera_of(70, 45)
    world_from_camera = look_at(np.array([0.1, -0.2, -0.3]), np.array([0.0, 0.0, 2.0]), up=np.array([0.0, -1.0, 0.0]))
    base = random_gaussians(2000, seed=5, dtype=dtype, radius_m=(0.01, 0.1))
    base.means_m[-100:, 0] *= 3.0  # some outside the field of view, where xn is clamped and their footprints still reach in
    background = torch.tensor(BACKGROUND, dtype=dtype)
    results = []
    for numba_projection in (True, False):
        gaussians = requiring_grad(base)
        if numba_projection:
            out = render(gaussians, camera, world_from_camera, None, BACKGROUND, backend="cpu")
        else:
            screen = project_to_screen(gaussians, camera_frame_means(gaussians, torch.from_numpy(world_from_camera)), camera)
            out = composite_cpu(screen, camera.width, camera.height, background)
        results.append((out, torch.autograd.grad(weighted_sum(out), [getattr(gaussians, name) for name in FIELDS])))
    (fast, fast_grads), (twin, twin_grads) = results
    eps = torch.finfo(dtype).eps
    for name in ("rgb", "depth_m", "silhouette"):
        torch.testing.assert_close(getattr(fast, name), getattr(twin, name), atol=8 * eps, rtol=8 * eps)
    for name, actual, expected in zip(FIELDS, fast_grads, twin_grads):
        scale = expected.abs().max()
        assert scale > 0 and (actual != 0).any(), name
        assert (actual - expected).abs().max() <= 64 * eps * scale, name


def test_single_gaussian_known_answer():
    """A Gaussian whose mean projects onto a pixel centre gives o*c + (1-o)*bg, o*z and o there; around it, the
    EWA ellipse of an off-axis mean (closed form of J r^2 I J^T for fx == fy)."""
    camera = Camera(32, 24, fx=30.0, fy=30.0, cx=15.5, cy=11.5)
    depth_m, opacity = 2.0, 0.6
    pixel = (20, 5)  # (u, v)
    means_cam = torch.tensor([[(pixel[0] - camera.cx) * depth_m / camera.fx, (pixel[1] - camera.cy) * depth_m / camera.fy, depth_m]])
    world_from_camera = look_at(np.array([1.0, 2.0, 0.5]), np.array([1.0, 4.0, 0.5]))
    gaussians = GaussianTensors(
        means_m=torch.from_numpy(means_cam.numpy() @ world_from_camera[:3, :3].T + world_from_camera[:3, 3]).float(),
        rgb=torch.tensor([[0.9, 0.5, 0.1]]),
        log_radii_m=torch.log(torch.tensor([2.0 * depth_m / camera.fx])),  # two pixels
        opacity_logits=torch.logit(torch.tensor([opacity])),
    )
    out = render(gaussians, camera, world_from_camera, background_rgb=BACKGROUND, backend="cpu")
    expected_rgb = opacity * gaussians.rgb[0] + (1 - opacity) * torch.tensor(BACKGROUND)
    torch.testing.assert_close(out.rgb[pixel[1], pixel[0]], expected_rgb, atol=1e-5, rtol=0)
    assert out.depth_m[pixel[1], pixel[0]].item() == pytest.approx(opacity * depth_m, abs=1e-5)
    assert out.silhouette[pixel[1], pixel[0]].item() == pytest.approx(opacity, abs=1e-6)
    # Sigma2D = (2 px)^2 [[1 + xn^2, xn yn], [xn yn, 1 + yn^2]]; its inverse [[a, b], [b, c]]:
    xn, yn = (pixel[0] - camera.cx) / camera.fx, (pixel[1] - camera.cy) / camera.fy
    spread = 4.0 * (1 + xn**2 + yn**2)
    a, b, c = (1 + yn**2) / spread, -xn * yn / spread, (1 + xn**2) / spread
    assert out.silhouette[pixel[1], pixel[0] + 1].item() == pytest.approx(opacity * np.exp(-a / 2), abs=1e-6)
    assert out.silhouette[pixel[1] + 1, pixel[0]].item() == pytest.approx(opacity * np.exp(-c / 2), abs=1e-6)
    assert out.silhouette[pixel[1] + 1, pixel[0] + 1].item() == pytest.approx(opacity * np.exp(-(a + 2 * b + c) / 2), abs=1e-6)
    assert out.silhouette[pixel[1] + 1, pixel[0] - 1].item() == pytest.approx(opacity * np.exp(-(a - 2 * b + c) / 2), abs=1e-6)
    # Along the row the 3-sigma cut-off lies at 3 / sqrt(a) = 6.07 px (a circle of radius f r / z would end at 6).
    assert 36 < 9 / a < 49
    assert out.silhouette[pixel[1], pixel[0] + 6].item() == pytest.approx(opacity * np.exp(-36 * a / 2), abs=1e-6)
    assert out.silhouette[pixel[1], pixel[0] + 7].item() == 0.0
    assert out.silhouette.argmax().item() == pixel[1] * camera.width + pixel[0]


def _ewa_covariance(means_cam: torch.Tensor, radii_m: torch.Tensor, camera: Camera) -> torch.Tensor:
    """(M, 2, 2) J (r^2 I) J^T built as matrices, J's x / z, y / z clamped to jacobian_limits."""
    x_lo, x_hi, y_lo, y_hi = jacobian_limits(camera)
    x, y, z = means_cam.unbind(1)
    xn, yn = (x / z).clamp(x_lo, x_hi), (y / z).clamp(y_lo, y_hi)
    zeros = torch.zeros_like(z)
    jacobian = torch.stack([torch.stack([camera.fx / z, zeros, -camera.fx * xn / z], 1),
                            torch.stack([zeros, camera.fy / z, -camera.fy * yn / z], 1)], 1)  # (M, 2, 3)
    return radii_m[:, None, None] ** 2 * jacobian @ jacobian.transpose(1, 2)


def test_screen_footprint_is_the_ewa_projection_of_the_isotropic_covariance():
    """conics_px and bounds_px against J (r^2 I) J^T built as matrices (means all over the image and off it, where
    the Jacobian is clamped): the inverse, and 3 sqrt(largest eigenvalue) for fx == fy (an upper bound for fx != fy,
    at most fy / fx larger here)."""
    camera = camera_of(40, 30)
    gaussians = random_gaussians(300, seed=13, dtype=torch.float64)
    means_cam = camera_frame_means(gaussians, torch.eye(4, dtype=torch.float64))
    ahead = means_cam[:, 2] > 0.01
    x_lo, x_hi, _, _ = jacobian_limits(camera)
    normalised = means_cam[ahead, :2] / means_cam[ahead, 2:]
    assert ((normalised[:, 0] < x_lo) | (normalised[:, 0] > x_hi)).any() and (normalised.abs() > 0.3).all(1).any()
    radii = torch.exp(gaussians.log_radii_m[ahead])
    for lens, exact in ((camera, False), (dataclasses.replace(camera, fy=camera.fx), True)):
        screen = project_to_screen(gaussians, means_cam, lens)
        covariance = _ewa_covariance(means_cam[ahead], radii, lens)
        conic = torch.linalg.inv(covariance)
        torch.testing.assert_close(screen.conics_px[ahead], torch.stack([conic[:, 0, 0], conic[:, 0, 1], conic[:, 1, 1]], 1), rtol=1e-10, atol=0)
        three_sigma = 3.0 * torch.linalg.eigvalsh(covariance)[:, 1].sqrt()
        if exact:
            torch.testing.assert_close(screen.bounds_px[ahead], three_sigma, rtol=1e-10, atol=0)
        else:
            assert (screen.bounds_px[ahead] >= three_sigma * (1 - 1e-12)).all()
            assert (screen.bounds_px[ahead] <= three_sigma * (camera.fy / camera.fx)).all()


@pytest.mark.parametrize("backend", ["cpu", "reference"])
def test_early_stop_and_alpha_clamp_known_answer(backend):
    """Three opaque Gaussians on one ray: T goes 1 -> 0.02 -> 4e-4, the third would take it below 1e-4 and is left out;
    an opacity above 0.99 is clamped to 0.99."""
    camera = Camera(16, 16, fx=20.0, fy=20.0, cx=8.0, cy=8.0)
    depths = torch.tensor([1.0, 2.0, 3.0], dtype=torch.float64)
    stack = GaussianTensors(
        means_m=torch.stack([torch.zeros(3, dtype=torch.float64), torch.zeros(3, dtype=torch.float64), depths], dim=1),
        rgb=torch.tensor([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]], dtype=torch.float64),
        log_radii_m=torch.log(0.1 * depths),
        opacity_logits=torch.logit(torch.tensor([0.98, 0.98, 0.98], dtype=torch.float64)),
    )
    out = render(stack, camera, np.eye(4), background_rgb=BACKGROUND, backend=backend)
    weights = torch.tensor([0.98, 0.98 * 0.02], dtype=torch.float64)
    expected_rgb = torch.tensor([weights[0], weights[1], 0.0], dtype=torch.float64) + 0.02 * 0.02 * torch.tensor(BACKGROUND, dtype=torch.float64)
    torch.testing.assert_close(out.rgb[8, 8], expected_rgb, atol=1e-12, rtol=0)
    assert out.depth_m[8, 8].item() == pytest.approx((weights * depths[:2]).sum().item(), abs=1e-12)
    assert out.silhouette[8, 8].item() == pytest.approx(1 - 0.02 * 0.02, abs=1e-12)
    clamped = GaussianTensors(stack.means_m[:1], stack.rgb[:1], stack.log_radii_m[:1], torch.tensor([9.0], dtype=torch.float64))
    assert render(clamped, camera, np.eye(4), backend=backend).silhouette[8, 8].item() == pytest.approx(0.99, abs=1e-12)


def test_pose_delta_is_a_right_perturbation():
    camera = camera_of(32, 24)
    world_from_camera = look_at(np.array([0.2, 0.1, -0.2]), np.array([0.0, 0.0, 2.0]), up=np.array([0.0, -1.0, 0.0]))
    twist = np.array([0.05, -0.03, 0.02, 0.04, 0.02, -0.05])
    gaussians = random_gaussians(300, seed=1, dtype=torch.float64)
    perturbed = render(gaussians, camera, world_from_camera, torch.from_numpy(twist), backend="cpu")
    composed = render(gaussians, camera, world_from_camera @ exp_se3(twist), backend="cpu")
    torch.testing.assert_close(perturbed.rgb, composed.rgb, atol=1e-12, rtol=0)
    torch.testing.assert_close(perturbed.depth_m, composed.depth_m, atol=1e-12, rtol=0)


@pytest.mark.parametrize("backend", ["cpu", "reference"])
def test_silhouette_in_unit_interval_and_behind_camera_skipped(backend):
    camera = camera_of(40, 30)
    gaussians = requiring_grad(random_gaussians(800, seed=5, opacity_logit_mean=4.0))
    out = render(gaussians, camera, np.eye(4), backend=backend)
    assert out.silhouette.min() >= 0.0 and out.silhouette.max() <= 1.0
    assert out.silhouette.max() > 0.99
    (out.rgb.sum() + out.depth_m.sum() + out.silhouette.sum()).backward()
    behind = gaussians.means_m[:, 2] <= 0.01
    assert behind.any()
    for name in FIELDS:
        grad = getattr(gaussians, name).grad
        assert torch.isfinite(grad).all(), name
        assert (grad[behind] == 0).all(), name


def test_huge_splats_near_the_camera_match_reference():
    """Splats far larger than the image, with means projecting far outside it (no integer overflow in the boxes)."""
    camera = camera_of(40, 30)
    gaussians = random_gaussians(200, seed=9)
    near = torch.tensor([[0.0, 0.0, 0.02], [100.0, -50.0, 1.0], [-3.0, 2.0, 0.011]])
    gaussians = GaussianTensors(
        means_m=torch.cat([gaussians.means_m, near]),
        rgb=torch.cat([gaussians.rgb, torch.rand(3, 3, generator=torch.Generator().manual_seed(1))]),
        log_radii_m=torch.cat([gaussians.log_radii_m, torch.log(torch.tensor([0.01, 1e17, 0.5]))]),
        opacity_logits=torch.cat([gaussians.opacity_logits, torch.tensor([-2.0, -3.0, -2.5])]),
    )
    fast = render(gaussians, camera, np.eye(4), background_rgb=BACKGROUND, backend="cpu")
    reference = render(gaussians, camera, np.eye(4), background_rgb=BACKGROUND, backend="reference")
    assert (fast.silhouette > 0.05).all()  # the huge splats cover every pixel
    for name in ("rgb", "depth_m", "silhouette"):
        torch.testing.assert_close(getattr(fast, name), getattr(reference, name), atol=1e-5, rtol=0)


def test_tiled_reference_equals_dense_reference():
    """The benchmark's tiled torch baseline culls per tile exactly: same maps as the dense reference."""
    camera = camera_of(50, 35)
    gaussians = random_gaussians(700, seed=11, opacity_logit_mean=1.0)
    screen = project_to_screen(gaussians, camera_frame_means(gaussians, torch.eye(4, dtype=torch.float64)), camera)
    background = torch.tensor(BACKGROUND)
    dense = composite_reference(screen, camera.width, camera.height, background)
    tiled = composite_reference(screen, camera.width, camera.height, background, tile_px=16)
    for name in ("rgb", "depth_m", "silhouette"):
        torch.testing.assert_close(getattr(tiled, name), getattr(dense, name), atol=1e-6, rtol=0)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_tile_lists_hold_the_overlapping_gaussians_front_to_back(dtype):
    """Every tile lists exactly the Gaussians whose pixel box overlaps it, by float32 depth, ties in index order
    (many exact ties, and float64 depths that differ but round to the same float32)."""
    width, height, count = 70, 45, 3000
    rng = np.random.default_rng(4)
    packed = np.zeros((count, cpu_kernel.PACKED_COLUMNS), dtype)
    packed[:, cpu_kernel.U] = rng.uniform(-10, width + 10, count)
    packed[:, cpu_kernel.V] = rng.uniform(-10, height + 10, count)
    packed[:, cpu_kernel.BOUND] = rng.uniform(0.6, 18.0, count)
    depths = rng.choice([-1.0, 0.5, 1.0, 1.0 + 1e-12, 2.0], count) + rng.integers(0, 3, count) * 0.25
    packed[:, cpu_kernel.DEPTH] = depths
    packed[:, cpu_kernel.OPACITY] = 0.5
    bins = cpu_kernel.bin_tiles(packed, width, height)
    entry_gaussian = np.empty(bins.tile_starts[-1], np.int64)
    for gaussian in range(count):
        entry_gaussian[bins.slot_entries[bins.slot_starts[gaussian] : bins.slot_starts[gaussian + 1]]] = gaussian
    depth32 = packed[:, cpu_kernel.DEPTH].astype(np.float32)
    reach = packed[:, cpu_kernel.BOUND].astype(np.float64) + cpu_kernel.BOX_SLACK_PX
    u, v = packed[:, cpu_kernel.U].astype(np.float64), packed[:, cpu_kernel.V].astype(np.float64)
    # Pixel box (clipped to the image) of every Gaussian, brute force.
    x0, x1 = np.maximum(np.ceil(u - reach), 0), np.minimum(np.floor(u + reach), width - 1)
    y0, y1 = np.maximum(np.ceil(v - reach), 0), np.minimum(np.floor(v + reach), height - 1)
    kept = (depth32 > 0.01) & (x0 <= x1) & (y0 <= y1)
    tile = cpu_kernel.TILE_PX
    for index in range(bins.tile_starts.size - 1):
        tx, ty = index % bins.tiles_x, index // bins.tiles_x
        listed = entry_gaussian[bins.tile_starts[index] : bins.tile_starts[index + 1]]
        overlapping = kept & (x1 >= tx * tile) & (x0 <= tx * tile + tile - 1) & (y1 >= ty * tile) & (y0 <= ty * tile + tile - 1)
        assert sorted(listed) == list(np.flatnonzero(overlapping)), index
        expected = sorted(listed, key=lambda gaussian: (depth32[gaussian], gaussian))
        assert list(listed) == expected, index
        np.testing.assert_array_equal(bins.entry_rows[bins.tile_starts[index] : bins.tile_starts[index + 1]], packed[listed])
    np.testing.assert_array_equal(np.diff(bins.slot_starts) > 0, kept)


def test_float32_gaussians_composite_as_their_float64_values_rounded_once():
    """float32 inputs are stored as float32 and computed in float64: maps and gradients equal the float64 path's,
    rounded to float32, bit for bit."""
    camera = camera_of(40, 30)
    gaussians = random_gaussians(600, seed=12, opacity_logit_mean=1.0)
    screen32 = project_to_screen(gaussians, camera_frame_means(gaussians, torch.eye(4, dtype=torch.float64)), camera)
    fields = ("means_px", "conics_px", "bounds_px", "depths_m", "opacity", "rgb")
    generator = torch.Generator().manual_seed(0)
    weights = [torch.randn(shape, generator=generator) for shape in ((30, 40, 3), (30, 40), (30, 40))]
    results = {}
    for dtype in (torch.float32, torch.float64):
        screen = ScreenGaussians(**{name: getattr(screen32, name).detach().to(dtype).requires_grad_(name != "bounds_px") for name in fields})
        out = composite_cpu(screen, camera.width, camera.height, torch.tensor((0.25, 0.5, 0.125), dtype=dtype))  # exact in both
        maps = (out.rgb, out.depth_m, out.silhouette)
        loss = sum((image * weight.to(dtype)).sum() for image, weight in zip(maps, weights))
        grads = torch.autograd.grad(loss, [getattr(screen, name) for name in fields if name != "bounds_px"])
        results[dtype] = [tensor.detach() for tensor in maps + tuple(grads)]
    for single, double in zip(results[torch.float32], results[torch.float64]):
        assert single.dtype == torch.float32
        torch.testing.assert_close(single, double.to(torch.float32), atol=0, rtol=0)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="gsplat runs on CUDA only")
def test_gsplat_agrees_with_cpu_kernel():
    pytest.importorskip("gsplat")
    camera = Camera(64, 48, fx=60.0, fy=60.0, cx=31.5, cy=23.5)
    # Over the whole image, corners included: both draw the EWA footprint (gsplat_backend's docstring lists what
    # still differs: its 1/255 alpha skip and square cut-off).
    gaussians = random_gaussians(500, seed=2, radius_m=(0.02, 0.04))
    gaussians.means_m[:, 2] = gaussians.means_m[:, 2].abs() + 1.5
    cpu = render(gaussians, camera, np.eye(4), background_rgb=BACKGROUND, backend="cpu")
    cuda_gaussians = GaussianTensors(**{name: getattr(gaussians, name).cuda() for name in FIELDS})
    gpu = render(cuda_gaussians, camera, np.eye(4), background_rgb=BACKGROUND, backend="gsplat")
    for name in ("rgb", "silhouette"):
        assert (getattr(gpu, name).cpu() - getattr(cpu, name)).abs().mean() < 0.02, name
    assert (gpu.depth_m.cpu() - cpu.depth_m).abs().mean() < 0.05


def test_sort_depth_keys_equals_numpy_sort():
    """The tile sort (LSD radix on the depth bits of keys already in index order) against np.sort: every digit
    used, many ties, one-key and empty lists."""
    rng = np.random.default_rng(6)
    for count, depth_bits in [(5000, rng.integers(0, 2**31, 5000)), (3000, rng.choice([7, 2**20 + 3, 2**30], 3000)), (1, [5]), (0, [])]:
        indices = np.sort(rng.choice(10 * count + 1, count, replace=False))
        keys = (np.asarray(depth_bits, np.int64) << 32) | indices
        sorted_keys = keys.copy()
        cpu_kernel.sort_depth_keys(sorted_keys)
        np.testing.assert_array_equal(sorted_keys, np.sort(keys))


def test_balanced_groups_cover_every_item_once_and_even_out_the_costs():
    costs = np.random.default_rng(8).uniform(0, 10, 300) ** 2
    for group_count in (1, 2, 3, 7):
        items, group_starts = cpu_kernel.balanced_groups(costs, group_count)
        assert sorted(items) == list(range(costs.size))
        loads = [costs[items[group_starts[g] : group_starts[g + 1]]].sum() for g in range(group_count)]
        assert max(loads) - min(loads) <= costs.max()
