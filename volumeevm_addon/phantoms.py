"""Test volumes made in code, with closed-form images where they exist (like ``skimage.data``).

Every renderer is measured against the dense reference
(:mod:`volumeevm_addon.rendering._reference`); these phantoms add absolute anchors and the stress
cases of ``../shared/design/notes/dvr_evaluation.md`` (§2, §4, §7.2). Each volume function
returns a :class:`~volumeevm_addon.Volume` (``source="phantom:<name>"``, spacing 1 mm unless told
otherwise, origin 0: the centre of voxel ``(0, 0, 0)``), so
``VolumeEVM.from_volume(vol, threshold)`` builds its region. Index order is ``[x, y, z]``.

=====================  ==========================================================================
function               what it exposes, and its closed form
=====================  ==========================================================================
:func:`marschner_lobb` reconstruction and sampling near Nyquist (ripple, ringing);
                       ``ρ = [1 - sin(πz/2) + α(1 + cos(2π f_M cos(π r/2)))] / (2(1 + α))``,
                       ``r = √(x² + y²)``, f_M = 6, α = 0.25 on ``[-1, 1]³``
:func:`box`            opacity correction along oblique rays (F2), anisotropic voxels (F15),
                       footprint normalisation (F10); for a constant opacity ``a`` per mm,
                       ``alpha = 1 - (1 - a)^chord`` with :func:`box_chords_mm`
:func:`gaussian_blobs` integration, zoom, splat kernels; for extinction ``k·density`` per mm
                       (:func:`extinction_tf`), ``alpha = 1 - exp(-Σ k A σ √π exp(-b²/σ²))``
                       (:func:`blobs_optical_depth`, ``b`` the centre's distance to the ray)
:func:`ramp`           interpolation and classification order; linear, so trilinear is exact
:func:`checker`        sampling phase, moiré under minification (sharp 0/1 checks)
:func:`thin_plate`     thin structures at grazing angles (F14); the profile across the plate
                       integrates to ``thickness`` voxels
:func:`shell`          thin curved structures (F14); the same profile along the radius
:func:`noise`          gradient and shading stability (F16), region cuts through material (F17)
:func:`timing_volume`  timing at the target size (256³): a smooth object with empty space round
                       it, as real scans have
=====================  ==========================================================================

>>> from volumeevm_addon import VolumeEVM, phantoms
>>> vol = phantoms.box((8, 8, 8), lo=(2, 2, 2), hi=(6, 6, 6))
>>> VolumeEVM.from_volume(vol, 0.5).voxel_count
64
"""

import numpy as np

from ._errors import VolumeEVMError
from .model._volume import BLENDER_UNITS_PER_MM, Volume
from .rendering._transfer import TransferFunction

__all__ = ["marschner_lobb", "marschner_lobb_value", "box", "box_chords_mm", "gaussian_blobs",
           "blobs_optical_depth", "extinction_tf", "ramp", "checker", "thin_plate", "shell",
           "noise", "timing_volume"]

ML_FM = 6.0
"""Marschner–Lobb modulation frequency f_M."""
ML_ALPHA = 0.25
"""Marschner–Lobb weight α of the radial term."""


# ---------------------------------------------------------------------------- checks
def _shape(shape):
    try:
        s = tuple(int(n) for n in shape)
    except (TypeError, ValueError):
        raise VolumeEVMError(f"shape: expected 3 positive integers, got {shape!r}") from None
    if len(s) != 3 or min(s) < 1 or s != tuple(shape):
        raise VolumeEVMError(f"shape: expected 3 positive integers, got {shape!r}")
    return s


