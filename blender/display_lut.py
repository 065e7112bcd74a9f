"""The scene's colour management baked into a 3-D lookup table, for the viewport DVR.

F12 shows a render through the scene's view transform, look, exposure, gamma (and curves, white
balance) for its display device; Blender's 3D viewport draws add-ons' ``POST_VIEW`` drawings
*after* that transform, into its overlay. So the viewport's DVR applies the scene's colour
management itself: its straight scene-linear colour goes through this table (a 3-D texture,
trilinear) to the display value F12 would show.

The table is baked with Blender's own OpenColorIO and no other library: a float image whose
pixels are a lattice of :data:`SIZE`³ straight scene-linear colours is saved as a 16-bit PNG with
the scene's view settings (``Image.save_render(path, scene=scene)``, what F12's saving does)
and read back. The DVR's straight colour lies in [0, 1] (transfer-function colours and shading
are clamped to it; exposure is part of the bake), so the lattice covers that cube through a
cube-root shaper, lattice coordinate ``u = c^(1/3)``: dense where tone curves are steep, near
black. Against Blender's own transform on 4,000 colours at 8 bits: Standard and Filmic within
0.4 levels, AgX within 2.8 (99 % within 1.0: its gamut mapping bends saturated colours).

Baking writes data (an image), which Blender refuses inside a draw handler: the draw asks
:func:`table` for the table of the scene's current settings (:func:`settings_key`); when it
has none it draws with the previous table (first the sRGB one) and a timer bakes it
(:func:`refresh`) and redraws. A bake that fails leaves the sRGB table, Blender's "Standard"
view transform without exposure, gamma or look (the viewport's colours before this table),
and :func:`problem` says so for the sidebar.
"""

import functools
import os
import tempfile

import bpy
import numpy as np

from ..volumeevm_addon import VolumeEVMError
from .scene import changed

#: Lattice points per axis.
SIZE = 33
#: The shaper: lattice coordinate ``u = c ** (1 / SHAPER)`` of a straight colour ``c``.
SHAPER = 3.0

_tables = {}  # settings key -> (SIZE, SIZE, SIZE, 3) display-encoded colours, [b, g, r]
_problem = {"key": None, "text": ""}  # the last failed bake's key and why
_pending = []  # the scene names a timer will bake for


def lattice():
    """The straight scene-linear colours of the table's lattice, ``(SIZE, SIZE, SIZE, 3)``
    indexed ``[b, g, r]`` (red fastest, as a 3-D texture's x)."""
    c = np.linspace(0.0, 1.0, SIZE) ** SHAPER
    b, g, r = np.meshgrid(c, c, c, indexing="ij")
    return np.stack([r, g, b], axis=-1)


@functools.cache
def srgb_table():
    """The table without the scene's colour management: the sRGB transfer function (the view
    transform "Standard" without exposure, gamma or look), float32, made once."""
    c = lattice()
    srgb = np.where(c <= 0.0031308, 12.92 * c, 1.055 * c ** (1 / 2.4) - 0.055)
    return srgb.astype(np.float32)


def settings_key(scene):
    """What the table of ``scene`` depends on: its display device and view settings."""
    view = scene.view_settings
    key = [scene.display_settings.display_device, view.view_transform, view.look,
           round(view.exposure, 6), round(view.gamma, 6), view.use_curve_mapping]
    if view.use_curve_mapping:
        key += [tuple(tuple(point.location) for point in curve.points)
                for curve in view.curve_mapping.curves]
    for name in ("use_white_balance", "white_balance_temperature", "white_balance_tint"):
        if hasattr(view, name):  # Blender 5.x
            key.append(getattr(view, name))
    return tuple(key)


