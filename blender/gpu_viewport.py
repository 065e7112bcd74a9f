"""The selected volumes' DVR in the 3D viewport: a draw handler over Solid and Material Preview.

With the Render settings' Viewport DVR on (``Scene.volumeevm_render.viewport``), every 3D
viewport draws each selected volume (the tool stack's live result when it has tools) after the
scene (``POST_VIEW``), with the Render settings' transfer function (a label map: its label
colours, :func:`.transfer.volume_transfer_function`), mode, quality, resolution
level and early termination, through the GPU method's one draw routine
(:func:`.gpu_draw.draw`):

- the viewport's projection and view matrices become the core's :class:`Camera`
  (``camera_from_viewport``), so the viewport samples as F12's render does;
- the rays stop at the scene's geometry: the viewport's depth buffer is read back
  (``read_depth``) and its window depth converted to axial depth (``axial_from_window``); the
  volume veils what lies behind it and what lies in front hides it;
- the premultiplied colour goes over the viewport with ``ALPHA_PREMULT`` blending.

Colour: Blender draws add-ons' ``POST_VIEW`` drawings into the viewport's overlay, an 8-bit
sRGB texture (the GPU encodes what a shader writes, so it holds linear values), after the
scene's view transform; its display pass then merges the overlay over the colour-managed scene
in display-linear space: ``shown = (scene_display^2.2 * (1 - a) + overlay)^(1/2.2)``
(``gpu_shader_display_transform_frag.glsl``, the same in 4.5 and 5.x). So the DVR applies the
scene's colour management itself (``gpu_frame(..., display=True)``): its straight colour through
the scene's display table (:mod:`.display_lut`: view transform, look, exposure, gamma, as F12
saves them), raised to the power 2.2 and premultiplied. Where the volume is opaque, or over a
black background, the viewport shows F12's display pixel of a transparent-film render; a
translucent DVR over other things blends with them in display space, not scene-linear. While a
table for new settings is baked (a timer: a draw cannot write data) the last one is drawn; a
scene whose table cannot be baked is drawn with the sRGB table ("Standard"), and the sidebar
says so (:func:`colour_problem`).

While a view moves (its matrices, a drawn volume's placement, or the tool stack's live result
change from one draw of the region to the next) and the Render setting "Fast While Moving" is
on, the draw casts a ray per block of :data:`MOVING_PIXEL`² pixels with a step
:data:`MOVING_STEP` times longer; once the view has rested for :data:`REST_SECONDS` a timer
redraws the viewports at full quality (:class:`ViewMotion` decides, fed with times and
signatures, so it is tested without a viewport). The sidebar says which resolution level a
draw showed when it is not the full one (:func:`shown_level`).

The handler is added on register and removed on unregister; on file load the GPU textures of
the old file's volumes are freed (:data:`HANDLERS`). A problem (no VolumeEVM, no transfer
function, a volume too large for the GPU at every level) is shown in the sidebar
(:func:`problem`), not raised from the draw.
"""

import time

import bpy
import gpu
import numpy as np
from bpy.app.handlers import persistent

from ..volumeevm_addon import VolumeEVMError
from ..volumeevm_addon.rendering import axial_from_window, camera_from_viewport
from . import display_lut, gpu_draw, gpu_textures, runtime
from .dvr import settings_options
from .handlers import ViewportDraw
from .objects import get_vevm, volume_object
from .transfer import volume_transfer_function

#: While a view moves the viewport casts one ray per ``MOVING_PIXEL²`` pixels, each with a step
#: ``MOVING_STEP`` times the Render settings': on llvmpipe the CT head's frame took 84 ms instead
#: of 335 at 512², 0.33 s instead of 1.7 at 1280×720 (RMSE 0.03 / 0.02 to the resting frame,
#: mostly its blocky edges). The step alone gave 1.5×, a coarser resolution level less.
MOVING_PIXEL = 2
MOVING_STEP = 2.0
#: Seconds a view must rest before it is drawn at full quality again.
REST_SECONDS = 0.25

_problems = {}  # volume object name -> the last draw's problem
_levels = {}  # volume object name -> the resolution level's factor it was last drawn at


