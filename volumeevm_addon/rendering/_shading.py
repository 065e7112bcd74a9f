"""Gradient shading: a Blinn–Phong headlight, the same for every renderer.

The light sits at the camera: ``L = V = -ray direction``, so ``H = L``, and the normal is the
normalised gradient of the density (:mod:`._gradients`), two-sided (absolute values). The
settings are a :class:`Shading` record; :class:`Lighting` joins them with the view's map from
index-space gradients to world normals, and lights samples (:meth:`Lighting.shade`). The terms
of the model are :func:`blinn_phong`'s; ray casting and splatting light one sample at a time
with :func:`headlight` (in float64, as :meth:`Lighting.shade`), shear-warp one sample (or, with
pre-classification, one voxel) at a time in float32.
"""

import math
from dataclasses import dataclass

import numpy as np

from .._errors import VolumeEVMError
from .._jit import kernel
from ..model._volume import transform

__all__ = ["Shading", "Lighting", "checked_shading", "blinn_phong", "headlight"]


@dataclass(frozen=True, kw_only=True)
class Shading:
    """Blinn–Phong gradient shading with the light at the camera (a headlight).

    ``rgb_shaded = rgb · (ambient + diffuse · |N·L|) + specular · |N·H| ** shininess`` (clipped to
    1), with ``N = -∇f / |∇f|`` (two-sided: absolute values), ``L = V = -ray direction`` so
    ``H = L``. Where ``|∇f| == 0`` the sample is lit as if facing the light without highlight:
    ``rgb · (ambient + diffuse)``. Opacity is not changed.

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

    Raises
    ------
    VolumeEVMError
        Naming the field that is not a finite number >= 0.

    Examples
    --------
    >>> Shading(specular=0.0)
    Shading(ambient=0.3, diffuse=0.7, specular=0.0, shininess=20.0)
    """

    ambient: float = 0.3
    diffuse: float = 0.7
    specular: float = 0.3
    shininess: float = 20.0

    def __post_init__(self):
        for name in ("ambient", "diffuse", "specular", "shininess"):
            try:
                v = float(getattr(self, name))
            except (TypeError, ValueError):
                raise VolumeEVMError(
                    f"shading.{name}: expected a number, got {getattr(self, name)!r}") from None
            if not np.isfinite(v) or v < 0:
                raise VolumeEVMError(f"shading.{name}: must be finite and >= 0, got {v!r}")


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
        unknown = set(shading) - {"ambient", "diffuse", "specular", "shininess"}
        if unknown:
            raise VolumeEVMError(f"shading: unknown keys {sorted(unknown)}")
        return Shading(**shading)
    if isinstance(shading, Shading):
        return shading
    raise VolumeEVMError(f"shading: None, True, a dict or a Shading, got {shading!r}")


def blinn_phong(cos, has, shading):
    """The terms of the headlight for ``cos = |N·L|`` (``has``: where the gradient is not 0;
    elsewhere ``cos`` must be 1): the factor on the straight colour, ``ambient + diffuse·cos``,
    and the highlight added to it, ``specular·cos**shininess`` (0 where not ``has``), both in
    ``cos``'s dtype."""
    real = cos.dtype.type
    lit = real(shading.ambient) + real(shading.diffuse) * cos
    glint = np.where(has, real(shading.specular) * cos ** real(shading.shininess), real(0.0))
    return lit, glint


@dataclass(frozen=True, slots=True, eq=False)
class Lighting:
    """A view's headlight: its :class:`Shading` and ``inv_t``, the matrix that takes
    index-space gradients to world normals (the transpose of the inverse of the index-to-world
    linear map), ``normal = inv_t @ gradient``."""

    shading: Shading
    inv_t: np.ndarray

    @classmethod
    def of_view(cls, shading, grid_to_world):
        """The lighting of a view through ``grid_to_world``, or None without ``shading``."""
        if shading is None:
            return None
        return cls(shading, np.linalg.inv(grid_to_world)[:3, :3].T)

    def shade(self, rgb, grad, view_dirs):
        """Straight colours ``rgb`` (m, 3) lit: gradients ``grad`` (m, 3, index space), unit
        world ray directions ``view_dirs`` (m, 3); the result is clipped to 1."""
        n_world = transform(grad, self.inv_t.T)
        norm = np.linalg.norm(n_world, axis=1)
        has = norm > 0
        cos = np.abs(np.einsum("mi,mi->m", n_world, view_dirs)) / np.where(has, norm, 1.0)
        cos = np.where(has, cos, 1.0)
        lit, glint = blinn_phong(cos, has, self.shading)
        out = rgb * lit[:, None] + glint[:, None]
        return np.minimum(out, 1.0)


@kernel
def headlight(rgb, gradient, normal, towards, weights):
    """:meth:`Lighting.shade` of one sample, compiled, in float64 as that computes: the
    straight colour ``rgb`` lit for the index-space ``gradient``; ``normal``: the 9 entries of
    :attr:`Lighting.inv_t` row by row; ``towards``: the unit world ray direction; ``weights``:
    ambient, diffuse, specular, shininess. Each channel is rounded to float32, as
    :meth:`Lighting.shade`'s callers store it, and returned as float64."""
    ga, gb, gc = gradient
    nx = ga * normal[0] + gb * normal[1] + gc * normal[2]
    ny = ga * normal[3] + gb * normal[4] + gc * normal[5]
    nz = ga * normal[6] + gb * normal[7] + gc * normal[8]
    norm = math.sqrt(nx * nx + ny * ny + nz * nz)
    cos = 1.0
    glint = 0.0
    if norm > 0:
        cos = abs(nx * towards[0] + ny * towards[1] + nz * towards[2]) / norm
        glint = weights[2] * cos ** weights[3]
    lit = weights[0] + weights[1] * cos
    red, green, blue = rgb
    return (np.float64(np.float32(min(red * lit + glint, 1.0))),
            np.float64(np.float32(min(green * lit + glint, 1.0))),
            np.float64(np.float32(min(blue * lit + glint, 1.0))))
