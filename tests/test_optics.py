"""The optical model every CPU renderer shares (``rendering/_optics.py``): the record built
from the transfer function and the compiled helpers of classification, opacity correction and
visibility, each against the NumPy rule it twins (``_transfer``, ``_depth``), on random and
real densities."""

import numpy as np
import pytest

from volumeevm_addon import Shading, TransferFunction
from volumeevm_addon.rendering import _depth
from volumeevm_addon.rendering._modes import MODE_CODES, Compositing
from volumeevm_addon.rendering._optics import (
    attenuation_threshold,
    classify,
    classify_preintegrated,
    corrected,
    optics,
    visible,
    visible_threshold,
)
from volumeevm_addon.rendering._transfer import opacity_correction

# Control points on the rows of a 4096-row table over [0, 4095]: linear between rows is the
# function itself, up to the table's float32 rounding.
ON_ROWS = TransferFunction([(0, 0.1, 0.2, 0.3, 0.0), (1000, 0.9, 0.5, 0.1, 0.2),
                            (1001, 0.2, 0.9, 0.4, 0.9), (3000, 1.0, 1.0, 1.0, 0.05),
                            (4095, 0.0, 0.3, 0.6, 0.6)], unit_length_mm=0.8)


def classified(opt, densities):
    """The compiled classification of each density through the record's table, (m, 4)."""
    return np.array([classify(opt.lut, opt.lut_lo, opt.lut_scale, d) for d in densities])


def test_the_record_holds_the_transfer_function_for_the_step():
    step = 0.35
    opt = optics(ON_ROWS, Compositing("under", termination=0.9), Shading(), step_mm=step)
    straight = ON_ROWS.straight_table(lo=0.0, hi=4095.0, n=4096)
    np.testing.assert_array_equal(opt.lut[:, :3], straight[:, :3].astype(np.float32))
    np.testing.assert_array_equal(
        opt.lut[:, 3], opacity_correction(straight[:, 3], step, 0.8).astype(np.float32))
    assert (opt.mode, opt.lut_lo, opt.lut_scale) == (MODE_CODES["under"], 0.0, 1.0)
    assert opt.units == np.float32(step / 0.8) and opt.step_mm == step
    assert opt.visible == _depth.visible_threshold(opt.units, np.float64)
    assert opt.termination == np.float32(0.9) and opt.shaded and not opt.nearest
    assert opt.phong == (0.3, 0.7, 0.3, 20.0, 0.005 * 4095, 0.02 * 4095)
    assert len(opt.pre) == 0


def test_without_a_step_the_table_holds_opacity_per_unit_length():
    """Splatting's record: each sample is corrected for its own path later; no termination."""
    opt = optics(ON_ROWS, Compositing("over", termination=1.0), None)
    straight = ON_ROWS.straight_table(lo=0.0, hi=4095.0, n=4096)
    np.testing.assert_array_equal(opt.lut, straight.astype(np.float32))
    assert opt.units == 1 and opt.unit_length == np.float32(0.8) and opt.termination == np.inf
    assert opt.phong == (0.0,) * 6 and not opt.shaded


def test_xray_needs_no_transfer_function():
    opt = optics(None, Compositing("xray", xray_scale=0.25, xray_offset=-1000.0), None,
                 step_mm=0.5)
    assert opt.lut.shape == (0, 4) and opt.mode == MODE_CODES["xray"]
    assert (opt.xray_scale, opt.xray_offset) == (np.float32(0.25), np.float32(-1000.0))


def test_compiled_classification_is_the_transfer_function():
    """On random densities, inside and beyond the control range: the table read linearly is
    the piecewise-linear function (exactly, but for the table's float32 rounding)."""
    opt = optics(ON_ROWS, Compositing("over"), None)
    rng = np.random.default_rng(3)
    densities = np.concatenate([rng.uniform(-500, 4600, 3000), [0, 1000, 1000.5, 1001, 4095]])
    densities = densities.astype(np.float32)
    got = classified(opt, densities)
    np.testing.assert_allclose(got, ON_ROWS.evaluate(densities), rtol=0, atol=1e-7)
    # Beyond the range the function is constant: the end rows exactly.
    np.testing.assert_array_equal(classified(opt, np.float32([-500.0, 4600.0])),
                                  opt.lut[[0, -1]].astype(np.float64))


