"""Gradient shading: a Blinn–Phong headlight, the same for every renderer.

The light sits at the camera: ``L = V = -ray direction``, so ``H = L``, and the normal is the
normalised gradient of the density (:mod:`._gradients`), two-sided (absolute values). Where the
gradient is small its direction is noise: the shading fades out there (:func:`fade`, a
smoothstep of the gradient's magnitude between two fractions of the transfer function's value
range), so flat regions are lit evenly instead of speckled. The settings are a
:class:`Shading` record; :class:`Lighting` joins them with the view's map from index-space
gradients to world normals and the fade's magnitudes, and lights samples
(:meth:`Lighting.shade`). The terms of the model are :func:`blinn_phong`'s; ray casting and
splatting light one sample at a time with :func:`headlight` (in float64, as
:meth:`Lighting.shade`), shear-warp one sample (or, with pre-classification, one voxel) at a
time in float32; all of them fade with :func:`fade`.
"""

import math
from dataclasses import dataclass

import numpy as np

from .._errors import VolumeEVMError
from .._jit import kernel
from ..model._volume import transform

__all__ = ["Shading", "Lighting", "checked_shading", "blinn_phong", "fade", "fade_magnitudes",
           "headlight", "headlight_weights"]


@dataclass(frozen=True, kw_only=True)
class Shading:
    """Blinn–Phong gradient shading with the light at the camera (a headlight).

    ``rgb_shaded = rgb · (ambient + diffuse · c) + t · specular · |N·H| ** shininess``
    (clipped to 1) with ``c = 1 - t + t · |N·L|``, ``N = -∇f / |∇f|`` (two-sided: absolute
    values), ``L = V = -ray direction`` so ``H = L``, and ``t`` the fade (:func:`fade`): 0
    where the index-space gradient's magnitude ``|∇f|`` (data units per voxel) is at most
    ``fade_from · w``, 1 from ``fade_to · w`` (``w``: the width of the transfer function's
    value range), a smoothstep between. Where ``t == 0`` the sample is lit as if facing the
    light without highlight: ``rgb · (ambient + diffuse)``. Opacity is not changed.

    Every renderer's ``shading`` option takes one (or ``True`` for the defaults, or a dict of
    these keyword-only fields).

    Parameters
    ----------
    ambient : float, optional
        Light every sample gets whatever its normal (default 0.3).
    diffuse : float, optional
        Weight of the Lambertian term ``|N·L|`` (default 0.7).
    specular : float, optional
        Weight of the highlight ``|N·H| ** shininess`` (default 0.3).
    shininess : float, optional
        Exponent of the highlight: larger is smaller and sharper (default 20).
    fade_from, fade_to : float, optional
        Where the shading fades in, as fractions of the transfer function's value range per
        voxel (defaults 0.005 and 0.02: on CT presets, 20 and 82 HU per voxel; on the CT head
        soft tissue's gradients (:mod:`._gradients`) have a median of 5 HU per voxel and a
        90th percentile of 14, bone's a 10th percentile of 85).
        ``0, 0`` lights every non-zero gradient fully.

    Raises
    ------
    VolumeEVMError
        Naming the field that is not a finite number >= 0, or ``fade_from`` above ``fade_to``.

    Examples
    --------
    >>> Shading(specular=0.0)
    Shading(ambient=0.3, diffuse=0.7, specular=0.0, shininess=20.0, fade_from=0.005, fade_to=0.02)
    """

    ambient: float = 0.3
    diffuse: float = 0.7
    specular: float = 0.3
    shininess: float = 20.0
    fade_from: float = 0.005
    fade_to: float = 0.02

    def __post_init__(self):
        for name in _FIELDS:
            try:
                v = float(getattr(self, name))
            except (TypeError, ValueError):
                raise VolumeEVMError(
                    f"shading.{name}: expected a number, got {getattr(self, name)!r}") from None
            if not np.isfinite(v) or v < 0:
                raise VolumeEVMError(f"shading.{name}: must be finite and >= 0, got {v!r}")
        if float(self.fade_from) > float(self.fade_to):
            raise VolumeEVMError(f"shading.fade_from: must be <= fade_to ({self.fade_to!r}), "
                                 f"got {self.fade_from!r}")


_FIELDS = ("ambient", "diffuse", "specular", "shininess", "fade_from", "fade_to")
"""The fields of :class:`Shading`."""


def checked_shading(shading):
    """A renderer's ``shading`` option as a :class:`Shading` or None: ``None``/``False`` ->
    None, ``True`` -> ``Shading()``, a dict -> ``Shading(**dict)``, a Shading as it is.

    Raises
    ------
    VolumeEVMError
        For anything else, or a dict with other keys than the fields of :class:`Shading`.
    """
    if shading is True:
        return Shading()
    if shading is None or shading is False:
        return None
    if isinstance(shading, dict):
        unknown = set(shading) - set(_FIELDS)
        if unknown:
            raise VolumeEVMError(f"shading: unknown keys {sorted(unknown)}")
        return Shading(**shading)
    if isinstance(shading, Shading):
        return shading
    raise VolumeEVMError(f"shading: None, True, a dict or a Shading, got {shading!r}")


