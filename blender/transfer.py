"""The transfer function as a colour ramp in the Render settings (``Scene.volumeevm_render``).

The ramp is a Blend texture's ``color_ramp``: element position ``p`` stands for the value
``lo + p (hi - lo)`` in the data's own units (``value_lo``, ``value_hi``), its colour for the
straight colour and its alpha for the opacity per ``unit_length_mm`` mm of ray.
:func:`transfer_function` reads it as the core's :class:`TransferFunction`;
:func:`set_transfer_function` and :func:`load_preset` write one into it. A label map is rendered
with its own label table instead (:func:`volume_transfer_function`, :mod:`.label_table`).
"""

import bpy
import numpy as np

from ..volumeevm_addon import PRESETS, TransferFunction, VolumeEVMError
from .label_table import label_transfer_function, uses_labels
from .objects import render_volume

#: The Hounsfield range the CT presets are written for; stretched onto a volume's value range
#: only when the user asks (``preset_stretch``).
CT_RANGE = (-1024.0, 3071.0)
RAMP_NAME = "VolumeEVM Transfer Function"


def ensure_ramp(settings):
    """The settings' colour-ramp texture (made, with the settings' preset, if missing)."""
    if settings.ramp is None:
        _new_ramp(settings)
        load_preset(settings, settings.preset, render_volume(bpy.context, settings))
    return settings.ramp


def _new_ramp(settings):
    texture = bpy.data.textures.new(RAMP_NAME, "BLEND")
    texture.use_color_ramp = True
    settings.ramp = texture
    return texture


def transfer_function(settings):
    """The :class:`TransferFunction` of the settings' colour ramp over ``[value_lo, value_hi]``.

    Positions that coincide (a step) are moved apart by 1e-6 of the range; colours are clamped
    to ``[0, 1]``. The ramp's interpolation is taken as linear whatever it shows.

    Raises
    ------
    VolumeEVMError
        No ramp yet, or a value range that is empty or not finite.
    """
    texture = settings.ramp
    if texture is None or texture.color_ramp is None:
        raise VolumeEVMError("no transfer function yet: load a preset in the Render panel")
    lo, hi = float(settings.value_lo), float(settings.value_hi)
    if not (np.isfinite(lo) and np.isfinite(hi) and hi > lo):
        raise VolumeEVMError(f"transfer function range: need low < high, got {lo} .. {hi}")
    elements = texture.color_ramp.elements
    positions = np.empty(len(elements), np.float64)
    elements.foreach_get("position", positions)
    colours = np.empty(len(elements) * 4, np.float32)
    elements.foreach_get("color", colours)
    colours = np.clip(colours.reshape(-1, 4).astype(np.float64), 0.0, 1.0)
    order = np.argsort(positions, kind="stable")
    positions, colours = positions[order], colours[order]
    nudge = np.arange(len(positions)) * 1e-6  # strictly increasing even for equal positions
    values = lo + (positions + nudge) * (hi - lo)
    points = np.column_stack([values, colours])
    return TransferFunction(points, unit_length_mm=settings.unit_length_mm, name=settings.preset)


def volume_transfer_function(settings, vol_obj):
    """The transfer function ``vol_obj`` is rendered with: its label table's categorical one
    for a label map that uses its label colours (:func:`.label_table.uses_labels`; opacity per
    the settings' ``unit_length_mm``), else the settings' colour ramp (:func:`transfer_function`).
    Render VolumeEVM, :func:`.dvr.render_dvr` without a ``tf`` and the Viewport DVR use it.

    Parameters
    ----------
    settings : VolumeEVMRenderSettings
        The scene's Render settings (``scene.volumeevm_render``).
    vol_obj : bpy.types.Object or None
        The volume object to render.

    Returns
    -------
    TransferFunction

    Raises
    ------
    VolumeEVMError
        As :func:`transfer_function` (no ramp yet, a bad value range).
    """
    if uses_labels(vol_obj):
        return label_transfer_function(vol_obj, unit_length_mm=settings.unit_length_mm)
    return transfer_function(settings)