def _vector(name, value, positive=False):
    try:
        v = np.array(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise VolumeEVMError(f"{name}: expected 3 numbers, got {value!r}") from None
    if v.shape != (3,) or not np.all(np.isfinite(v)) or (positive and np.any(v <= 0)):
        kind = "positive numbers" if positive else "finite numbers"
        raise VolumeEVMError(f"{name}: expected 3 {kind}, got {value!r}")
    return v


def _positive(name, value):
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise VolumeEVMError(f"{name}: expected a number, got {value!r}") from None
    if not np.isfinite(v) or v <= 0:
        raise VolumeEVMError(f"{name}: must be a finite number > 0, got {value!r}")
    return v


def _volume(array, name, spacing=(1.0, 1.0, 1.0), origin=(0.0, 0.0, 0.0)):
    return Volume(array, spacing=tuple(float(s) for s in spacing),
                  origin=tuple(float(o) for o in origin), units="a.u.",
                  source=f"phantom:{name}")


def _centred_index(shape):
    """Index coordinates relative to the grid's centre, as three broadcastable axes."""
    return np.ix_(*(np.arange(n) - (n - 1) / 2.0 for n in shape))


# ---------------------------------------------------------------------------- Marschner–Lobb
def marschner_lobb_value(x, y, z):
    """The Marschner–Lobb function at ``(x, y, z)``, the continuous truth behind
    :func:`marschner_lobb`.

    ``ρ = [1 - sin(πz/2) + α(1 + cos(2π f_M cos(π r/2)))] / (2(1 + α))`` with ``r = √(x² + y²)``,
    ``f_M = 6``, ``α = 0.25`` (Marschner & Lobb, Visualization '94), domain ``[-1, 1]³``.

    Parameters
    ----------
    x, y, z : array_like
        Positions in the function's units, broadcast together.

    Returns
    -------
    ndarray of np.float64
        Values in ``[0, 1]`` inside the domain.

    Examples
    --------
    >>> round(float(marschner_lobb_value(0.0, 0.0, 1.0)), 12)
    0.2
    """
    x, y, z = (np.asarray(v, dtype=np.float64) for v in (x, y, z))
    r = np.sqrt(x * x + y * y)
    radial = np.cos(2.0 * np.pi * ML_FM * np.cos(0.5 * np.pi * r))
    return (1.0 - np.sin(0.5 * np.pi * z) + ML_ALPHA * (1.0 + radial)) / (2.0 * (1.0 + ML_ALPHA))


def marschner_lobb(n=41):
    """The Marschner–Lobb signal sampled at ``n`` points per axis over ``[-1, 1]³``.

    Sample ``i`` sits at ``x = -1 + 2i/(n - 1)``, both faces included. The default 41 points
    (spacing 0.05 of the function's unit) is the convention of open-scivis'
    ``marschner_lobb_41x41x41`` and of the TU Wien thesis (99.8 % of the signal's energy below
    the grid's Nyquist limit; the radial term's local frequency peaks at 9.42 against a limit of
    10 cycles per unit, so this is the hard case). Voxels are 1 mm (the whole cube is 40 mm).

    Parameters
    ----------
    n : int, optional
        Samples per axis, >= 2 (default 41).

    Returns
    -------
    Volume
        float64 values in ``[0, 1]``.

    Raises
    ------
    VolumeEVMError
        If ``n`` is not an integer >= 2.

    Examples
    --------
    >>> marschner_lobb(5).shape
    (5, 5, 5)
    """
    if int(n) != n or n < 2:
        raise VolumeEVMError(f"n: expected an integer >= 2, got {n!r}")
    t = np.linspace(-1.0, 1.0, int(n))
    array = marschner_lobb_value(t[:, None, None], t[None, :, None], t[None, None, :])
    return _volume(np.clip(array, 0.0, 1.0), "marschner_lobb")


# ---------------------------------------------------------------------------- box
def box(shape=(32, 32, 32), lo=(8, 8, 8), hi=(24, 24, 24), density=1.0, spacing=(1, 1, 1), *,
        origin=(0.0, 0.0, 0.0)):
    """A homogeneous box: voxels with ``lo <= index < hi`` (per axis) hold ``density``, others 0.

    The box's solid is the union of those voxels' cells: index space ``lo - 0.5 .. hi - 0.5``
    (:func:`box_chords_mm`). With the boundary policy "clamp" a VolumeEVM of the box (any
    threshold in ``(0, density]``) renders exactly as that homogeneous solid.

    Parameters
    ----------
    shape : tuple of 3 int, optional
        Grid size (default 32³).
    lo, hi : tuple of 3 int, optional
        First voxel in and first voxel past the box per axis, ``0 <= lo < hi <= shape``.
    density : float, optional
        The box's density (default 1).
    spacing : tuple of 3 float, optional
        Voxel size in mm (default 1 mm).
    origin : tuple of 3 float, optional
        Position (mm) of the centre of voxel ``(0, 0, 0)``: moves the grid, e.g. to put the
        same physical box on grids of another spacing. Keyword-only.

    Returns
    -------
    Volume
        float64: ``density`` inside the box, 0 elsewhere.

    Raises
    ------
    VolumeEVMError
        For a bad ``shape``, ``lo``/``hi`` that are not integers inside the grid with
        ``lo < hi``, or a bad ``spacing`` or ``origin``.

    Examples
    --------
    >>> float(box((4, 4, 4), lo=(1, 1, 1), hi=(3, 3, 3)).array.sum())
    8.0
    """
    s = _shape(shape)
    lo_i, hi_i = (np.asarray(v) for v in (lo, hi))
    if (lo_i.shape != (3,) or hi_i.shape != (3,) or not np.all(lo_i == np.round(lo_i))
            or not np.all(hi_i == np.round(hi_i))):
        raise VolumeEVMError(f"lo/hi: expected 3 integers each, got {lo!r}, {hi!r}")
    if np.any(lo_i < 0) or np.any(hi_i > s) or np.any(lo_i >= hi_i):
        raise VolumeEVMError(f"lo/hi: need 0 <= lo < hi <= shape {s}, got {lo!r}, {hi!r}")
    array = np.zeros(s)
    array[tuple(slice(int(a), int(b)) for a, b in zip(lo_i, hi_i))] = float(density)
    return _volume(array, "box", _vector("spacing", spacing, positive=True),
                   _vector("origin", origin))


def box_chords_mm(camera, grid_to_world, lo, hi):
    """Chord length (mm) of every pixel ray of ``camera`` with the box of voxels
    ``lo <= index < hi`` (index space ``lo - 0.5 .. hi - 0.5``: the voxels' cells).

    ``lo`` and ``hi`` may be fractional (faces at any index-space position). Rays start at the
    camera (perspective) or the camera plane (orthographic); chords are measured in world units
    and converted with :data:`BLENDER_UNITS_PER_MM`.

    Parameters
    ----------
    camera : Camera
        The camera whose pixel rays are measured.
    grid_to_world : (4, 4) array_like
        Voxel-centre index space to world (:func:`volumeevm_addon.grid_to_world`).
    lo, hi : (3,) array_like
        The box in voxel indices, as for :func:`box`.

    Returns
    -------
    (H, W) ndarray of np.float64
        Chord length in mm, 0 for rays that miss the box.
    """
    o, d = (x.reshape(-1, 3) for x in camera.rays())
    g = np.asarray(grid_to_world, dtype=np.float64)
    a = g[:3, :3]
    c_lo = g[:3, 3] + a @ (np.asarray(lo, dtype=np.float64) - 0.5)
    c_hi = g[:3, 3] + a @ (np.asarray(hi, dtype=np.float64) - 0.5)
    t_in = np.zeros(len(o))
    t_out = np.full(len(o), np.inf)
    for ax in range(3):
        n = np.cross(a[:, (ax + 1) % 3], a[:, (ax + 2) % 3])  # normal of this axis' faces
        p, q = sorted((n @ c_lo, n @ c_hi))
        po, pd = o @ n, d @ n
        parallel = pd == 0
        with np.errstate(divide="ignore", invalid="ignore"):
            ta, tb = (p - po) / pd, (q - po) / pd
        inside = (p <= po) & (po <= q)
        t_in = np.maximum(t_in, np.where(parallel, np.where(inside, -np.inf, np.inf),
                                         np.minimum(ta, tb)))
        t_out = np.minimum(t_out, np.where(parallel, np.inf, np.maximum(ta, tb)))
    return (np.maximum(t_out - t_in, 0.0) / BLENDER_UNITS_PER_MM).reshape(camera.shape)


# ---------------------------------------------------------------------------- Gaussian blobs
def _blob_params(centres, sigmas, amplitudes):
    c = np.array(centres, dtype=np.float64)
    if c.ndim != 2 or c.shape[1] != 3 or len(c) < 1 or not np.all(np.isfinite(c)):
        raise VolumeEVMError(f"centres: expected (N, 3) finite mm positions, got {centres!r}")
    s = np.broadcast_to(np.asarray(sigmas, dtype=np.float64), (len(c),))
    amp = np.broadcast_to(np.asarray(amplitudes, dtype=np.float64), (len(c),))
    if not np.all(np.isfinite(s)) or np.any(s <= 0):
        raise VolumeEVMError(f"sigmas: expected positive mm values, got {sigmas!r}")
    if not np.all(np.isfinite(amp)):
        raise VolumeEVMError(f"amplitudes: expected finite values, got {amplitudes!r}")
    return c, s, amp


def gaussian_blobs(shape, centres, sigmas, amplitudes, spacing=(1, 1, 1)):
    """A sum of isotropic Gaussians ``Σ A·exp(-|x - c|²/σ²)`` sampled at the voxel centres.

    Positions are in mm along the grid's axes from the centre of voxel ``(0, 0, 0)`` (voxel
    ``i`` is at ``i·spacing``), so the same ``centres`` and ``sigmas`` on a grid of another
    spacing sample the same physical field (and with the origin 0 of the returned volume they
    are its physical coordinates).

    Parameters
    ----------
    shape : tuple of 3 int
        Grid size.
    centres : (N, 3) array_like
        Blob centres, mm.
    sigmas, amplitudes : (N,) array_like or float
        Widths ``σ`` (mm; the closed form is exact while each blob lies well inside the grid,
        and grid reconstruction is good for ``σ >= 4`` voxels) and peak densities ``A``.
    spacing : tuple of 3 float, optional
        Voxel size in mm (default 1 mm).

    Returns
    -------
    Volume
        float64 densities, spacing ``spacing``, origin 0.

    Raises
    ------
    VolumeEVMError
        For a bad ``shape`` or ``spacing``, centres that are not ``(N, 3)`` finite numbers,
        widths that are not positive or amplitudes that are not finite.

    Examples
    --------
    >>> vol = gaussian_blobs((5, 5, 5), [(2.0, 2.0, 2.0)], 1.5, 3.0)
    >>> float(vol.array.max())
    3.0
    """
    s = _shape(shape)
    sp = _vector("spacing", spacing, positive=True)
    c, sig, amp = _blob_params(centres, sigmas, amplitudes)
    axes = [np.arange(n) * d for n, d in zip(s, sp)]
    array = np.zeros(s)
    for cj, sj, aj in zip(c, sig, amp):
        fx, fy, fz = (np.exp(-((ax - cc) / sj) ** 2) for ax, cc in zip(axes, cj))
        array += aj * fx[:, None, None] * fy[None, :, None] * fz[None, None, :]
    return _volume(array, "gaussian_blobs", sp)


def blobs_optical_depth(camera, grid_to_world, spacing, centres, sigmas, amplitudes, k):
    """Closed-form optical depth of every pixel ray through :func:`gaussian_blobs`.

    ``Σ k·A·σ·√π·exp(-b²/σ²)`` for extinction ``k·density`` per mm (:func:`extinction_tf`), with
    ``b`` (mm) the distance from a blob's centre to the pixel's ray: the integral of the
    continuous field along the whole line, exact while the blobs lie inside the grid and in
    front of the camera. The image is ``alpha = 1 - exp(-depth)`` and colour ``rgb·alpha``.

    Parameters
    ----------
    camera : Camera
    grid_to_world : (4, 4) ndarray
        Voxel-centre index space to world (:func:`volumeevm_addon.grid_to_world`).
    spacing : tuple of 3 float
        Voxel size (mm) of the grid the blobs were sampled on.
    centres, sigmas, amplitudes
        As for :func:`gaussian_blobs` (mm from the centre of voxel ``(0, 0, 0)``).
    k : float
        Extinction per mm per unit density.

    Returns
    -------
    (H, W) ndarray of np.float64
        Optical depth (dimensionless) of each pixel's ray.

    Raises
    ------
    VolumeEVMError
        For a bad ``spacing``, ``centres``, ``sigmas`` or ``amplitudes`` (as
        :func:`gaussian_blobs`).
    """
    sp = _vector("spacing", spacing, positive=True)
    c, sig, amp = _blob_params(centres, sigmas, amplitudes)
    g = np.asarray(grid_to_world, dtype=np.float64)
    # Rays in grid mm (index · spacing): distances there are the blobs' own mm.
    to_mm = np.diag(np.append(sp, 1.0)) @ np.linalg.inv(g)
    o, d = (x.reshape(-1, 3) for x in camera.rays())
    o = o @ to_mm[:3, :3].T + to_mm[:3, 3]
    d = d @ to_mm[:3, :3].T
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    depth = np.zeros(len(o))
    for cj, sj, aj in zip(c, sig, amp):
        v = cj - o
        b2 = np.maximum(np.einsum("ij,ij->i", v, v) - np.einsum("ij,ij->i", v, d) ** 2, 0.0)
        depth += float(k) * aj * sj * np.sqrt(np.pi) * np.exp(-b2 / sj**2)
    return depth.reshape(camera.shape)


def extinction_tf(k, hi, rgb=(1.0, 1.0, 1.0), *, tol=1e-4):
    """A transfer function of extinction ``k·density`` per mm for densities in ``[0, hi]``.

    Opacity per mm ``1 - exp(-k·s)`` at density ``s`` (0 below 0, held beyond ``hi``), constant
    colour ``rgb``; piecewise linear with equally spaced control points, enough of them that the
    table is within ``tol`` of the exact opacity (the interpolation error is at most
    ``h²·k²/8`` for a point spacing ``h``).

    Parameters
    ----------
    k : float
        Extinction per mm per unit density, > 0.
    hi : float
        Largest density the function must follow, > 0.
    rgb : tuple of 3 float, optional
        Straight colour in ``[0, 1]`` (default white).
    tol : float, optional
        Largest opacity error of the piecewise-linear table, > 0 (keyword-only).

    Returns
    -------
    TransferFunction
        Opacity per 1 mm, named ``"extinction k=<k>"``.

    Raises
    ------
    VolumeEVMError
        If ``k``, ``hi`` or ``tol`` is not a finite number > 0, or ``rgb`` is outside
        ``[0, 1]``.

    Examples
    --------
    >>> tf = extinction_tf(0.5, 2.0)
    >>> bool(abs(tf.evaluate([2.0])[0, 3] - (1 - np.exp(-1.0))) < 1e-4)
    True
    """
    k = _positive("k", k)
    hi = _positive("hi", hi)
    tol = _positive("tol", tol)
    n = int(np.ceil(k * hi / np.sqrt(8.0 * tol))) + 1
    s = np.linspace(0.0, hi, max(n, 2))
    rows = np.empty((len(s), 5))
    rows[:, 0] = s
    rows[:, 1:4] = rgb
    rows[:, 4] = -np.expm1(-k * s)
    return TransferFunction(rows, name=f"extinction k={k:g}")


# ---------------------------------------------------------------------------- simple fields
def ramp(shape, axis=0):
    """A linear ramp from 0 (first slice) to 1 (last slice) along ``axis``.

    Trilinear interpolation reproduces it exactly, so any error on it is sampling or
    classification.

    Parameters
    ----------
    shape : tuple of 3 int
        Grid size.
    axis : {0, 1, 2}, optional
        The axis the values rise along (default x).

    Returns
    -------
    Volume
        float64 values in ``[0, 1]`` (0 everywhere for a single slice).

    Raises
    ------
    VolumeEVMError
        For a bad ``shape`` or ``axis``.

    Examples
    --------
    >>> ramp((3, 1, 1)).array.ravel().tolist()
    [0.0, 0.5, 1.0]
    """
    s = _shape(shape)
    if axis not in (0, 1, 2):
        raise VolumeEVMError(f"axis: expected 0, 1 or 2, got {axis!r}")
    n = s[axis]
    t = np.arange(n) / (n - 1) if n > 1 else np.zeros(1)
    return _volume(np.broadcast_to(np.expand_dims(t, [a for a in range(3) if a != axis]),
                                   s).copy(), "ramp")


def checker(shape, period=8):
    """A 3D checkerboard of 0 and 1: cubes of ``period`` voxels per side alternate.

    The pattern repeats every ``2·period`` voxels; voxel ``(0, 0, 0)`` is 0. Its sharp edges
    show the sampling phase and moiré under minification.

    Parameters
    ----------
    shape : tuple of 3 int
        Grid size.
    period : int, optional
        Side of a cube in voxels, >= 1 (default 8).

    Returns
    -------
    Volume
        float64 values 0 and 1.

    Raises
    ------
    VolumeEVMError
        For a bad ``shape`` or a ``period`` that is not an integer >= 1.

    Examples
    --------
    >>> checker((4, 1, 1), period=1).array.ravel().tolist()
    [0.0, 1.0, 0.0, 1.0]
    """
    s = _shape(shape)
    if int(period) != period or period < 1:
        raise VolumeEVMError(f"period: expected an integer >= 1, got {period!r}")
    i, j, k = np.ix_(*(np.arange(n) // int(period) for n in s))
    return _volume(((i + j + k) % 2).astype(np.float64), "checker")


def _slab_coverage(distance, thickness):
    """Fraction of a one-voxel box filter at signed ``distance`` (voxels) from the middle of a
    slab ``thickness`` voxels thick that lies in the slab; integrates to ``thickness``."""
    half = 0.5 * thickness
    return np.clip(np.minimum(distance + 0.5, half) - np.maximum(distance - 0.5, -half), 0.0, 1.0)


def thin_plate(shape, normal, thickness=1.0):
    """An antialiased plate through the grid's centre, perpendicular to ``normal``.

    Each voxel holds the part of a one-voxel box filter (along the normal, index units) that
    the slab ``|distance| <= thickness/2`` covers, so values are in ``[0, 1]`` and the profile
    integrates to ``thickness`` across the plate. Sums of the samples keep that exactly along
    an axis and within about 2 % for generic normals; normals such as ``(1, 1, 0)``, whose
    voxel-centre distances are coarsely spaced, alias more (up to 15 % for ``thickness <= 1``).

    Parameters
    ----------
    shape : tuple of 3 int
        Grid size.
    normal : (3,) array_like
        The plate's normal in index space, not zero.
    thickness : float, optional
        The plate's thickness in voxels, > 0 (default 1).

    Returns
    -------
    Volume
        float64 coverage in ``[0, 1]``.

    Raises
    ------
    VolumeEVMError
        For a bad ``shape``, a zero or non-finite ``normal`` or a ``thickness`` that is not
        a finite number > 0.

    Examples
    --------
    >>> float(thin_plate((5, 5, 5), (0, 0, 1), thickness=2.0).array[2, 2].sum())
    2.0
    """
    s = _shape(shape)
    n = _vector("normal", normal)
    if not np.linalg.norm(n) > 0:
        raise VolumeEVMError(f"normal: must not be zero, got {normal!r}")
    n /= np.linalg.norm(n)
    x, y, z = _centred_index(s)
    return _volume(_slab_coverage(x * n[0] + y * n[1] + z * n[2],
                                  _positive("thickness", thickness)), "thin_plate")


def shell(shape, radius, thickness=1.0):
    """An antialiased spherical shell about the grid's centre: the slab profile of
    :func:`thin_plate` along the radius.

    Parameters
    ----------
    shape : tuple of 3 int
        Grid size.
    radius : float
        Radius of the shell's middle, in voxels, > 0.
    thickness : float, optional
        The shell's thickness in voxels, > 0 (default 1).

    Returns
    -------
    Volume
        float64: the part of each voxel the shell covers, in ``[0, 1]``.

    Raises
    ------
    VolumeEVMError
        For a bad ``shape``, or a ``radius`` or ``thickness`` that is not a finite number > 0.
    """
    s = _shape(shape)
    x, y, z = _centred_index(s)
    r = np.sqrt(x * x + y * y + z * z)
    return _volume(_slab_coverage(r - _positive("radius", radius),
                                  _positive("thickness", thickness)), "shell")


def noise(shape, smoothing=2.0, seed=0):
    """Band-limited noise: white Gaussian noise smoothed and rescaled to ``[0, 1]``.

    The noise comes from ``numpy.random.default_rng(seed)`` and is smoothed by a Gaussian of
    standard deviation ``smoothing`` voxels (periodic, by FFT); the result has min 0 and max
    1. The same ``seed`` gives the same volume.

    Parameters
    ----------
    shape : tuple of 3 int
        Grid size.
    smoothing : float, optional
        Standard deviation of the smoothing Gaussian in voxels, > 0 (default 2).
    seed : int, optional
        Seed of the random generator (default 0).

    Returns
    -------
    Volume
        float64 values in ``[0, 1]``.

    Raises
    ------
    VolumeEVMError
        For a bad ``shape``, or a ``smoothing`` that is not a finite number > 0.

    Examples
    --------
    >>> a = noise((8, 8, 8), seed=1).array
    >>> float(a.min()), float(a.max()), bool((a == noise((8, 8, 8), seed=1).array).all())
    (0.0, 1.0, True)
    """
    s = _shape(shape)
    sigma = _positive("smoothing", smoothing)
    white = np.random.default_rng(seed).standard_normal(s)
    freqs = np.meshgrid(np.fft.fftfreq(s[0]), np.fft.fftfreq(s[1]), np.fft.rfftfreq(s[2]),
                        indexing="ij", sparse=True)
    gain = np.exp(-2.0 * (np.pi * sigma) ** 2 * sum(f * f for f in freqs))
    smooth = np.fft.irfftn(np.fft.rfftn(white) * gain, s=s, axes=(0, 1, 2))
    lo, hi = smooth.min(), smooth.max()
    return _volume((smooth - lo) / (hi - lo) if hi > lo else np.zeros(s), "noise")


def timing_volume(n=256):
    """A smooth ``n³`` phantom for timing: two linked tori (chain links).

    Each torus has a Gaussian tube profile, with empty space round them as in a real scan (2 %
    of the voxels are above 0.5 at n = 256). Each torus is a 2-D field plus a 1-D one, so it
    builds fast.

    Parameters
    ----------
    n : int, optional
        Grid size along each axis, >= 2 (default 256, the size timings are quoted for).

    Returns
    -------
    Volume
        float32 values in ``[0, 1]`` over ``[-1, 1]³``.

    Raises
    ------
    VolumeEVMError
        For an ``n`` that is not an integer of at least 2.
    """
    if int(n) != n or n < 2:
        raise VolumeEVMError(f"n: expected an integer >= 2, got {n!r}")
    t = np.linspace(-1.0, 1.0, int(n), dtype=np.float32)
    x, y, z = t[:, None, None], t[None, :, None], t[None, None, :]
    ring, tube, shift = np.float32(0.4), np.float32(0.12), np.float32(0.22)
    # Link 1 in the xy plane about (-shift, 0, 0); link 2 in the xz plane about (+shift, 0, 0).
    d1 = (np.sqrt((x + shift) ** 2 + y * y) - ring) ** 2 + z * z
    d2 = (np.sqrt((x - shift) ** 2 + z * z) - ring) ** 2 + y * y
    array = np.exp(-d1 / tube**2) + np.exp(-d2 / tube**2)
    return _volume(np.minimum(array, np.float32(1.0)), "timing")