def bake(scene):
    """The display-encoded colours F12 shows for the lattice's colours under the colour
    management of ``scene`` (``(SIZE, SIZE, SIZE, 3)``, float32, 16-bit precision).

    Raises
    ------
    VolumeEVMError
        When Blender cannot save or read back the lattice through the scene's view settings.
    """
    colours = lattice().reshape(-1, 3)
    pixels = np.ones((len(colours), 4), np.float32)
    pixels[:, :3] = colours
    settings = scene.render.image_settings
    items = [(settings, "media_type", "IMAGE")] if hasattr(settings, "media_type") else []
    items += [(settings, "file_format", "PNG"), (settings, "color_mode", "RGBA"),
              (settings, "color_depth", "16"), (settings, "color_management", "FOLLOW_SCENE")]
    image = back = None
    try:
        with tempfile.TemporaryDirectory(prefix="volumeevm_lut_") as folder:
            path = os.path.join(folder, "lut.png")
            image = bpy.data.images.new("VolumeEVM display table", SIZE * SIZE, SIZE,
                                        alpha=True, float_buffer=True)
            image.pixels.foreach_set(pixels.ravel())
            with changed(items):
                image.save_render(path, scene=scene)
            back = bpy.data.images.load(path)
            back.colorspace_settings.name = "Non-Color"  # the saved values, not decoded
            read = np.empty(len(back.pixels), np.float32)
            back.pixels.foreach_get(read)
    except (OSError, RuntimeError, TypeError, ValueError) as error:
        raise VolumeEVMError(f"the scene's view transform "
                             f"'{scene.view_settings.view_transform}' could not be baked "
                             f"into the viewport's colour table ({error})") from error
    finally:
        for made in (image, back):
            if made is not None:
                bpy.data.images.remove(made)
    if read.size != pixels.size:
        raise VolumeEVMError(f"the viewport's colour table came back with {read.size // 4} "
                             f"pixels, not {len(pixels)}")
    return read.reshape(SIZE, SIZE, SIZE, 4)[..., :3].copy()


def refresh(scene):
    """Bake the table of ``scene``'s current settings unless it is kept (a few are); a failure
    is kept for :func:`problem` until the settings change.

    Returns
    -------
    bool
        Whether a table for the current settings is kept now.
    """
    key = settings_key(scene)
    if key in _tables:
        return True
    if _problem["key"] == key:
        return False
    try:
        table = bake(scene)
    except VolumeEVMError as error:
        _problem.update(key=key, text=str(error))
        return False
    _tables[key] = table
    while len(_tables) > 4:
        _tables.pop(next(iter(_tables)))
    _problem.update(key=None, text="")
    return True


def table(scene):
    """The table for drawing ``scene`` now, without writing data (a draw handler may call it):
    ``(table, current)``, the kept table of its settings; the sRGB table when its bake failed;
    else the last one kept (the sRGB table at first) with ``current`` False and a timer set to
    bake it and redraw."""
    key = settings_key(scene)
    if key in _tables:
        return _tables[key], True
    if _problem["key"] == key:
        return srgb_table(), False
    if scene.name not in _pending:
        _pending.append(scene.name)
        if not bpy.app.timers.is_registered(_bake_pending):
            bpy.app.timers.register(_bake_pending, first_interval=0.0)
    return (_tables[next(reversed(_tables))] if _tables else srgb_table()), False


def _bake_pending():
    """The timer: bake the tables the draws asked for, then redraw the viewports (half a
    second later while a render runs: it may hold the data)."""
    from .gpu_viewport import redraw

    if bpy.app.is_job_running("RENDER"):
        return 0.5
    while _pending:
        scene = bpy.data.scenes.get(_pending.pop())
        if scene is not None:
            refresh(scene)
    redraw()


def problem(scene):
    """Why the viewport cannot show ``scene``'s view transform (its last bake failed), or ""."""
    return _problem["text"] if _problem["key"] == settings_key(scene) else ""


def free():
    """Forget every table and failure; cancel a pending bake (file load, unregister)."""
    _tables.clear()
    _problem.update(key=None, text="")
    _pending.clear()
    if bpy.app.timers.is_registered(_bake_pending):
        bpy.app.timers.unregister(_bake_pending)
