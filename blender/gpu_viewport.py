"""The selected volumes' DVR in the 3D viewport: a draw handler over Solid and Material Preview.

With the Render settings' Viewport DVR on (``Scene.volumeevm_render.viewport``), every 3D
viewport draws each selected volume (the tool stack's live result when it has tools) after the
scene (``POST_VIEW``), with the Render settings' transfer function, mode, quality, resolution
level and early termination, through the GPU method's one draw routine
(:func:`.gpu_dvr.draw`):

- the viewport's projection and view matrices become the core's :class:`Camera`
  (``camera_from_viewport``), so the viewport samples as F12's render does;
- the rays stop at the scene's geometry: the viewport's depth buffer is read back
  (``read_depth``) and its window depth converted to axial depth (``axial_from_window``); the
  volume veils what lies behind it and what lies in front hides it;
- the premultiplied colour goes over the viewport with ``ALPHA_PREMULT`` blending.

Colour: Blender draws add-ons' ``POST_VIEW`` drawings into the viewport's overlay, after the
scene's view transform, so the DVR is encoded for an sRGB display there (``gpu_frame(...,
srgb=True)``). The viewport then shows what F12 shows with the view transform "Standard"
(exposure 0, gamma 1, no look); with "Filmic" or "AgX" F12 tone-maps the DVR and the viewport
does not, so the viewport is brighter and more saturated in the highlights.

The handler is added on register and removed on unregister; on file load the GPU textures of
the old file's volumes are freed (:data:`HANDLERS`). A problem (no VolumeEVM, no transfer
function, a volume too large for the GPU) is shown in the sidebar (:func:`problem`), not
raised from the draw.
"""

import bpy
import gpu
import numpy as np
from bpy.app.handlers import persistent

from ..volumeevm_addon import VolumeEVMError, axial_from_window, camera_from_viewport, gpu_frame
from . import gpu_dvr, runtime
from .dvr import settings_options
from .objects import get_vevm, volume_object
from .transfer import transfer_function

_handle = None
_problems = {}  # volume object name -> the last draw's problem


def draw_volume(vevm, tf, projection, view_matrix, size, *, matrix_world=None, mode="over",
                **options):
    """Draw ``vevm``'s DVR over the bound framebuffer, stopped by its depth buffer.

    The viewport's drawing, and the tests' (over ``GPUOffScreen.draw_view3d``).

    Parameters
    ----------
    vevm : VolumeEVM
    tf : TransferFunction or None
        None only for ``mode="xray"``.
    projection, view_matrix : (4, 4) array_like
        The view's projection and world-to-view matrices.
    size : (int, int)
        The framebuffer's width and height in pixels.
    matrix_world : (4, 4) array_like, optional
        The volume object's placement.
    mode : str
        As for the core's ``render``.
    **options
        The GPU method's options (:func:`.gpu_dvr.options`), ``level`` and ``srgb`` (as for the
        core's ``gpu_frame``).

    Raises
    ------
    VolumeEVMError
        For bad settings, or a volume larger than the GPU's textures.
    """
    width, height = size
    camera = camera_from_viewport(np.asarray(projection, np.float64),
                                  np.asarray(view_matrix, np.float64), width, height)
    window = np.empty(width * height, np.float32)
    gpu.state.active_framebuffer_get().read_depth(0, 0, width, height,
                                                  data=gpu_dvr.float_buffer(window))
    depth_in = np.flipud(axial_from_window(window.reshape(height, width), camera))
    frame = gpu_frame(vevm, camera, tf, mode=mode, depth_in=depth_in,
                      matrix_world=matrix_world, **options)
    if frame.vevm.evm.is_empty():
        return
    xray = (options.get("xray_scale", 1.0), options.get("xray_offset", 0.0))
    gpu_dvr.draw(frame, tf, xray=xray, blend="ALPHA_PREMULT")


def _live_vevm(vol_obj):
    """The VolumeEVM a volume shows now: its tool stack's last result, else its own (the draw
    never evaluates the stack: the depsgraph handler keeps the result live)."""
    if len(vol_obj.volumeevm.tools):
        state = runtime.stack_state(vol_obj.volumeevm.uid, vol_obj.name)
        if state is not None and state.result is not None:
            return state.result
    return get_vevm(vol_obj)


def _selected_volumes(context):
    """The volume objects of the selected volumes and surfaces, each once."""
    found = {}
    for obj in context.selected_objects:
        if obj.volumeevm.role in ("VOLUME", "SURFACE"):
            try:
                vol = volume_object(obj)
            except VolumeEVMError:
                continue
            found[vol.name] = vol
    return list(found.values())


def _draw():
    """The POST_VIEW handler: the selected volumes, when the Render settings ask for it."""
    context = bpy.context
    settings = getattr(context.scene, "volumeevm_render", None)
    region, view = context.region, context.region_data
    if settings is None or not settings.viewport or region is None or view is None:
        return
    volumes = _selected_volumes(context)
    if not volumes:
        return
    try:
        tf = None if settings.mode == "xray" else transfer_function(settings)
    except VolumeEVMError as error:
        _problems.update((vol.name, str(error)) for vol in volumes)
        return
    for vol in volumes:
        try:
            options = settings_options(settings, vol, gpu_dvr.METHOD)
            draw_volume(_live_vevm(vol), tf, view.window_matrix, view.view_matrix,
                        (region.width, region.height), matrix_world=vol.matrix_world,
                        mode=settings.mode, srgb=True, **options)
            _problems.pop(vol.name, None)
        except VolumeEVMError as error:
            _problems[vol.name] = str(error)


def problem(vol_obj):
    """What kept the viewport from drawing ``vol_obj`` the last time it tried, or ""."""
    return _problems.get(vol_obj.name, "")


def redraw(settings=None, context=None):
    """Redraw every 3D viewport (the Viewport DVR setting's update callback)."""
    for window in bpy.context.window_manager.windows:
        for area in window.screen.areas:
            if area.type == "VIEW_3D":
                area.tag_redraw()


@persistent
def on_load_pre(*_args):
    """Free the GPU textures of the volumes of the file being closed."""
    gpu_dvr.free()
    _problems.clear()


HANDLERS = (("load_pre", on_load_pre),)


def register():
    """Add the draw handler to every 3D viewport."""
    global _handle
    if _handle is None:
        _handle = bpy.types.SpaceView3D.draw_handler_add(_draw, (), "WINDOW", "POST_VIEW")


def unregister():
    """Remove the draw handler and free the GPU textures and shader."""
    global _handle
    if _handle is not None:
        bpy.types.SpaceView3D.draw_handler_remove(_handle, "WINDOW")
        _handle = None
    gpu_dvr.free()
    _problems.clear()
