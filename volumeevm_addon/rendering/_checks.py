"""Input checks shared by :func:`~volumeevm_addon.render`, every renderer and the camera.

Each raises a :class:`VolumeEVMError` that names the parameter, and returns the value
converted (a float, an int, a float64 matrix) for the caller to use. The records a renderer
receives are duck-typed (a camera or transfer function made by another copy of the package,
as a reloaded add-on in Blender has, is accepted): what is checked is that they have what the
renderers use.
"""

import numpy as np

from .._errors import VolumeEVMError
from ._depth import checked_depth_in
from ._modes import MODES, Compositing

__all__ = ["RAY_STEPS_PER_VOXEL", "REFERENCE_STEPS_PER_VOXEL", "finite_number",
           "positive_number", "positive_integer", "flag", "checked_step_mm", "checked_xray",
           "checked_affine", "check_mode", "check_volumeevm", "check_camera",
           "check_transfer_function", "categorical", "checked_categorical_level", "checked_view"]

RAY_STEPS_PER_VOXEL = 2
"""The ray casters' default step: the smallest voxel size over this (half a voxel)."""
REFERENCE_STEPS_PER_VOXEL = 16
"""The reference's default step: the smallest voxel size over this."""

_VOLUMEEVM_API = ("evm", "shape", "spacing", "origin", "orientation", "table", "index")
_CAMERA_API = ("rays", "axial_depth", "shape", "clip_start", "clip_end", "project", "forward",
               "is_ortho", "position")
_TF_API = ("evaluate", "transparent_between", "straight_table", "unit_length_mm", "value_range")


# ---------------------------------------------------------------------------- numbers
def finite_number(name, value):
    """``value`` as a finite float (not a bool or a string)."""
    if isinstance(value, (bool, np.bool_, str, bytes)):
        raise VolumeEVMError(f"{name}: expected a number, got {value!r}")
    try:
        v = float(value)
    except (TypeError, ValueError) as error:
        raise VolumeEVMError(f"{name}: expected a number, got {value!r}") from error
    if not np.isfinite(v):
        raise VolumeEVMError(f"{name}: must be finite, got {value!r}")
    return v


def positive_number(name, value):
    """``value`` as a finite float > 0."""
    v = finite_number(name, value)
    if v <= 0:
        raise VolumeEVMError(f"{name}: must be a finite number > 0, got {value!r}")
    return v


def positive_integer(name, value):
    """``value`` as an int >= 1 (a whole float is accepted; not a bool or a string)."""
    if isinstance(value, (bool, np.bool_, str, bytes)):
        raise VolumeEVMError(f"{name}: expected an integer, got {value!r}")
    try:
        v = int(value)
    except (TypeError, ValueError, OverflowError) as error:
        raise VolumeEVMError(f"{name}: expected an integer, got {value!r}") from error
    if v != value or v < 1:
        raise VolumeEVMError(f"{name}: must be an integer >= 1, got {value!r}")
    return v


def flag(name, value):
    """``value`` as a bool if it is True or False (NumPy's ``np.True_`` and ``np.False_`` too,
    as :func:`volumeevm_addon.render` accepts them)."""
    if not isinstance(value, (bool, np.bool_)):
        raise VolumeEVMError(f"{name}: True or False, got {value!r}")
    return bool(value)


def checked_step_mm(step_mm, spacing, per_voxel):
    """The sample spacing along rays in mm: ``step_mm`` checked (a finite number > 0) or, for
    None, the default, the smallest voxel size over ``per_voxel``
    (:data:`RAY_STEPS_PER_VOXEL`, :data:`REFERENCE_STEPS_PER_VOXEL`)."""
    if step_mm is None:
        return float(np.min(spacing)) / per_voxel
    return positive_number("step_mm", step_mm)


def checked_xray(xray_scale, xray_offset):
    """``(xray_scale, xray_offset)`` as finite floats, the scale >= 0."""
    try:
        xray_scale, xray_offset = float(xray_scale), float(xray_offset)
    except (TypeError, ValueError):
        xray_scale = np.nan
    if not np.isfinite(xray_scale) or xray_scale < 0 or not np.isfinite(xray_offset):
        raise VolumeEVMError(f"xray_scale/xray_offset: need finite numbers, scale >= 0, got "
                             f"{xray_scale!r}, {xray_offset!r}")
    return xray_scale, xray_offset


