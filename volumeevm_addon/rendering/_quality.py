"""One quality setting for every method: the options of :func:`~volumeevm_addon.render` it means.

The Blender side's Render settings have one "Quality" (sampling density relative to each
method's default) and a few settings only some methods have; :func:`method_options` turns them
into the keyword options of one method, so that the sidebar, scripts and tests ask for the same
render in the same words.
"""

import numpy as np

from .._errors import VolumeEVMError
from ._levels import LEVELS
from ._registry import method_record

__all__ = ["method_options"]


def method_options(method, quality, spacing, *, shading=False, termination=0.99, level="auto",
                   slices_per_voxel=1, classification="pre", jitter=False, preintegrate=False):
    """The options of :func:`~volumeevm_addon.render` for one method at one quality setting.

    ``quality`` scales the sampling density (1 = each method's default sampling), as the
    method's record says (``Method.quality``): shear-warp's intermediate pixels per voxel
    (``intermediate_scale``), the ray casters' samples per voxel (``step_mm`` = half the
    smallest voxel size / quality; the GPU's too), the reference's (smallest voxel size / 16 /
    quality); for splatting, ``quality`` rounded is its number of sub-slabs per sheet
    (``substeps``). Every setting goes only to the methods that take it (their
    :func:`~volumeevm_addon.rendering.render_options`): ``slices_per_voxel`` and
    ``classification`` to shear-warp, ``jitter`` and ``preintegrate`` to the ray casters,
    ``termination`` to all but the reference.

    Parameters
    ----------
    method : str
        One of :data:`~volumeevm_addon.METHODS`, or the GPU's
        (:func:`~volumeevm_addon.rendering.methods`).
    quality : float
        Sampling density relative to the method's default; > 0.
    spacing : sequence of 3 float
        Voxel size in mm along x, y, z (the step of the ray casters follows the smallest).
    shading : bool, optional
        Gradient shading (passed only when on).
    termination : float, optional
        Early ray termination opacity (every method but the reference).
    level : {"auto", "full"}, optional
        The resolution level (:data:`~volumeevm_addon.LEVELS`): ``"auto"`` renders a volume
        much finer than the pixels from a coarser level, ``"full"`` every voxel (the
        reference ignores it).
    slices_per_voxel : int, optional
        Shear-warp: samples per voxel slice along each ray.
    classification : {"pre", "post"}, optional
        Shear-warp: when the transfer function is applied.
    jitter, preintegrate : bool, optional
        The ray casters: jittered samples, pre-integrated classification.

    Returns
    -------
    dict of str to object
        Keyword options for ``render(..., method=method, **options)``.

    Raises
    ------
    VolumeEVMError
        For an unknown ``method`` or ``level``, a ``quality`` that is not a positive number, or
        a ``spacing`` that is not three positive numbers.

    Examples
    --------
    >>> from volumeevm_addon.rendering import method_options
    >>> method_options("raycast", 2.0, (0.5, 0.5, 1.0))
    {'termination': 0.99, 'level': 'auto', 'step_mm': 0.125, 'jitter': False, 'preintegrate': False}
    >>> method_options("splat", 3.0, (1.0, 1.0, 1.0))["substeps"]
    3
    """
    record = method_record(method)
    quality = float(quality)
    if not np.isfinite(quality) or quality <= 0:
        raise VolumeEVMError(f"quality: must be > 0, got {quality!r}")
    if level not in LEVELS:
        raise VolumeEVMError(f"level: one of {LEVELS}, got {level!r}")
    sizes = np.asarray(spacing, np.float64)
    if sizes.shape != (3,) or not (np.isfinite(sizes).all() and (sizes > 0).all()):
        raise VolumeEVMError(f"spacing: three positive voxel sizes in mm, got {spacing!r}")
    takes = dict(record.options)
    options = {"termination": float(termination), "level": level}
    if shading:
        options["shading"] = True
    options.update(record.quality(quality, float(sizes.min())))
    for name, value, kind in (("slices_per_voxel", slices_per_voxel, int),
                              ("classification", classification, str),
                              ("jitter", jitter, bool), ("preintegrate", preintegrate, bool)):
        if name in takes:
            options[name] = value if kind is str else kind(value)
    return {name: value for name, value in options.items() if name == "level" or name in takes}
