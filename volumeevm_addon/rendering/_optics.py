"""The optical model every CPU renderer shares: one record of how samples become colour, built
once per render, and the compiled helpers of classification, opacity correction and the
visibility rule that every kernel uses.

:func:`optics` builds the :data:`Optics` record from the transfer function, the compositing
settings (mode, termination, X-ray), the shading and the step: the classification table
(straight colour, opacity over the step, linear between rows), the pre-integrated table, the
step in unit lengths of the transfer function and the visibility threshold of a whole step.
What only one method needs stays with it (the ray caster's view, splatting's sheet axes,
shear-warp's quantized pre-classification tables and its light in float32).

The helpers are the compiled twins of the NumPy rules: :func:`classify` of
:meth:`TransferFunction.evaluate` through the table, :func:`corrected` of
:func:`._transfer.opacity_correction`, :func:`visible` with :func:`visible_threshold` and
:func:`attenuation_threshold` of :func:`._depth.visible` and :func:`._depth.attenuates`. They
take numbers and the arrays they read (a compiled call passing arrays costs their reference
counting), in the precisions the kernels always used: float32 table positions, float64 colour
and opacity.
"""

from collections import namedtuple

import numpy as np

from .._jit import kernel
from . import _depth
from ._checks import categorical
from ._depth import VISIBLE_ALPHA, VISIBLE_OPTICAL_DEPTH
from ._modes import MODE_CODES
from ._shading import fade_magnitudes, headlight_weights

__all__ = ["Optics", "optics", "table_cell", "classify", "classify_preintegrated", "corrected",
           "visible", "visible_threshold", "attenuation_threshold"]

_LUT_SIZE = 4096
"""Rows of the classification table (a categorical function: one per label,
:meth:`TransferFunction.lut_size`)."""
_PREINT_SIZE = 256
"""Rows and columns of the pre-integrated table."""

Optics = namedtuple("Optics", "mode termination nearest shaded phong lut lut_lo lut_scale pre "
                              "pre_lo pre_scale pre_n step_mm unit_length units visible "
                              "xray_scale xray_offset")
Optics.__doc__ = """How samples become colour, for every CPU renderer (:func:`optics`).

``mode``: :data:`._modes.MODE_CODES`; ``termination`` (float32): ``"over"`` stops a ray at this
opacity (inf: never); ``nearest``: a sample takes its nearest voxel's density (categorical
transfer functions: label numbers are never interpolated); ``shaded``: gradient shading with
``phong`` (6 floats, zeros unshaded), the Blinn–Phong weights and the fade
(:func:`._shading.headlight_weights`); ``lut`` (N, 4) float32 over ``lut_lo + i / lut_scale``
(floats): straight colour and the opacity over ``step_mm`` (empty for X-ray; the read is
:func:`classify`); ``pre`` (n·n, 4) float32 with ``pre_lo``, ``pre_scale``, ``pre_n``: the
pre-integrated table for segments of ``step_mm`` (empty: off); ``step_mm`` (float): the step the
tables are made for (the transfer function's unit length when there is none); ``unit_length``
(float32): the transfer function's unit length in mm; ``units`` (float32): the step in unit
lengths; ``visible`` (float64): the opacity from which a sample of a whole step is visible
(:func:`._depth.visible_threshold`); ``xray_scale``, ``xray_offset`` (float32): X-ray's
``μ = xray_scale · max(d - xray_offset, 0)`` per mm."""


def optics(tf, compositing, shading, *, step_mm=None, lut=True, pre_range=None):
    """The :data:`Optics` of a render.

    ``tf``: the transfer function (None for X-ray); ``compositing``: the checked
    :class:`._modes.Compositing`; ``shading``: the checked :class:`._shading.Shading` or None
    (over/under only); ``step_mm``: the samples' step, for which the tables' opacity is
    corrected (None: opacity per unit length, corrected per sample); ``lut``: build the
    classification table (except for X-ray); ``pre_range``: the densities ``(lo, hi)`` the
    pre-integrated table covers (None: no pre-integration).
    """
    mode = compositing.mode
    unit_length = 1.0 if tf is None else tf.unit_length_mm
    step = unit_length if step_mm is None else step_mm
    units = np.float32(step / unit_length)
    table, lut_lo, lut_scale = np.zeros((0, 4), np.float32), 0.0, 0.0
    if lut and mode != "xray":
        lo, hi = tf.value_range
        hi = hi if hi > lo else lo + 1.0
        size = tf.lut_size(_LUT_SIZE)
        table = tf.straight_table(lo=lo, hi=hi, n=size)
        if step_mm is not None:
            table = table.copy()
            table[:, 3] = 1.0 - np.power(1.0 - table[:, 3], step_mm / unit_length)
        table, lut_lo, lut_scale = table.astype(np.float32), lo, (size - 1) / (hi - lo)
    pre, pre_lo, pre_scale, pre_n = np.zeros((0, 4), np.float32), 0.0, 0.0, 0
    if pre_range is not None:
        pre_lo, hi = pre_range
        pre_n = _PREINT_SIZE
        pre = tf.preintegrated_table(lo=pre_lo, hi=hi, n=pre_n, step_mm=step_mm).reshape(-1, 4)
        pre, pre_scale = np.ascontiguousarray(pre), (pre_n - 1) / (hi - pre_lo)
    phong = (0.0,) * 6
    if shading is not None:
        phong = headlight_weights(shading, fade_magnitudes(shading, tf))
    termination = compositing.termination
    return Optics(MODE_CODES[mode], np.float32(termination if termination < 1 else np.inf),
                  categorical(tf, mode), shading is not None, phong, table, float(lut_lo),
                  float(lut_scale), pre, float(pre_lo), float(pre_scale), pre_n, float(step),
                  np.float32(unit_length), units,
                  float(_depth.visible_threshold(units, np.float64)),
                  np.float32(compositing.xray_scale), np.float32(compositing.xray_offset))