# ---------------------------------------------------------------------------- matrices
def checked_affine(name, matrix, *, invertible=False):
    """``matrix`` as a finite affine 4x4 float64 array (last row ``0, 0, 0, 1``); with
    ``invertible``, its 3x3 part must not be singular (a grid-to-world map)."""
    try:
        m = np.asarray(matrix, dtype=np.float64)
    except (TypeError, ValueError) as error:
        raise VolumeEVMError(f"{name}: expected an array of numbers, got "
                             f"{type(matrix).__name__}") from error
    if m.shape != (4, 4) or not np.isfinite(m).all() or not np.allclose(m[3], (0, 0, 0, 1)):
        raise VolumeEVMError(f"{name}: expected a finite affine 4x4 matrix (last row "
                             f"0, 0, 0, 1), got shape {m.shape}")
    if invertible and (abs(np.linalg.det(m[:3, :3])) < 1e-300
                       or np.linalg.cond(m[:3, :3]) > 1e12):
        raise VolumeEVMError(f"{name}: the 3x3 part is singular")
    return m


# ---------------------------------------------------------------------------- records
def check_mode(mode):
    """``mode`` must be one of :data:`._modes.MODES`."""
    if mode not in MODES:
        raise VolumeEVMError(f"mode: one of {MODES}, got {mode!r}")


def check_volumeevm(vevm):
    """``vevm`` must be a VolumeEVM (duck-typed)."""
    if not all(hasattr(vevm, a) for a in _VOLUMEEVM_API):
        raise VolumeEVMError(f"vevm: expected a VolumeEVM, got {type(vevm).__name__}")


def check_camera(camera):
    """``camera`` must be a Camera (duck-typed)."""
    if not all(hasattr(camera, a) for a in _CAMERA_API):
        raise VolumeEVMError(f"camera: expected a Camera, got {type(camera).__name__}")


def check_transfer_function(tf, mode):
    """``tf`` must be a TransferFunction (duck-typed), except for ``"xray"``, which does not
    use one."""
    if mode != "xray" and not all(hasattr(tf, a) for a in _TF_API):
        raise VolumeEVMError(f"tf: expected a TransferFunction, got {type(tf).__name__}")


def categorical(tf, mode):
    """True when ``tf`` is a categorical transfer function that ``mode`` uses: samples take
    the nearest voxel's label (``TransferFunction.categorical``)."""
    return mode != "xray" and bool(getattr(tf, "is_categorical", False))


def checked_categorical_level(tf, mode, level, options):
    """The resolution level to render with ``tf``: ``level`` as given, except that a
    categorical function renders the full level for ``"auto"``.

    A categorical function (label map) is drawn with the nearest voxel's label: interpolating
    labels, a coarser level (its densities are block means) or gradients of label numbers
    would invent labels, so it is refused with those (the methods that interpolate by
    construction, splatting's kernels, are refused by their record: ``Method.categorical``).
    """
    if not categorical(tf, mode):
        return level
    if mode not in ("over", "under"):
        raise VolumeEVMError(f"mode: a categorical transfer function (labels) renders with "
                             f"'over' or 'under', got {mode!r}")
    for name, allowed in (("shading", (None, False)), ("preintegrate", (False,)),
                          ("slices_per_voxel", (1,))):
        if name in options and options[name] not in allowed:
            raise VolumeEVMError(f"{name}: a categorical transfer function (labels) samples the "
                                 f"nearest voxel's label; it takes {name}={allowed[0]!r}, got "
                                 f"{options[name]!r}")
    if level == "auto":
        return "full"
    if level not in ("full", 1):
        raise VolumeEVMError(f"level: coarser levels average densities, which invents labels; a "
                             f"categorical transfer function renders level 'full', got {level!r}")
    return level


def checked_view(vevm, camera, tf, grid_to_world, mode, depth_in, termination, xray_scale,
                 xray_offset):
    """The checks every VolumeEVM renderer makes on its common parameters.

    Returns
    -------
    g : (4, 4) ndarray of np.float64
        ``grid_to_world``.
    depth_in : (H, W) ndarray of np.float64 or None
        (:func:`._depth.checked_depth_in`)
    compositing : Compositing
        ``mode``, ``termination`` (a number in ``(0, 1]``) and the X-ray parameters.
    """
    check_volumeevm(vevm)
    check_camera(camera)
    check_mode(mode)
    check_transfer_function(tf, mode)
    g = checked_affine("grid_to_world", grid_to_world, invertible=True)
    depth_in = checked_depth_in(depth_in, camera.shape)
    try:
        termination = float(termination)
    except (TypeError, ValueError):
        termination = np.nan
    if not 0.0 < termination <= 1.0:
        raise VolumeEVMError(f"termination: a number in (0, 1], got {termination!r}")
    return g, depth_in, Compositing(mode, termination, *checked_xray(xray_scale, xray_offset))