def test_compiled_classification_on_ct_densities(data_dir):
    """The CT head's densities through the bone preset: within the change of the function
    over one row of the table (linear interpolation of samples of a piecewise-linear
    function), and exactly NumPy's linear interpolation of the same table."""
    tf = TransferFunction.preset("ct_bone")
    opt = optics(tf, Compositing("over"), None, step_mm=0.5)
    densities = np.load(data_dir / "ct_head_invesalius.npy")[::7, ::7, ::5].ravel()
    densities = np.unique(densities).astype(np.float32)
    got = classified(opt, densities)
    rows = np.float64((densities - np.float32(opt.lut_lo)) * np.float32(opt.lut_scale))
    rows = np.clip(rows, 0, len(opt.lut) - 1)
    for ch in range(4):
        expected = np.interp(rows, np.arange(len(opt.lut)), opt.lut[:, ch].astype(np.float64))
        np.testing.assert_allclose(got[:, ch], expected, rtol=0, atol=1e-12)
    straight = tf.evaluate(densities)
    straight[:, 3] = opacity_correction(straight[:, 3], 0.5, tf.unit_length_mm)
    row_change = np.abs(np.diff(opt.lut.astype(np.float64), axis=0)).max(axis=0)
    assert (np.abs(got - straight) <= row_change + 1e-7).all()
    assert got[:, 3].max() > 0.1  # bone is there


def test_categorical_labels_classify_exactly():
    """A categorical function has a row per label: each label reads its own row, no blend."""
    tf = TransferFunction.categorical({3: (1.0, 0.0, 0.0, 0.6), 4: (0.0, 1.0, 0.0, 0.3),
                                       9: (0.0, 0.0, 1.0, 0.9)})
    opt = optics(tf, Compositing("over"), None)
    assert opt.nearest
    labels = np.arange(2, 11, dtype=np.float32)
    np.testing.assert_array_equal(classified(opt, labels),
                                  tf.evaluate(labels).astype(np.float32).astype(np.float64))


def test_preintegrated_diagonal_is_the_table_for_the_step():
    """A segment of constant density reads the pre-integrated table's diagonal: the opacity of
    the step and the straight colour."""
    tf = TransferFunction.preset("mri", data_range=(0, 200))
    opt = optics(tf, Compositing("over"), None, step_mm=0.6, pre_range=(0.0, 255.0))
    table = tf.table(lo=0.0, hi=255.0, n=opt.pre_n, step_mm=0.6, dtype=np.float32)
    step = 255.0 / (opt.pre_n - 1)
    for i in (0, 17, 100, 128, 255):
        d = np.float32(i * step)
        r, g, b, a = classify_preintegrated(opt.pre, opt.pre_lo, opt.pre_scale, opt.pre_n, d, d)
        assert a == table[i, 3]
        if a > 0:
            np.testing.assert_allclose((r, g, b), table[i, :3] / a, rtol=1e-6)


def test_opacity_correction_is_the_closed_formula():
    rng = np.random.default_rng(5)
    alphas = np.concatenate([rng.random(500), [0.0, 1.0, 0.5]])
    ratios = np.concatenate([rng.uniform(0, 3, 500), [0.25, 2.0, 0.0]])
    got = np.array([corrected(a, r) for a, r in zip(alphas, ratios)])
    np.testing.assert_allclose(got, 1.0 - (1.0 - alphas) ** ratios, rtol=1e-15, atol=1e-16)
    np.testing.assert_allclose(got, opacity_correction(alphas, ratios), rtol=1e-15, atol=1e-16)
    assert got[-1] == 0.0 and got[-2] == 1.0  # no length: transparent; opaque stays opaque
    # One length is the opacity itself, bit for bit (not 1 - (1 - a)).
    assert all(corrected(a, np.float32(1)) == a for a in alphas)
    # Two half lengths give one length.
    halves = np.array([1 - (1 - corrected(a, 0.5)) ** 2 for a in alphas])
    np.testing.assert_allclose(halves, alphas, rtol=0, atol=1e-15)


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_visibility_rule_is_depths(dtype):
    """The compiled rule with the threshold in the samples' precision decides as
    ``_depth.visible`` does, at and around the threshold of random lengths."""
    rng = np.random.default_rng(11)
    for units in np.concatenate([rng.uniform(0.01, 4, 20), [1.0, 0.0]]):
        threshold = visible_threshold(units)
        assert threshold == _depth.visible_threshold(units, np.float64)
        t = dtype(threshold)
        alphas = np.array([0, t, np.nextafter(t, dtype(0)), np.nextafter(t, dtype(1)), 2 * t,
                           t / 2, 1, -t], dtype)
        got = np.array([visible(a, t) for a in alphas])
        np.testing.assert_array_equal(got, _depth.visible(alphas, units))
        if units > 0:
            assert got.tolist()[:4] == [False, True, False, True]


def test_attenuation_rule_is_depths():
    rng = np.random.default_rng(13)
    for mm in np.concatenate([rng.uniform(0.01, 5, 20), [1.0]]):
        t = np.float32(attenuation_threshold(mm))  # (Numba returns float32 as a Python float)
        assert t == _depth.attenuation_threshold(mm, np.float32)
        taus = np.array([0, t, np.nextafter(t, np.float32(0)), 3 * t, t / 3], np.float32)
        got = np.array([visible(tau, t) for tau in taus])
        np.testing.assert_array_equal(got, _depth.attenuates(taus, mm))
        assert got.tolist() == [False, True, False, True, False]
