"""Transfer functions: piecewise-linear colour and opacity over the data's own units.

Conventions
-----------
- **Points.** A transfer function is a table of control points ``(value, r, g, b, alpha)``, one row
  each, with strictly increasing ``value`` in the data's own units (HU stays HU). Colour and
  opacity are linearly interpolated between points and held constant beyond the first and the
  last point. :meth:`TransferFunction.from_points` builds the same table from separate colour and
  opacity point lists.
- **Colour** ``r, g, b`` is straight (not premultiplied), in ``[0, 1]``.
- **Opacity per unit length.** ``alpha`` is the opacity accumulated over a physical length
  ``unit_length_mm`` (the reference length Δ0, 1 mm unless told otherwise), like VTK's
  ``ScalarOpacityUnitDistance``. A sample that stands for a ray segment of ``Δ`` mm gets

      alpha' = 1 - (1 - alpha) ** (Δ / Δ0)

  Δ is a *physical* length in mm, so the correction is right for anisotropic voxels: a step
  ``δ`` in index space is ``Δ = |diag(spacing) · δ|`` mm. Two half steps give exactly what one
  full step gives: ``1 - (1 - a_half) ** 2 == alpha'``.
- **Output** of :meth:`TransferFunction.classify` and :meth:`TransferFunction.table` is
  premultiplied RGBA ``(r·alpha', g·alpha', b·alpha', alpha')``.
- **Lookup tables.** :meth:`TransferFunction.table` samples the function at ``n`` equally spaced
  values over ``[lo, hi]`` (by default the range of the control points, outside of which the
  function is constant, so clamping loses nothing there). The straight table is computed once per
  ``(lo, hi, n)`` and cached on the instance; only the cheap opacity correction is redone for
  another step length. :meth:`TransferFunction.quantize` maps densities to table rows.
- **Pre-integrated tables.** :meth:`TransferFunction.preintegrated_table` classifies a whole ray
  segment of ``step_mm`` mm over which the density runs linearly from ``s_f`` (front) to ``s_b``
  (back): the emission–absorption integral along it (Engel, Kraus & Ertl, "High-quality
  pre-integrated volume rendering using hardware-accelerated pixel shading", Graphics Hardware
  2001), so that transfer functions much narrower than the density change per step are not
  missed between samples.
- **Categorical functions** (:meth:`TransferFunction.categorical`, for label maps): a colour
  and opacity per integer label, no blending between labels. Values are rounded to the nearest
  integer before the lookup, the lookup tables have one row per integer
  (:meth:`TransferFunction.lut_size`), and every renderer samples the nearest voxel's label
  instead of interpolating (interpolating label numbers would invent labels that are not
  there: halfway between labels 1 and 3 is label 2).
"""

from dataclasses import KW_ONLY, dataclass, field

import numpy as np

from .._errors import VolumeEVMError

__all__ = ["TransferFunction", "PRESETS", "opacity_correction"]

_PREINT_SUBSAMPLES = 8
"""Midpoint sub-samples per table cell in :meth:`TransferFunction.preintegrated_table`."""
_ALPHA_CAP = 1.0 - 1e-12
"""Opacity 1 per unit length, as a finite extinction for pre-integration (``-ln 1e-12`` ≈ 27.6
per unit length)."""

MAX_CATEGORICAL_SPAN = 32000
"""Largest ``max label - min label`` of a categorical function (its tables have a row per
integer in between)."""

PRESETS = ("ct_skin", "ct_bone", "ct_vessels", "mri", "microscopy")
"""Names accepted by :meth:`TransferFunction.preset`."""


def opacity_correction(alpha, step_mm, unit_length_mm=1.0):
    """Opacity of a segment of ``step_mm`` mm from an opacity given per ``unit_length_mm``.

    Parameters
    ----------
    alpha : ndarray or float
        Opacity in ``[0, 1]`` accumulated over ``unit_length_mm``.
    step_mm : ndarray or float
        Segment length(s) in mm, ``>= 0``; broadcast against ``alpha``.
    unit_length_mm : float, optional
        The reference length Δ0 in mm (default 1).

    Returns
    -------
    ndarray
        ``1 - (1 - alpha) ** (step_mm / unit_length_mm)`` in float64.
    """
    a = np.asarray(alpha, dtype=np.float64)
    r = np.asarray(step_mm, dtype=np.float64) / float(unit_length_mm)
    return 1.0 - np.power(1.0 - a, r)