class ViewMotion:
    """Which views are moving: a view moves from the draw whose signature (its matrices, what it
    shows) differs from its previous draw's until it has rested for ``rest`` seconds.

    A view seen for the first time rests (enabling the Viewport DVR draws at full quality).
    """

    def __init__(self, rest=REST_SECONDS):
        self.rest = rest
        self._views = {}  # key -> (signature, when it last changed)

    def observe(self, key, signature, now):
        """Record a draw of the view ``key`` showing ``signature`` (any comparable value) at
        time ``now`` (seconds): the seconds left until the view counts as resting, 0.0 when
        it rests (draw at full quality)."""
        last = self._views.get(key)
        if last is None:
            self._views[key] = (signature, -np.inf)
            return 0.0
        if last[0] != signature:
            self._views[key] = (signature, now)
            return self.rest
        return max(0.0, last[1] + self.rest - now)

    def clear(self):
        """Forget every view (file load, unregister)."""
        self._views.clear()


_motion = ViewMotion()


def draw_options(options, moving):
    """The options of a viewport draw (:func:`draw_volume`): the Render settings' ``options``
    at rest; while the view moves, a ray per :data:`MOVING_PIXEL`² pixels and a step
    :data:`MOVING_STEP` times longer."""
    if not moving:
        return options
    return {**options, "step_mm": options["step_mm"] * MOVING_STEP, "pixel": MOVING_PIXEL}


def block_starts(size, n):
    """The first of the ``size`` pixels along an axis that show each of ``n`` coarse pixels
    when the stretch shader (:func:`.gpu_draw.draw_stretched`) draws them: pixel ``x`` shows
    coarse pixel ``floor((x + 1/2) n / size)``, so coarse pixel ``i`` starts at
    ``ceil(i size / n - 1/2)`` (integer arithmetic)."""
    i = np.arange(n, dtype=np.int64)
    return -((n - 2 * i * size) // (2 * n))


def draw_volume(vevm, tf, projection, view_matrix, size, *, matrix_world=None, mode="over",
                pixel=1, display=None, **options):
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
    pixel : int
        One ray per ``pixel × pixel`` block of the framebuffer's pixels, the coarser frame
        stretched over it (each block's rays stop at its nearest geometry); 1: a ray a pixel.
    display : (N, N, N, 3) ndarray, optional
        A display table (:mod:`.display_lut`): draw for the viewport's display. None: the
        scene-linear colour.
    **options
        The GPU method's options (the core's ``render_options("gpu")``) and ``level``.

    Returns
    -------
    int
        The resolution level's factor drawn (1: full).

    Raises
    ------
    VolumeEVMError
        For bad settings, or a volume larger than the GPU's textures at every level (a level
        that fits is drawn otherwise, :func:`.gpu_textures.fitted_frame`).
    """
    width, height = size
    window = np.empty(width * height, np.float32)
    gpu.state.active_framebuffer_get().read_depth(0, 0, width, height,
                                                  data=gpu_textures.float_buffer(window))
    window = window.reshape(height, width)
    coarse = (-(-width // pixel), -(-height // pixel))
    if pixel > 1:  # the nearest depth of each block of the pixels the stretch shows it on
        for axis, n in ((0, coarse[1]), (1, coarse[0])):
            window = np.minimum.reduceat(window, block_starts(window.shape[axis], n), axis)
    camera = camera_from_viewport(np.asarray(projection, np.float64),
                                  np.asarray(view_matrix, np.float64), *coarse)
    depth_in = np.flipud(axial_from_window(window, camera))
    frame = gpu_textures.fitted_frame(vevm, camera, tf, mode=mode, depth_in=depth_in,
                                      matrix_world=matrix_world, display=display is not None,
                                      **options)
    if not frame.vevm.evm.is_empty():
        xray = (options.get("xray_scale", 1.0), options.get("xray_offset", 0.0))
        if pixel > 1:
            gpu_draw.draw_stretched(frame, tf, coarse, xray=xray, display=display)
        else:
            gpu_draw.draw(frame, tf, xray=xray, blend="ALPHA_PREMULT", display=display)
    return frame.level


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
    """The POST_VIEW handler: the region's view (:func:`draw_view`)."""
    context = bpy.context
    region, view = context.region, context.region_data
    if region is not None and view is not None:
        draw_view(context.scene, _selected_volumes(context), region.as_pointer(),
                  (region.width, region.height), view.window_matrix, view.view_matrix)