def blinn_phong(cos, t, shading):
    """The terms of the headlight for ``cos = |N·L|`` and the fade ``t`` (:func:`fade`): the
    factor on the straight colour, ``ambient + diffuse·(1 - t + t·cos)``, and the highlight
    added to it, ``t·specular·cos**shininess``, both in ``cos``'s dtype."""
    real = cos.dtype.type
    lit = real(shading.ambient) + real(shading.diffuse) * (real(1.0) - t + t * cos)
    glint = t * (real(shading.specular) * cos ** real(shading.shininess))
    return lit, glint


@kernel
def fade(magnitude, lo, hi):
    """How much of the shading a gradient of index-space ``magnitude`` gets, in float64: 0 up
    to ``lo``, 1 from ``hi`` on (and above 0 when ``lo == hi``), the smoothstep
    ``x²·(3 - 2x)`` of ``x = (magnitude - lo) / (hi - lo)`` between."""
    if magnitude <= lo:
        return 0.0
    if magnitude >= hi:
        return 1.0
    x = (np.float64(magnitude) - lo) / (hi - lo)
    return x * x * (3.0 - 2.0 * x)


@dataclass(frozen=True, slots=True, eq=False)
class Lighting:
    """A view's headlight: its :class:`Shading`; ``inv_t``, the matrix that takes index-space
    gradients to world normals (the transpose of the inverse of the index-to-world linear map),
    ``normal = inv_t @ gradient``; ``fade``, the index-space gradient magnitudes ``(lo, hi)``
    between which the shading fades in (:func:`fade`)."""

    shading: Shading
    inv_t: np.ndarray
    fade: tuple

    @classmethod
    def of_view(cls, shading, grid_to_world, tf):
        """The lighting of a view through ``grid_to_world`` with the transfer function ``tf``
        (its value range sets the fade), or None without ``shading``."""
        if shading is None:
            return None
        return cls(shading, np.linalg.inv(grid_to_world)[:3, :3].T, fade_magnitudes(shading, tf))

    def weights(self):
        """The numbers :func:`headlight` takes as ``weights`` (floats): ambient, diffuse,
        specular, shininess and the fade's two magnitudes."""
        return headlight_weights(self.shading, self.fade)

    def shade(self, rgb, grad, view_dirs):
        """Straight colours ``rgb`` (m, 3) lit: gradients ``grad`` (m, 3, index space), unit
        world ray directions ``view_dirs`` (m, 3); the result is clipped to 1."""
        n_world = transform(grad, self.inv_t.T)
        norm = np.linalg.norm(n_world, axis=1)
        has = norm > 0
        cos = np.abs(np.einsum("mi,mi->m", n_world, view_dirs)) / np.where(has, norm, 1.0)
        lo, hi = self.fade
        magnitude = np.linalg.norm(grad, axis=1)
        with np.errstate(invalid="ignore", divide="ignore"):
            x = (magnitude - lo) / (hi - lo)
        t = np.where(magnitude <= lo, 0.0, np.where(magnitude >= hi, 1.0, x * x * (3.0 - 2.0 * x)))
        lit, glint = blinn_phong(cos, t, self.shading)
        out = rgb * lit[:, None] + glint[:, None]
        return np.minimum(out, 1.0)


def headlight_weights(shading, fade):
    """The numbers :func:`headlight` takes as ``weights`` (floats): ``shading``'s ambient,
    diffuse, specular and shininess, and the fade's two magnitudes ``fade``
    (:func:`fade_magnitudes`)."""
    return (float(shading.ambient), float(shading.diffuse), float(shading.specular),
            float(shading.shininess), *fade)


def fade_magnitudes(shading, tf):
    """The index-space gradient magnitudes ``(lo, hi)`` (floats) between which ``shading``
    fades in: its ``fade_from`` and ``fade_to`` times the width of ``tf``'s value range (1 for
    a single control point)."""
    lo, hi = tf.value_range
    width = hi - lo if hi > lo else 1.0
    return float(shading.fade_from) * width, float(shading.fade_to) * width


@kernel
def headlight(rgb, gradient, normal, towards, weights):
    """:meth:`Lighting.shade` of one sample, compiled, in float64 as that computes: the
    straight colour ``rgb`` lit for the index-space ``gradient``; ``normal``: the 9 entries of
    :attr:`Lighting.inv_t` row by row; ``towards``: the unit world ray direction; ``weights``:
    ambient, diffuse, specular, shininess and :attr:`Lighting.fade`'s two magnitudes. Each
    channel is rounded to float32, as :meth:`Lighting.shade`'s callers store it, and returned
    as float64."""
    ga, gb, gc = gradient
    nx = ga * normal[0] + gb * normal[1] + gc * normal[2]
    ny = ga * normal[3] + gb * normal[4] + gc * normal[5]
    nz = ga * normal[6] + gb * normal[7] + gc * normal[8]
    norm = math.sqrt(nx * nx + ny * ny + nz * nz)
    t = fade(math.sqrt(ga * ga + gb * gb + gc * gc), weights[4], weights[5])
    cos = 0.0
    if norm > 0:
        cos = abs(nx * towards[0] + ny * towards[1] + nz * towards[2]) / norm
    lit = weights[0] + weights[1] * (1.0 - t + t * cos)
    glint = t * (weights[2] * cos ** weights[3])
    red, green, blue = rgb
    return (np.float64(np.float32(min(red * lit + glint, 1.0))),
            np.float64(np.float32(min(green * lit + glint, 1.0))),
            np.float64(np.float32(min(blue * lit + glint, 1.0))))
