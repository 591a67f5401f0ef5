"""PSNR / SSIM / LPIPS against values known in closed form."""

import logging

import numpy as np
import pytest

from tambridge.evaluation import rendering
from tambridge.evaluation.rendering import lpips_value, psnr_db, score_renders, ssim_value


def test_psnr_of_a_known_mse():
    rng = np.random.default_rng(0)
    observed = rng.uniform(0.2, 0.8, size=(30, 40, 3))
    signs = rng.choice([-1.0, 1.0], size=observed.shape)
    rendered = observed + 0.05 * signs  # every pixel off by exactly 0.05: MSE = 0.0025
    assert psnr_db(rendered, observed) == pytest.approx(-10 * np.log10(0.0025), abs=1e-9)  # 26.0206 dB
    assert psnr_db(observed, observed) == float("inf")


def test_ssim_of_constant_images_is_the_luminance_term():
    # Constant images have zero variance, so SSIM = (2 a b + C1) / (a^2 + b^2 + C1) with C1 = (0.01 * 1)^2.
    a, b = 0.3, 0.6
    expected = (2 * a * b + 1e-4) / (a * a + b * b + 1e-4)
    assert ssim_value(np.full((32, 32, 3), a), np.full((32, 32, 3), b)) == pytest.approx(expected, rel=1e-5)  # float32 window weights


def test_ssim_is_one_for_equal_images_and_drops_with_noise():
    rng = np.random.default_rng(1)
    image = rng.uniform(0, 1, size=(48, 64, 3))
    assert ssim_value(image, image) == pytest.approx(1.0, abs=1e-6)
    scores = [ssim_value(np.clip(image + rng.normal(0, sigma, image.shape), 0, 1), image) for sigma in (0.05, 0.1, 0.2)]
    assert 1.0 > scores[0] > scores[1] > scores[2]


def test_lpips_is_none_with_a_warning_when_weights_are_missing(caplog, monkeypatch, tmp_path):
    monkeypatch.setattr(rendering.torch.hub, "get_dir", lambda: str(tmp_path))  # an empty hub cache
    rendering.lpips_model.cache_clear()
    try:
        with caplog.at_level(logging.WARNING, logger="tambridge.evaluation.rendering"):
            value = lpips_value(np.zeros((8, 8, 3)), np.ones((8, 8, 3)))
        assert value is None
        assert "LPIPS not computed" in caplog.text
        scores = score_renders([(0, np.zeros((16, 16, 3)), np.full((16, 16, 3), 0.1))])
        assert scores.lpips is None and scores.summary()["lpips"] is None
        assert scores.summary()["psnr_db"] == pytest.approx(20.0)
    finally:
        rendering.lpips_model.cache_clear()