def _check_points(points):
    try:
        pts = np.array(points, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise VolumeEVMError(f"points: not a numeric table ({exc})") from None
    if pts.ndim != 2 or pts.shape[1] != 5:
        raise VolumeEVMError(
            f"points: expected rows (value, r, g, b, alpha) of shape (N, 5), got shape {pts.shape}"
        )
    if pts.shape[0] < 1:
        raise VolumeEVMError("points: at least one control point is needed")
    if not np.all(np.isfinite(pts)):
        raise VolumeEVMError("points: NaN or infinite entries")
    values = pts[:, 0]
    if np.any(np.diff(values) <= 0):
        bad = int(np.nonzero(np.diff(values) <= 0)[0][0])
        raise VolumeEVMError(
            "points: values must be strictly increasing, "
            f"got {values[bad]!r} then {values[bad + 1]!r}"
        )
    rgb = pts[:, 1:4]
    if np.any(rgb < 0) or np.any(rgb > 1):
        raise VolumeEVMError(f"points: colour out of [0, 1] (min {rgb.min()!r}, max {rgb.max()!r})")
    a = pts[:, 4]
    if np.any(a < 0) or np.any(a > 1):
        raise VolumeEVMError(f"points: alpha out of [0, 1] (min {a.min()!r}, max {a.max()!r})")
    pts.setflags(write=False)
    return pts


def _check_step(step_mm):
    s = np.asarray(step_mm, dtype=np.float64)
    if not np.all(np.isfinite(s)) or np.any(s < 0):
        raise VolumeEVMError(f"step_mm: must be finite and >= 0, got {step_mm!r}")
    return s


@dataclass(frozen=True, eq=False)
class TransferFunction:
    """Piecewise-linear colour and opacity over data values.

    Parameters
    ----------
    points : (N, 5) array_like
        Rows ``(value, r, g, b, alpha)``: ``value`` in data units, strictly increasing; straight
        colour in ``[0, 1]``; ``alpha`` in ``[0, 1]`` per ``unit_length_mm`` of path.
    unit_length_mm : float, optional
        Reference length Δ0 (mm) over which ``alpha`` is accumulated. Default 1 mm.
        Keyword-only, like ``name``.
    name : str, optional
        A label (the preset name for presets).
    is_categorical : bool, optional
        True for a function of integer labels (:meth:`categorical`): values are rounded to the
        nearest integer, renderers sample the nearest voxel. Keyword-only.

    Raises
    ------
    VolumeEVMError
        For a table of the wrong shape, NaN or infinite entries, values that do not increase,
        colour or alpha outside ``[0, 1]``, or a non-positive ``unit_length_mm``; for a
        categorical function, values that are not consecutive integers.

    Examples
    --------
    >>> tf = TransferFunction([(0, 1, 0, 0, 0.0), (100, 1, 0, 0, 0.5)])
    >>> tf.evaluate([50.0]).tolist()
    [[1.0, 0.0, 0.0, 0.25]]
    >>> tf.classify([100.0], step_mm=2.0).tolist()
    [[0.75, 0.0, 0.0, 0.75]]
    """

    points: np.ndarray
    _: KW_ONLY
    unit_length_mm: float = 1.0
    name: str = ""
    is_categorical: bool = False
    _cache: dict = field(default_factory=dict, init=False, repr=False, compare=False)

    def __post_init__(self):
        object.__setattr__(self, "points", _check_points(self.points))
        u = float(self.unit_length_mm)
        if not np.isfinite(u) or u <= 0:
            raise VolumeEVMError(f"unit_length_mm: must be > 0, got {self.unit_length_mm!r}")
        object.__setattr__(self, "unit_length_mm", u)
        object.__setattr__(self, "is_categorical", bool(self.is_categorical))
        values = self.points[:, 0]
        if self.is_categorical and (np.any(values != np.rint(values))
                                    or np.any(np.diff(values) != 1)
                                    or values[-1] - values[0] > MAX_CATEGORICAL_SPAN + 2):
            raise VolumeEVMError("points: a categorical function needs one row per integer "
                                 f"value, at most {MAX_CATEGORICAL_SPAN + 3} rows")

    # ------------------------------------------------------------------ construction
    @classmethod
    def from_points(cls, color_points, opacity_points, *, unit_length_mm=1.0, name=""):
        """Build from separate colour ``(value, r, g, b)`` and opacity ``(value, alpha)`` lists.

        Each list is piecewise linear on its own; the result has a control point at every value
        of either list (so it is the same function), with the other quantity interpolated there.
        Colour and opacity are often edited apart (Blender's colour ramp, VTK's two functions).

        Parameters
        ----------
        color_points : (M, 4) array_like
            Rows ``(value, r, g, b)``, values strictly increasing, colour in ``[0, 1]``.
        opacity_points : (K, 2) array_like
            Rows ``(value, alpha)``, values strictly increasing, ``alpha`` in ``[0, 1]`` per
            ``unit_length_mm``.
        unit_length_mm : float, optional
            Reference length of the opacities (default 1 mm).
        name : str, optional
            A label.

        Returns
        -------
        TransferFunction

        Raises
        ------
        VolumeEVMError
            For lists that are not numeric, of the wrong shape, empty, not finite or whose
            values do not increase, naming the list; and as :class:`TransferFunction`.

        Examples
        --------
        >>> tf = TransferFunction.from_points([(0, 1, 1, 1), (100, 1, 0, 0)], [(50, 0.5)])
        >>> tf.points.tolist()
        [[0.0, 1.0, 1.0, 1.0, 0.5], [50.0, 1.0, 0.5, 0.5, 0.5], [100.0, 1.0, 0.0, 0.0, 0.5]]
        """
        try:
            c = np.array(color_points, dtype=np.float64)
            o = np.array(opacity_points, dtype=np.float64)
        except (TypeError, ValueError) as exc:
            raise VolumeEVMError(f"color_points/opacity_points: not numeric ({exc})") from None
        if c.ndim != 2 or c.shape[1] != 4 or len(c) < 1:
            raise VolumeEVMError(
                f"color_points: expected rows (value, r, g, b), got shape {c.shape}")
        if o.ndim != 2 or o.shape[1] != 2 or len(o) < 1:
            raise VolumeEVMError(
                f"opacity_points: expected rows (value, alpha), got shape {o.shape}")
        for label, arr in (("color_points", c), ("opacity_points", o)):
            if not np.all(np.isfinite(arr)):
                raise VolumeEVMError(f"{label}: NaN or infinite entries")
            if np.any(np.diff(arr[:, 0]) <= 0):
                raise VolumeEVMError(f"{label}: values must be strictly increasing")
        values = np.union1d(c[:, 0], o[:, 0])
        rows = np.empty((len(values), 5))
        rows[:, 0] = values
        for ch in range(3):
            rows[:, 1 + ch] = np.interp(values, c[:, 0], c[:, 1 + ch])
        rows[:, 4] = np.interp(values, o[:, 0], o[:, 1])
        return cls(rows, unit_length_mm=unit_length_mm, name=name)

    @classmethod
    def categorical(cls, colors, *, opacity=0.5, unit_length_mm=1.0, name=""):
        """A categorical function of a label map: a colour and opacity per integer label.

        Labels not given (and values beyond them) are transparent. Renderers sample the
        nearest voxel's label and look it up (module docstring), so a pixel only ever blends
        the colours of labels that are present.

        Parameters
        ----------
        colors : mapping of int to tuple or LabelInfo
            Label to ``(r, g, b)`` (opacity ``opacity``), ``(r, g, b, alpha)``, or a
            :class:`~volumeevm_addon.model.LabelInfo` (its colour, opacity ``opacity``), as in
            ``Volume.labels``; straight colour in ``[0, 1]``, alpha per ``unit_length_mm``.
        opacity : float, optional
            Opacity per ``unit_length_mm`` of labels given without one (default 0.5).
        unit_length_mm : float, optional
            Reference length of the opacities (default 1 mm).
        name : str, optional
            A label.

        Returns
        -------
        TransferFunction
            With ``is_categorical`` True and one control point per integer from the smallest
            label less 1 to the largest plus 1.

        Raises
        ------
        VolumeEVMError
            For no labels, a label that is not an integer, labels more than
            :data:`MAX_CATEGORICAL_SPAN` apart, or a colour that is not 3 or 4 numbers in
            ``[0, 1]`` (naming the label).

        Examples
        --------
        >>> tf = TransferFunction.categorical({1: (1, 0, 0), 3: (0, 0, 1, 0.8)})
        >>> tf.evaluate([1, 2, 3, 2.6]).tolist()
        [[1.0, 0.0, 0.0, 0.5], [0.0, 0.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.8], [0.0, 0.0, 1.0, 0.8]]
        >>> tf.lut_size(4096)
        5
        """
        try:
            items = sorted((_label_number(label), colour) for label, colour in dict(colors).items())
        except (TypeError, ValueError) as exc:
            raise VolumeEVMError(f"colors: expected a mapping label -> colour ({exc})") from None
        if not items:
            raise VolumeEVMError("colors: no labels")
        lo, hi = items[0][0] - 1, items[-1][0] + 1
        if hi - lo > MAX_CATEGORICAL_SPAN + 2:
            raise VolumeEVMError(f"colors: labels {lo + 1} .. {hi - 1} span more than "
                                 f"{MAX_CATEGORICAL_SPAN}")
        rows = np.zeros((hi - lo + 1, 5))
        rows[:, 0] = np.arange(lo, hi + 1)
        for label, colour in items:
            rgba = tuple(getattr(colour, "color", colour))
            if len(rgba) == 3:
                rgba += (opacity,)
            if len(rgba) != 4:
                raise VolumeEVMError(f"colors: label {label}: expected (r, g, b) or "
                                     f"(r, g, b, alpha), got {colour!r}")
            rows[label - lo, 1:] = rgba
        return cls(rows, unit_length_mm=unit_length_mm, name=name, is_categorical=True)

    @classmethod
    def preset(cls, name, *, data_range=None, unit_length_mm=1.0):
        """A ready-made transfer function.

        Parameters
        ----------
        name : str
            ``"ct_skin"`` (skin surface over faint bone), ``"ct_bone"``, ``"ct_vessels"``
            (contrast-filled vessels red, bone faint) — all in Hounsfield units — or ``"mri"``
            (grey ramp) and ``"microscopy"`` (green fluorescence ramp), which need ``data_range``.
        data_range : (float, float), optional
            ``(lo, hi)`` of the data, required for ``"mri"`` and ``"microscopy"``, ignored for
            the CT presets.
        unit_length_mm : float, optional
            Reference length of the opacities (default 1 mm).

        Returns
        -------
        TransferFunction
            Named ``name``.

        Raises
        ------
        VolumeEVMError
            For an unknown ``name`` (the message lists :data:`PRESETS`), or a missing or bad
            ``data_range`` where the preset needs one.

        Examples
        --------
        >>> TransferFunction.preset("mri", data_range=(0, 400)).value_range
        (0.0, 400.0)
        """
        pts = _preset_points(name, data_range)
        return cls(pts, unit_length_mm=unit_length_mm, name=name)

    # ------------------------------------------------------------------ evaluation
    @property
    def value_range(self):
        """``(first, last)`` control-point value: the function is constant outside it."""
        return float(self.points[0, 0]), float(self.points[-1, 0])

    def evaluate(self, values):
        """Straight ``(r, g, b, alpha)`` at ``values`` (alpha per ``unit_length_mm``).

        Parameters
        ----------
        values : array_like
            Data values, any shape.

        Returns
        -------
        (..., 4) ndarray of np.float64
            Interpolated between control points, held constant beyond the first and last.

        Raises
        ------
        VolumeEVMError
            If a value is NaN.
        """
        v = np.asarray(values, dtype=np.float64)
        if np.isnan(v).any():
            raise VolumeEVMError("values: NaN densities cannot be classified")
        if self.is_categorical:
            v = np.rint(v)
        xp = self.points[:, 0]
        out = np.empty(v.shape + (4,), dtype=np.float64)
        for ch in range(4):
            out[..., ch] = np.interp(v, xp, self.points[:, 1 + ch])
        return out

    def lut_size(self, n):
        """Rows of a lookup table over the control points' range for a renderer that would
        take ``n``: ``n``, or for a categorical function one row per integer (exact rows).

        Parameters
        ----------
        n : int
            The renderer's own table size.

        Returns
        -------
        int
        """
        if self.is_categorical:
            return len(self.points)
        return int(n)

    def transparent_between(self, lo, hi):
        """True where the opacity is 0 for every value in ``[lo, hi]``.

        Exact: the maximum of a piecewise-linear function on an interval is at an end or a
        control point inside. Renderers skip blocks whose density range is transparent.

        Parameters
        ----------
        lo, hi : ndarray
            Interval ends, ``lo <= hi``, broadcast together.

        Returns
        -------
        ndarray of bool
        """
        lo = np.asarray(lo, dtype=np.float64)
        hi = np.asarray(hi, dtype=np.float64)
        if self.is_categorical:  # the labels in [lo, hi] (exact on the integer points)
            lo, hi = np.rint(lo), np.rint(hi)
        xp, ap = self.points[:, 0], self.points[:, 4]
        opaque_at = xp[ap > 0]
        inner = np.searchsorted(opaque_at, hi, side="left") - np.searchsorted(
            opaque_at, lo, side="right")
        return (np.interp(lo, xp, ap) == 0) & (np.interp(hi, xp, ap) == 0) & (inner <= 0)

    def classify(self, densities, step_mm, *, dtype=np.float32):
        """Premultiplied RGBA of samples that each stand for ``step_mm`` mm of ray.

        Parameters
        ----------
        densities : array_like
            Data values, any shape.
        step_mm : float or ndarray
            Segment length(s) in mm, ``>= 0``, broadcast against ``densities``.
        dtype : dtype, optional
            Output type (``np.float32``; the reference renderer asks for ``np.float64``).

        Returns
        -------
        (..., 4) ndarray
            ``(r·a', g·a', b·a', a')`` with ``a' = 1 - (1 - alpha) ** (step_mm / unit_length_mm)``.

        Raises
        ------
        VolumeEVMError
            If ``step_mm`` is negative or not finite, or a density is NaN.
        """
        s = _check_step(step_mm)
        rgba = self.evaluate(densities)
        a = opacity_correction(rgba[..., 3], s, self.unit_length_mm)
        rgba[..., 3] = a
        rgba[..., :3] *= a[..., None]
        return rgba.astype(dtype, copy=False)

    # ------------------------------------------------------------------ lookup tables
    def _range(self, lo, hi, n):
        if lo is None and hi is None:
            lo, hi = self.value_range
            if hi <= lo:  # a single control point: a constant function
                hi = lo + 1.0
        if lo is None or hi is None:
            raise VolumeEVMError("lo/hi: give both or neither")
        lo, hi, n = float(lo), float(hi), int(n)
        if not (np.isfinite(lo) and np.isfinite(hi) and hi > lo):
            raise VolumeEVMError(f"lo/hi: need finite lo < hi, got {lo!r}, {hi!r}")
        if n < 2:
            raise VolumeEVMError(f"n: a table needs at least 2 rows, got {n}")
        return lo, hi, n

    def straight_table(self, *, lo=None, hi=None, n=4096):
        """Straight RGBA (alpha per ``unit_length_mm``) at ``n`` equally spaced values.

        The colour table of pre-classifying renderers, which correct opacity per sample later.
        Cached per ``(lo, hi, n)``, so every view of a render shares one.

        Parameters
        ----------
        lo, hi : float, optional
            Value range of the table; both or neither (default: the control points' range).
        n : int, optional
            Number of rows, >= 2 (default 4096).

        Returns
        -------
        (n, 4) ndarray of np.float64
            Read-only; row ``i`` is the value ``lo + i·(hi - lo)/(n - 1)``.

        Raises
        ------
        VolumeEVMError
            For only one of ``lo``/``hi``, ``lo >= hi``, non-finite ends or ``n < 2``.
        """
        lo, hi, n = self._range(lo, hi, n)
        key = (lo, hi, n)
        tab = self._cache.get(key)
        if tab is None:
            tab = self.evaluate(np.linspace(lo, hi, n))
            tab.setflags(write=False)
            self._cache[key] = tab
        return tab

    def table(self, *, lo=None, hi=None, n=4096, step_mm=None, dtype=np.float32):
        """Premultiplied RGBA lookup table for samples of ``step_mm`` mm.

        All parameters are keyword-only: ``lo``, ``hi`` and ``n`` must be the same in
        :meth:`quantize`, which finds a density's row.

        Parameters
        ----------
        lo, hi, n : optional
            The values of the rows, as for :meth:`straight_table` (default: 4096 rows over
            the control points' range).
        step_mm : float, optional
            Segment length in mm, ``>= 0`` (default ``unit_length_mm``: no correction).
        dtype : dtype, optional
            Output type (default ``np.float32``).

        Returns
        -------
        (n, 4) ndarray
            Index it with :meth:`quantize` (``np.take(table, idx, axis=0)``).

        Raises
        ------
        VolumeEVMError
            For a bad range or ``n`` (:meth:`straight_table`) or a negative ``step_mm``.

        Examples
        --------
        >>> tf = TransferFunction([(0, 1, 1, 1, 0.0), (10, 1, 1, 1, 0.5)])
        >>> tf.table(n=3, step_mm=2.0, dtype=np.float64)[:, 3].tolist()
        [0.0, 0.4375, 0.75]
        """
        tab = self.straight_table(lo=lo, hi=hi, n=n)
        s = self.unit_length_mm if step_mm is None else float(_check_step(step_mm))
        out = np.empty_like(tab)
        out[:, 3] = opacity_correction(tab[:, 3], s, self.unit_length_mm)
        out[:, :3] = tab[:, :3] * out[:, 3:4]
        return out.astype(dtype, copy=False)

    def preintegrated_table(self, *, lo=None, hi=None, n=256, step_mm, dtype=np.float32):
        """Premultiplied RGBA of ray segments of ``step_mm`` mm along which the density runs
        linearly from ``s_f`` to ``s_b`` (pre-integrated classification).

        Entry ``[i, j]`` is the segment from ``s_f = lo + i·h`` to ``s_b = lo + j·h``
        (``h = (hi - lo)/(n - 1)``): opacity ``1 - exp(-∫τ)`` and colour ``∫ c·τ·exp(-∫τ)``
        over the segment, with ``τ(s) = -ln(1 - alpha(s)) / unit_length_mm`` the extinction per
        mm (opacity 1 taken as ``1 - 1e-12``) and ``c`` the straight colour: the full integral
        with self-attenuation inside the segment, not the additive approximation. On the
        diagonal (constant density) this is exactly :meth:`table`. Off it, each table cell
        ``[s_m, s_m+1]`` the segment crosses is integrated with 8 midpoint sub-samples and the
        cells are composited front to back; windows of cells are assembled from composites of
        2^k cells, so the table costs O(n² log n). Cached per ``(lo, hi, n, step_mm)``.

        The range must cover every density a segment's ends can take: unlike :meth:`table`,
        clamping an end changes how much of the segment lies in each part of the function.

        Parameters
        ----------
        lo, hi : float, optional
            Density range of rows and columns (default: the control points' range).
        n : int, optional
            Rows and columns, >= 2 (default 256).
        step_mm : float
            Segment length in mm, > 0 (required, keyword-only like the others).
        dtype : dtype, optional
            Output type (default ``np.float32``).

        Returns
        -------
        (n, n, 4) ndarray
            Read-only; rows ``s_f``, columns ``s_b``.

        Raises
        ------
        VolumeEVMError
            For a bad range or ``n`` (:meth:`straight_table`), or a ``step_mm`` that is not a
            finite number > 0.
        """
        lo, hi, n = self._range(lo, hi, n)
        d = float(_check_step(step_mm))
        if d <= 0:
            raise VolumeEVMError(f"step_mm: a pre-integrated segment needs a length > 0, got {d}")
        key = ("preintegrated", lo, hi, n, d, np.dtype(dtype).str)
        tab = self._cache.get(key)
        if tab is None:
            q = _PREINT_SUBSAMPLES
            h = (hi - lo) / (n - 1)
            s = lo + h * (np.arange(n - 1)[:, None] + (np.arange(q) + 0.5) / q)
            straight = self.evaluate(s)  # (cells, q, 4)
            tau = -np.log1p(-np.minimum(straight[..., 3], _ALPHA_CAP)) / self.unit_length_mm
            colour = straight[..., :3]
            out = np.empty((n, n, 4))
            # Rising segments (j > i); falling ones are rising ones of the mirrored function
            # (grid value i is value n - 1 - i of the mirror).
            rows, starts = np.nonzero(np.add.outer(np.arange(n - 1), np.arange(n - 1)) < n - 1)
            for sign in (1, -1):
                c, t = _preintegrate_rising(tau[::sign, ::sign], colour[::sign, ::sign], d)
                i, j = starts, starts + rows + 1
                if sign == -1:
                    i, j = n - 1 - i, n - 1 - j
                out[i, j, :3] = c[rows, starts]
                out[i, j, 3] = 1.0 - t[rows, starts]
            diag = np.arange(n)
            out[diag, diag] = self.table(lo=lo, hi=hi, n=n, step_mm=d, dtype=np.float64)
            tab = out.astype(dtype)
            tab.setflags(write=False)
            self._cache[key] = tab
        return tab

    def quantize(self, densities, *, lo=None, hi=None, n=4096):
        """Row of :meth:`table` for each density: ``rint((d - lo)/(hi - lo)·(n - 1))`` clipped.

        Parameters
        ----------
        densities : array_like
            Data values, any shape.
        lo, hi, n : optional
            The table's range and size, as given to :meth:`table` (keyword-only).

        Returns
        -------
        ndarray of np.int32
            Same shape as ``densities``, in ``[0, n - 1]``: densities beyond the range take the
            end rows, where the function is constant when the range is the default.

        Raises
        ------
        VolumeEVMError
            For a bad range or ``n`` (:meth:`straight_table`), or a NaN density.

        Examples
        --------
        >>> tf = TransferFunction([(0, 1, 1, 1, 0.0), (10, 1, 1, 1, 0.5)])
        >>> tf.quantize([-5.0, 4.9, 5.1, 99.0], n=3).tolist()
        [0, 1, 1, 2]
        """
        lo, hi, n = self._range(lo, hi, n)
        d = np.asarray(densities, dtype=np.float64)
        if np.isnan(d).any():
            raise VolumeEVMError("densities: NaN densities cannot be classified")
        idx = np.rint((d - lo) * ((n - 1) / (hi - lo)))
        np.clip(idx, 0, n - 1, out=idx)
        return idx.astype(np.int32)


def _label_number(label):
    """An integer label from ``label`` (an int, or a float with an integer value)."""
    number = float(label)
    if not number.is_integer():
        raise ValueError(f"label {label!r} is not an integer")
    return int(number)


def _preintegrate_rising(tau, colour, length):
    """Premultiplied colour ``(n-1, n-1, 3)`` and transmittance ``(n-1, n-1)`` of rising
    segments of ``length`` mm, indexed ``[δ - 1, i]`` for the segment from grid value ``i`` to
    ``i + δ`` (entries with ``i + δ > n - 1`` are meaningless).

    ``tau`` and ``colour`` are the extinction and straight colour at the sub-samples of each
    cell, ``(cells, q)`` and ``(cells, q, 3)``. A segment crossing ``δ`` cells spends
    ``length / δ`` in each; each cell is composited from its sub-samples, then windows of
    ``2^k`` cells are composited from two of ``2^(k-1)`` and a window of ``δ`` cells from the
    powers of two in ``δ``.
    """
    cells, q = tau.shape
    delta = np.arange(1, cells + 1)[:, None]
    trans = np.exp(-tau[None] * (length / (q * delta))[..., None])  # (δ, cell, q)
    c = np.zeros((cells, cells, 3))
    t = np.ones((cells, cells))
    for k in range(q):
        c += (t * (1.0 - trans[..., k]))[..., None] * colour[None, :, k]
        t *= trans[..., k]
    levels = [(c, t)]
    width = 1
    while 2 * width <= cells:
        c0, t0 = levels[-1]
        levels.append((c0[:, :-width] + t0[:, :-width, None] * c0[:, width:],
                       t0[:, :-width] * t0[:, width:]))
        width *= 2
    rows = np.arange(cells)[:, None]
    pos = np.broadcast_to(np.arange(cells)[None, :], (cells, cells)).copy()
    acc_c = np.zeros((cells, cells, 3))
    acc_t = np.ones((cells, cells))
    for k, (ck, tk) in enumerate(levels):
        take = ((delta >> k) & 1).astype(bool) & (pos + (1 << k) <= cells)
        idx = np.minimum(pos, ck.shape[1] - 1)
        acc_c = np.where(take[..., None], acc_c + acc_t[..., None] * ck[rows, idx], acc_c)
        acc_t = np.where(take, acc_t * tk[rows, idx], acc_t)
        pos += take << k
    return acc_c, acc_t


def _preset_points(name, data_range):
    hu = {
        "ct_skin": [
            (-1024, 0.00, 0.00, 0.00, 0.00),
            (-600, 0.80, 0.55, 0.45, 0.00),
            (-400, 0.85, 0.62, 0.52, 0.25),
            (-100, 0.90, 0.70, 0.60, 0.35),
            (150, 0.92, 0.76, 0.66, 0.35),
            (400, 1.00, 0.96, 0.90, 0.70),
            (3071, 1.00, 1.00, 1.00, 0.90),
        ],
        "ct_bone": [
            (-1024, 0.00, 0.00, 0.00, 0.00),
            (150, 0.90, 0.75, 0.60, 0.00),
            (300, 0.95, 0.85, 0.70, 0.30),
            (700, 1.00, 0.95, 0.88, 0.80),
            (3071, 1.00, 1.00, 1.00, 1.00),
        ],
        "ct_vessels": [
            (-1024, 0.00, 0.00, 0.00, 0.00),
            (100, 0.60, 0.05, 0.05, 0.00),
            (200, 0.80, 0.10, 0.10, 0.40),
            (450, 0.90, 0.20, 0.15, 0.60),
            (600, 0.90, 0.85, 0.80, 0.05),
            (1200, 1.00, 1.00, 0.95, 0.30),
            (3071, 1.00, 1.00, 1.00, 0.40),
        ],
    }
    if name in hu:
        return hu[name]
    if name not in PRESETS:
        raise VolumeEVMError(f"name: unknown preset {name!r}; choose one of {', '.join(PRESETS)}")
    if data_range is None:
        raise VolumeEVMError(f"data_range: preset {name!r} needs the data's (lo, hi)")
    try:
        lo, hi = (float(x) for x in data_range)
    except (TypeError, ValueError):
        raise VolumeEVMError(f"data_range: expected (lo, hi), got {data_range!r}") from None
    if not (np.isfinite(lo) and np.isfinite(hi) and hi > lo):
        raise VolumeEVMError(f"data_range: need finite lo < hi, got {data_range!r}")
    w = hi - lo
    if name == "mri":
        return [
            (lo, 0.0, 0.0, 0.0, 0.0),
            (lo + 0.15 * w, 0.30, 0.30, 0.30, 0.0),
            (lo + 0.40 * w, 0.70, 0.68, 0.65, 0.10),
            (hi, 1.00, 1.00, 1.00, 0.50),
        ]
    return [  # microscopy
        (lo, 0.0, 0.0, 0.0, 0.0),
        (lo + 0.10 * w, 0.05, 0.40, 0.10, 0.0),
        (lo + 0.50 * w, 0.20, 0.90, 0.30, 0.25),
        (hi, 0.70, 1.00, 0.70, 0.70),
    ]
