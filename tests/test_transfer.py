"""Transfer functions: interpolation, premultiplication, opacity correction, tables, presets."""

import numpy as np
import pytest

from volumeevm_addon import PRESETS, TransferFunction, VolumeEVMError
from volumeevm_addon.rendering._transfer import opacity_correction

POINTS = [
    (-100.0, 0.0, 0.0, 1.0, 0.0),
    (0.0, 1.0, 0.5, 0.0, 0.4),
    (300.0, 1.0, 1.0, 1.0, 0.9),
]


def test_interpolation_at_and_between_points():
    tf = TransferFunction(POINTS)
    np.testing.assert_array_equal(tf.evaluate([-100.0, 0.0, 300.0]), np.array(POINTS)[:, 1:])
    mid = tf.evaluate([-50.0, 150.0, 75.0])
    np.testing.assert_allclose(mid[0], (0.5, 0.25, 0.5, 0.2), rtol=1e-15)
    np.testing.assert_allclose(mid[1], (1.0, 0.75, 0.5, 0.65), rtol=1e-15)
    np.testing.assert_allclose(mid[2], (1.0, 0.625, 0.25, 0.525), rtol=1e-15)
    # constant beyond the ends
    np.testing.assert_array_equal(tf.evaluate([-1e9, 1e9]), np.array(POINTS)[[0, -1], 1:])
    assert tf.value_range == (-100.0, 300.0)
    assert tf.evaluate(np.zeros((2, 3, 4))).shape == (2, 3, 4, 4)


def test_classify_is_premultiplied_and_float32():
    tf = TransferFunction(POINTS)
    out = tf.classify(np.array([[0.0, 150.0]]), step_mm=1.0)
    assert out.dtype == np.float32 and out.shape == (1, 2, 4)
    straight = tf.evaluate([0.0, 150.0])
    np.testing.assert_allclose(out[0, :, 3], straight[:, 3], rtol=1e-7)
    np.testing.assert_allclose(out[0, :, :3], straight[:, :3] * straight[:, 3:], rtol=1e-7)
    assert tf.classify([0.0], 1.0, dtype=np.float64).dtype == np.float64


def test_opacity_correction_formula_and_composition():
    tf = TransferFunction(POINTS)  # unit length 1 mm
    a = tf.classify([150.0], step_mm=2.5, dtype=np.float64)[0, 3]
    assert a == pytest.approx(1 - (1 - 0.65) ** 2.5, rel=1e-15)
    # Two half steps composited (over) equal one full step.
    values = np.linspace(-150, 350, 41)
    for step in (0.3, 1.0, 1.7):
        full = tf.classify(values, step, dtype=np.float64)
        half = tf.classify(values, step / 2, dtype=np.float64)
        over_a = half[:, 3] + (1 - half[:, 3]) * half[:, 3]
        np.testing.assert_allclose(over_a, full[:, 3], rtol=0, atol=1e-15)
        # colour of a homogeneous segment: c·alpha for any split
        over_c = half[:, :3] + (1 - half[:, 3:]) * half[:, :3]
        np.testing.assert_allclose(over_c, full[:, :3], rtol=0, atol=1e-15)
    # zero step: transparent; alpha 1 stays 1 for any step > 0
    assert opacity_correction(0.7, 0.0) == 0.0
    assert opacity_correction(1.0, 1e-6) == 1.0


def test_reference_length():
    """alpha is per unit_length_mm: a 4 mm reference at a 4 mm step gives alpha itself."""
    tf1 = TransferFunction(POINTS, unit_length_mm=1.0)
    tf4 = TransferFunction(POINTS, unit_length_mm=4.0)
    v = np.array([0.0, 150.0])
    np.testing.assert_allclose(tf4.classify(v, 4.0, dtype=np.float64)[:, 3], [0.4, 0.65],
                               rtol=1e-15)
    np.testing.assert_allclose(tf4.classify(v, 4.0, dtype=np.float64),
                               tf1.classify(v, 1.0, dtype=np.float64), rtol=1e-15)


def test_anisotropic_spacing():
    """The step is a physical length: the same index step along x (0.5 mm voxels) and z (2 mm
    voxels) gets different opacities, consistent with the physical path length."""
    tf = TransferFunction(POINTS)
    spacing = np.array([0.5, 0.5, 2.0])
    index_steps = np.array([[0.25, 0, 0], [0, 0, 0.25], [0.25, 0.25, 0.25]])
    step_mm = np.linalg.norm(index_steps * spacing, axis=1)
    a = tf.classify(np.full(3, 150.0), step_mm, dtype=np.float64)[:, 3]
    np.testing.assert_allclose(a, 1 - 0.35 ** np.array([0.125, 0.5, np.sqrt(0.125**2 * 2 + 0.25)]),
                               rtol=1e-14)
    # 16 z-steps of a 2 mm voxel == 64 x-steps of 0.5 mm voxels over the same 8 mm
    tz = (1 - a[1]) ** 16
    tx = (1 - a[0]) ** 64
    assert tz == pytest.approx(tx, rel=1e-13)