_drawing = ViewportDraw(_draw)


def draw_view(scene, volumes, key, size, projection, view_matrix):
    """Draw ``volumes`` (volume objects) over the bound framebuffer of one view when the Render
    settings of ``scene`` ask for it; coarser while the view ``key`` moves (:class:`ViewMotion`,
    a timer redraws the viewports once it rests). The handler's drawing, apart from the
    context it reads (the tests call it headless, where handlers never run)."""
    settings = getattr(scene, "volumeevm_render", None)
    if settings is None or not settings.viewport or not volumes:
        return
    shown = []
    for vol in volumes:
        try:
            tf = None if settings.mode == "xray" else volume_transfer_function(settings, vol)
            shown.append((vol, _live_vevm(vol), tf))
        except VolumeEVMError as error:  # e.g. no ramp yet, no VolumeEVM built yet
            _problems[vol.name] = str(error)
    signature = (tuple(map(tuple, projection)), tuple(map(tuple, view_matrix)), tuple(size),
                 tuple((vol.name, tuple(map(tuple, vol.matrix_world)), id(vevm))
                       for vol, vevm, _ in shown))
    display, _ = display_lut.table(scene)
    wait = _motion.observe(key, signature, time.monotonic())
    moving = wait > 0.0 and settings.viewport_fast
    if moving:
        _redraw_after(wait)
    for vol, vevm, tf in shown:
        try:
            options = draw_options(settings_options(settings, vol, gpu_draw.METHOD), moving)
            _levels[vol.name] = draw_volume(vevm, tf, projection, view_matrix, size,
                                            matrix_world=vol.matrix_world, mode=settings.mode,
                                            display=display, **options)
            _problems.pop(vol.name, None)
        except VolumeEVMError as error:
            _problems[vol.name] = str(error)


def _redraw_rested():
    """The timer that redraws the viewports once a moving view may have rested."""
    redraw()


def _redraw_after(seconds):
    """Redraw the viewports in ``seconds`` (a little later, so the view has rested by then)."""
    if not bpy.app.timers.is_registered(_redraw_rested):
        bpy.app.timers.register(_redraw_rested, first_interval=seconds + 0.02)


def problem(vol_obj):
    """What kept the viewport from drawing ``vol_obj`` the last time it tried, or ""."""
    return _problems.get(vol_obj.name, "")


def colour_problem(scene):
    """Why the viewport cannot show the DVR through ``scene``'s view transform, or ""."""
    problem = display_lut.problem(scene)
    return f"Viewport colours as 'Standard': {problem}" if problem else ""


def shown_level(vol_obj):
    """Which coarser resolution level the viewport last showed ``vol_obj`` at (e.g. "Showing
    level 2 (2× coarser voxels)"), or "" for the full level."""
    text = gpu_draw.level_text(_levels.get(vol_obj.name, 1))
    return f"Showing {text}" if text else ""


def redraw(settings=None, context=None):
    """Redraw every 3D viewport (the Viewport DVR setting's update callback)."""
    for window in bpy.context.window_manager.windows:
        for area in window.screen.areas:
            if area.type == "VIEW_3D":
                area.tag_redraw()


@persistent
def on_load_pre(*_args):
    """Free the GPU textures of the volumes of the file being closed."""
    gpu_draw.free()
    _forget()


def _forget():
    """Forget the views, what the last draws said and the display tables; cancel the rest and
    bake timers (Blender 4.5's ``bpy`` module hangs at exit when a file load dropped a timer
    it had)."""
    _problems.clear()
    _levels.clear()
    _motion.clear()
    display_lut.free()
    if bpy.app.timers.is_registered(_redraw_rested):
        bpy.app.timers.unregister(_redraw_rested)


HANDLERS = (("load_pre", on_load_pre),)


def register():
    """Add the draw handler to every 3D viewport."""
    _drawing.add()


def unregister():
    """Remove the draw handler and free the GPU textures and shaders."""
    _drawing.remove()
    gpu_draw.free()
    _forget()