def load_preset(settings, name, vol_obj=None, *, stretch=None):
    """Write preset ``name`` into the settings' ramp and value range.

    A preset means what ``TransferFunction.preset(name)`` means in a script: the CT presets are
    in Hounsfield units, whatever the volume's units; ``mri`` and ``microscopy`` take the
    volume's value range (0 .. 1 without a volume). Only when asked (``stretch``, default the
    settings' ``preset_stretch``) is a CT preset stretched from :data:`CT_RANGE` onto the
    volume's value range (CT data stored in other units).

    Raises
    ------
    VolumeEVMError
        ``name`` is not one of :data:`~volumeevm_addon.PRESETS`.
    """
    if name not in PRESETS:
        raise VolumeEVMError(f"preset must be one of {PRESETS}, got {name!r}")
    stretch = settings.preset_stretch if stretch is None else stretch
    data_range = value_range(vol_obj)
    tf = TransferFunction.preset(name, data_range=data_range)
    if stretch and name.startswith("ct_"):
        points = np.array(tf.points, np.float64)
        (a, b), (c, d) = CT_RANGE, data_range
        points[:, 0] = c + (points[:, 0] - a) * (d - c) / (b - a)
        tf = TransferFunction(points, name=name)
    if settings.preset != name:  # the settings' update callbacks load it again: done first,
        settings.preset = name  # so the ramp ends up this volume's
    if settings.preset_stretch != stretch:
        settings.preset_stretch = stretch
    set_transfer_function(settings, tf)


def value_range(vol_obj):
    """A volume object's value range (0 .. 1 for None or a constant volume)."""
    if vol_obj is not None:
        s = vol_obj.volumeevm
        if s.value_max > s.value_min:
            return float(s.value_min), float(s.value_max)
    return 0.0, 1.0


def preset_note(settings, vol_obj):
    """What the sidebar says about the loaded preset on ``vol_obj``: a CT preset stretched onto
    the volume's range, or in HU on a volume whose units say otherwise; "" otherwise."""
    if not settings.preset.startswith("ct_"):
        return ""
    if settings.preset_stretch:
        lo, hi = value_range(vol_obj)
        a, b = CT_RANGE
        return f"CT preset stretched from {a:g} .. {b:g} HU onto {lo:g} .. {hi:g}"
    units = vol_obj.volumeevm.units if vol_obj is not None else ""
    if units not in ("", "HU"):
        return f"CT preset in HU on data in {units}: stretch it, or set the volume's units"
    return ""


def set_transfer_function(settings, tf):
    """Write ``tf`` into the settings' colour ramp, value range and opacity length.

    Raises
    ------
    VolumeEVMError
        ``tf`` has more control points than a ramp holds (32).
    """
    points = np.asarray(tf.points, np.float64)
    if len(points) > 32:
        raise VolumeEVMError(f"tf: a colour ramp holds 32 points, the function has {len(points)}")
    lo, hi = float(points[0, 0]), float(points[-1, 0])
    if hi <= lo:
        hi = lo + 1.0
    texture = settings.ramp if settings.ramp is not None else _new_ramp(settings)
    ramp = texture.color_ramp
    ramp.interpolation = "LINEAR"
    ramp.color_mode = "RGB"
    elements = ramp.elements
    while len(elements) > 1:
        elements.remove(elements[-1])
    elements[0].position = 0.0
    for _ in range(len(points) - 1):
        elements.new(1.0)
    positions = (points[:, 0] - lo) / (hi - lo)
    for element, position, row in zip(elements, positions, points):
        element.position = float(position)
        element.color = tuple(float(v) for v in row[1:5])
    settings.value_lo, settings.value_hi = lo, hi
    settings.unit_length_mm = tf.unit_length_mm