def test_from_points_merges_colour_and_opacity():
    tf = TransferFunction.from_points([(0, 1, 0, 0), (100, 0, 0, 1)], [(50, 0.0), (150, 1.0)])
    np.testing.assert_array_equal(tf.points[:, 0], [0, 50, 100, 150])
    np.testing.assert_allclose(tf.evaluate([25.0, 75.0, 125.0]),
                               [(0.75, 0, 0.25, 0.0), (0.25, 0, 0.75, 0.25), (0, 0, 1, 0.75)],
                               rtol=1e-15)


def test_table_and_quantize():
    tf = TransferFunction(POINTS)
    tab = tf.table(n=401, step_mm=0.5)  # default range: the control points, step 1 HU
    assert tab.shape == (401, 4) and tab.dtype == np.float32
    values = np.array([-100.0, -37.0, 0.0, 123.0, 300.0])
    idx = tf.quantize(values, n=401)
    np.testing.assert_array_equal(idx, [0, 63, 100, 223, 400])
    np.testing.assert_allclose(np.take(tab, idx, axis=0), tf.classify(values, 0.5), rtol=1e-6)
    # clamped outside the range: the function is constant there
    np.testing.assert_array_equal(tf.quantize([-1e6, 1e6], n=401), [0, 400])
    # the straight table is computed once per (lo, hi, n) and cached
    assert tf.straight_table(n=401) is tf.straight_table(n=401)
    assert not tf.straight_table(n=401).flags.writeable
    other = tf.table(lo=-1000, hi=1000, n=64)
    np.testing.assert_allclose(other, tf.classify(np.linspace(-1000, 1000, 64), 1.0), rtol=1e-6)


def _segment_integral(tf, s_f, s_b, length, m=100000):
    """Emission-absorption integral along a linear density ramp, by a fine midpoint sum."""
    u = (np.arange(m) + 0.5) / m
    straight = tf.evaluate(s_f + u * (s_b - s_f))
    depth = -np.log1p(-straight[:, 3]) * length / m / tf.unit_length_mm
    before = np.exp(-np.concatenate([[0.0], np.cumsum(depth)[:-1]]))
    colour = ((before * -np.expm1(-depth))[:, None] * straight[:, :3]).sum(axis=0)
    return np.r_[colour, -np.expm1(-depth.sum())]


def test_preintegrated_table_against_fine_integration():
    tf = TransferFunction([(0.0, 1, 0.5, 0.2, 0.0), (0.3, 0.2, 1, 0.3, 0.9),
                           (0.32, 1, 1, 1, 0.95), (0.5, 0.1, 0.2, 1, 0.0), (1.0, 1, 1, 1, 0.2)],
                          unit_length_mm=2.0)
    n = 101
    tab = tf.preintegrated_table(lo=0.0, hi=1.0, n=n, step_mm=1.5, dtype=np.float64)
    assert tab.shape == (n, n, 4) and not tab.flags.writeable
    assert tf.preintegrated_table(lo=0.0, hi=1.0, n=n, step_mm=1.5, dtype=np.float64) is tab
    # Constant density: the point classification; a rising and a falling segment differ in
    # colour (what lies in front hides what lies behind) but not in opacity.
    np.testing.assert_allclose(tab[np.arange(n), np.arange(n)],
                               tf.table(lo=0.0, hi=1.0, n=n, step_mm=1.5, dtype=np.float64),
                               atol=1e-15)
    np.testing.assert_allclose(tab[..., 3], tab[..., 3].T, atol=1e-12)
    assert np.abs(tab[..., :3] - tab[..., :3].transpose(1, 0, 2)).max() > 0.1
    h = 1.0 / (n - 1)
    for i, j in [(0, 100), (100, 0), (29, 33), (33, 29), (40, 41), (10, 60), (70, 45)]:
        # measured max error 1.5e-4 (8 sub-samples per cell; kinks between grid values)
        np.testing.assert_allclose(tab[i, j], _segment_integral(tf, i * h, j * h, 1.5),
                                   atol=5e-4)
    with pytest.raises(VolumeEVMError, match="step_mm"):
        tf.preintegrated_table(step_mm=0.0)