# ---------------------------------------------------------------------------- classification
@kernel
def table_cell(value, lo, scale, n):
    """Row of an ``n``-row table over ``lo + i / scale`` below density ``value`` and the
    fraction towards the next (float64); the position is clamped to the table, in float32."""
    x = min(max((value - np.float32(lo)) * np.float32(scale), np.float32(0)), np.float32(n - 1))
    i = min(np.int64(x), n - 2)
    return i, np.float64(x) - i


@kernel
def classify(lut, lo, scale, value):
    """Straight RGB and opacity (float64) of density ``value``: linear in the table ``lut``
    over ``lo + i / scale`` (:data:`Optics`)."""
    i, f = table_cell(value, lo, scale, lut.shape[0])
    return (lut[i, 0] + f * (lut[i + 1, 0] - lut[i, 0]),
            lut[i, 1] + f * (lut[i + 1, 1] - lut[i, 1]),
            lut[i, 2] + f * (lut[i + 1, 2] - lut[i, 2]),
            lut[i, 3] + f * (lut[i + 1, 3] - lut[i, 3]))


@kernel
def classify_preintegrated(pre, lo, scale, n, front, back):
    """Straight RGB and opacity (float64) of a segment of one step whose density runs linearly
    from ``front`` to ``back``: bilinear in the pre-integrated table ``pre`` (:data:`Optics`),
    the colour its premultiplied colour over its opacity."""
    i, fi = table_cell(front, lo, scale, n)
    j, fj = table_cell(back, lo, scale, n)
    flat = i * n + j
    alpha = _bilinear(pre, flat, n, fi, fj, 3)
    over = alpha if alpha > 0 else 1.0
    return (_bilinear(pre, flat, n, fi, fj, 0) / over, _bilinear(pre, flat, n, fi, fj, 1) / over,
            _bilinear(pre, flat, n, fi, fj, 2) / over, alpha)


@kernel
def _bilinear(tab, flat, n, fi, fj, ch):
    """Channel ``ch`` of the (n·n, 4) table ``tab`` from rows ``flat``, ``flat + 1``,
    ``flat + n``, ``flat + n + 1`` (fractions ``fi`` across, ``fj`` along), float64."""
    top = tab[flat, ch] + fj * (tab[flat + 1, ch] - tab[flat, ch])
    bottom = tab[flat + n, ch] + fj * (tab[flat + n + 1, ch] - tab[flat + n, ch])
    return top + fi * (bottom - top)


# ---------------------------------------------------------------------------- correction
@kernel
def corrected(alpha, ratio):
    """Opacity over ``ratio`` lengths of a sample of opacity ``alpha`` over one (float64):
    ``1 - (1 - alpha) ** ratio`` (:func:`._transfer.opacity_correction`), ``alpha`` itself
    for one length."""
    if ratio != 1:
        return 1.0 - (1.0 - alpha) ** np.float64(ratio)
    return alpha


# ---------------------------------------------------------------------------- visibility
@kernel
def visible(value, threshold):
    """The visibility rule of :mod:`._depth` for one sample: its opacity (X-ray: its optical
    depth) ``value`` is above 0 and at least ``threshold`` (:func:`visible_threshold`,
    :func:`attenuation_threshold`, in ``value``'s precision)."""
    return value > 0 and value >= threshold


@kernel
def visible_threshold(units):
    """:func:`._depth.visible_threshold` (float64) of a sample over ``units`` unit lengths."""
    return 1.0 - (1.0 - VISIBLE_ALPHA) ** np.float64(units)


@kernel
def attenuation_threshold(mm):
    """:func:`._depth.attenuation_threshold` (float32) of an X-ray sample over ``mm``."""
    return np.float32(np.float64(mm) * VISIBLE_OPTICAL_DEPTH)
