"""Image and sweep metrics: known values on small synthetic images."""

import numpy as np
import pytest

from volumeevm_addon.metrics import (
    bias_jump,
    image_errors,
    luminance,
    popping_index,
    rmse,
    spectral_peak,
    temporal_errors,
)


def _image(value, alpha, shape=(8, 10)):
    img = np.zeros(shape + (4,), np.float32)
    img[..., :3] = value
    img[..., 3] = alpha
    return img


def test_image_errors_of_a_constant_offset():
    ref = _image(0.2, 0.5)
    img = ref.copy()
    img[..., 3] += 0.1
    e = image_errors(img, ref)
    assert e["rmse"] == pytest.approx(0.05, abs=1e-6)  # one channel of four off by 0.1
    assert e["rmse_alpha"] == pytest.approx(0.1, abs=1e-6)
    assert e["max_abs"] == pytest.approx(0.1, abs=1e-6)
    assert e["psnr"] == pytest.approx(-20 * np.log10(0.05), abs=1e-3)
    assert image_errors(ref, ref)["psnr"] == float("inf")


def test_foreground_rmse_ignores_empty_background():
    ref = np.zeros((10, 10, 4))
    img = ref.copy()
    img[0, 0] = 0.4  # one pixel differs by 0.4 in each channel
    e = image_errors(img, ref)
    assert e["rmse_foreground"] == pytest.approx(0.4)
    assert e["rmse"] == pytest.approx(0.04)
    with pytest.raises(ValueError, match="shape"):
        rmse(img, ref[:5])


def test_popping_index_and_temporal_error_see_a_jump_the_reference_lacks():
    ramp = np.linspace(0.1, 0.3, 21)
    refs = np.stack([_image(v, v) for v in ramp])
    smooth = refs + 0.01  # a constant bias: no popping, no temporal error
    assert popping_index(smooth, refs) == pytest.approx(1.0, rel=1e-4)
    np.testing.assert_allclose(temporal_errors(smooth, refs), 0.0, atol=1e-7)
    jumped = smooth.copy()
    jumped[11:, ..., :3] += 0.05  # a step at frame 11: five reference steps at once
    assert popping_index(jumped, refs) == pytest.approx(6.0, rel=1e-3)
    te = temporal_errors(jumped, refs)
    assert te.argmax() == 10 and te[10] > 0.04 and np.delete(te, 10).max() < 1e-7
    angles = np.linspace(40, 50, 21)
    assert bias_jump(angles, jumped, refs) == pytest.approx(
        np.mean((luminance(jumped[11:]) - luminance(refs[11:])) / luminance(refs[11:]))
        - np.mean((luminance(jumped[:10]) - luminance(refs[:10])) / luminance(refs[:10])))
    with pytest.raises(ValueError, match="both sides"):
        bias_jump(angles[:5], jumped[:5], refs[:5])


def test_spectral_peak_separates_bands_from_noise():
    y, x = np.mgrid[0:64, 0:64]
    bands = 0.01 * np.sin(2 * np.pi * x / 8.0)
    noise = np.random.default_rng(1).normal(0, 0.01, (64, 64))
    assert spectral_peak(bands) > 100
    assert spectral_peak(noise) < 6
    assert spectral_peak(np.zeros((8, 8))) == 0.0