@pytest.mark.parametrize("name", PRESETS)
def test_presets(name):
    tf = TransferFunction.preset(name, data_range=(0, 1000))
    assert tf.name == name
    assert np.all(np.diff(tf.points[:, 0]) > 0)
    lo, hi = tf.value_range
    tab = tf.table(step_mm=1.0)
    assert tab[0, 3] == 0.0 and tab[:, 3].max() > 0.2  # air / background transparent
    if name.startswith("ct_"):
        assert lo == -1024 and hi == 3071  # Hounsfield units
        assert tf.evaluate([-1000.0])[0, 3] == 0.0
        assert tf.evaluate([1000.0])[0, 3] > 0.2  # bone is visible in every CT preset
    else:
        assert (lo, hi) == (0.0, 1000.0)


def test_preset_errors():
    with pytest.raises(VolumeEVMError, match="unknown preset 'pet'"):
        TransferFunction.preset("pet")
    with pytest.raises(VolumeEVMError, match="data_range: preset 'mri' needs"):
        TransferFunction.preset("mri")
    with pytest.raises(VolumeEVMError, match="data_range: need finite lo < hi"):
        TransferFunction.preset("microscopy", data_range=(5, 5))


@pytest.mark.parametrize("points, match", [
    ([(0, 0, 0, 0, 0), (0, 1, 1, 1, 1)], "strictly increasing"),
    ([(10, 0, 0, 0, 0), (0, 1, 1, 1, 1)], "strictly increasing"),
    ([(0, 0, 0, 0, 1.5)], r"alpha out of \[0, 1\]"),
    ([(0, 0, 0, 0, -0.1)], r"alpha out of \[0, 1\]"),
    ([(0, 2, 0, 0, 0.5)], r"colour out of \[0, 1\]"),
    ([(np.nan, 0, 0, 0, 0.5)], "NaN"),
    ([(0, 0, 0, 0, np.nan)], "NaN"),
    ([(0, 0, 0, 0)], r"shape \(N, 5\)"),
    ([], r"shape"),
    ("ramp", "not a numeric table"),
])
def test_invalid_points(points, match):
    with pytest.raises(VolumeEVMError, match=match):
        TransferFunction(points)


def test_other_invalid_input():
    tf = TransferFunction(POINTS)
    with pytest.raises(VolumeEVMError, match="unit_length_mm"):
        TransferFunction(POINTS, unit_length_mm=0)
    with pytest.raises(VolumeEVMError, match="step_mm"):
        tf.classify([0.0], step_mm=-1.0)
    with pytest.raises(VolumeEVMError, match="step_mm"):
        tf.classify([0.0], step_mm=np.nan)
    with pytest.raises(VolumeEVMError, match="NaN densities"):
        tf.classify([np.nan], step_mm=1.0)
    with pytest.raises(VolumeEVMError, match="NaN densities"):
        tf.quantize([np.nan])
    with pytest.raises(VolumeEVMError, match="lo < hi"):
        tf.table(lo=5, hi=5)
    with pytest.raises(VolumeEVMError, match="at least 2 rows"):
        tf.table(n=1)
    with pytest.raises(VolumeEVMError, match="give both"):
        tf.table(lo=0)
    with pytest.raises(VolumeEVMError, match="opacity_points: values must be strictly"):
        TransferFunction.from_points([(0, 0, 0, 0)], [(1, 0.5), (1, 0.5)])


def test_transparent_between():
    tf = TransferFunction([(0, 0, 0, 0, 0.0), (10, 0, 0, 0, 0.0), (20, 1, 1, 1, 0.5),
                           (30, 1, 1, 1, 0.0), (40, 1, 1, 1, 0.0), (45, 1, 1, 1, 0.2)])
    lo = np.array([-5.0, 0.0, 2.0, 9.0, 10.0, 15.0, 30.0, 31.0, 29.0, 41.0, 39.0, 30.0])
    hi = np.array([-1.0, 10.0, 8.0, 11.0, 10.0, 16.0, 40.0, 35.0, 31.0, 42.0, 39.5, 40.0])
    want = [True, True, True, False, True, False, True, True, False, False, True, True]
    np.testing.assert_array_equal(tf.transparent_between(lo, hi), want)
    # a positive-opacity control point strictly inside the interval is found
    spike = TransferFunction([(0, 0, 0, 0, 0.0), (5, 0, 0, 0, 0.3), (6, 0, 0, 0, 0.0)])
    np.testing.assert_array_equal(spike.transparent_between([0.0, 6.0], [10.0, 10.0]),
                                  [False, True])
