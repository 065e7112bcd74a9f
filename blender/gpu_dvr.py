"""Direct volume rendering on the GPU through Blender's own ``gpu`` module: textures, shader,
one draw routine, and the offscreen render.

The core computes everything but the drawing (``gpu_frame``, ``gpu_region``, ``gpu_gradients``,
``gpu_occupancy``, ``gpu_transfer_table``: checks, the pixel rays, the region's RG texture,
shading's gradients, the empty-space blocks, the transfer-function table, the std140
uniforms); this module uploads them and draws one full-screen quad whose fragment shader
(``volumeevm_addon/rendering/shaders/dvr.frag.glsl``, :func:`gpu_shader_source`) marches the
pixel's ray:

- take the pixel's ray in index space from the two affine maps of the uniforms (its parameter
  is axial depth), clip it to the grid's box, the clip range and the scene's depth
  (``depth_in``, axial: a render's Z pass, or a viewport's depth buffer converted);
- cut it into equal parts no longer than the step and sample each at its midpoint, as the
  reference does: a trilinear fetch of ``(density·inside, inside)`` renormalised (boundary
  policy "clamp"); each part counts only for its length in region cells (cut at cell
  boundaries, as the CPU ray caster cuts it), so the region's surface is placed exactly;
- classify after interpolation through the 1-D transfer-function texture; with shading, light
  the colour by the gradient interpolated the same way (the gradient texture's fetch over the
  region's weight) with the CPU methods' headlight and fade (``_shading``: ``headlight``
  below is the same formula); correct the opacity for the part's length, composite front to
  back with early termination (over), sum the
  attenuation (X-ray) or keep the maximum (MIP);
- leap over the empty blocks of ``8³`` voxels around the sample, as far as the empty-space
  texture says they reach (the same image);
- write premultiplied RGBA and the axial depth of the front of the first visible part
  (the core's depth rule), ``1e10`` where nothing is visible; for a viewport, the colour
  through the scene's display table first (:mod:`.display_lut`, a 3-D texture kept while
  the table is the same).

Textures are made lazily on the first draw and kept per VolumeEVM (the region, the gradients
once a shaded frame needs them, and the empty-space blocks of its last few transfer functions
and modes) and per transfer-function version (its table, the last few); the shader once per
process. They are freed with the VolumeEVM, by :func:`free`, and on file
load. Drawing saves and restores the GPU state it changes. A VolumeEVM's region texture is
uploaded whole: Blender's Python ``GPUTexture`` (4.5 and 5.x) cannot write into part of an
existing texture, so a new tool-stack result is a new upload, not a re-upload of its changed box.
A volume larger than the GPU's 3D textures is drawn from the first coarser level that fits
(:func:`fitted_frame`).

A GPU context is needed on the calling (main) thread: Blender with a window has one; in
background mode Blender 5.x makes one with ``gpu.init()``, Blender 4.5 after one small
Workbench render (:func:`ensure_context`, which raises :class:`GPUUnavailable` when neither
works, so the render can fall back to the CPU ray caster). Without EGL that attempt crashes
Blender instead of failing, so it is made first in a process of its own.
"""

import subprocess
import sys
import weakref
from contextlib import contextmanager

import bpy
import gpu
import numpy as np
from gpu_extras.batch import batch_for_shader

from ..volumeevm_addon import VolumeEVMError
from ..volumeevm_addon.rendering import (
    BACKGROUND_DEPTH,
    GPU_UNIFORMS_GLSL,
    gpu_frame,
    gpu_gradients,
    gpu_occupancy,
    gpu_region,
    gpu_shader_source,
    gpu_transfer_table,
    methods,
)
from . import display_lut

#: The method's name among Render VolumeEVM's methods (:data:`.dvr.METHODS`): the core's GPU
#: record (its options, quality and CPU fallback).
METHOD = next(name for name, record in methods().items() if record.gpu)


class _Refused(VolumeEVMError):
    """The GPU refused a texture: its size or memory."""


class GPUUnavailable(VolumeEVMError):
    """No GPU context can be made on this thread (a headless machine without EGL, a worker
    thread): the GPU method cannot draw."""


_SENTINEL = -1.0
"""The depth target's clear value: no pixel of a draw keeps it (the shader writes every
pixel), so a pixel holding it means the draw was silently dropped."""

_VERTEX = gpu_shader_source("dvr.vert.glsl")
"""The full-screen quad's vertex shader."""
_FRAGMENT = gpu_shader_source("dvr.frag.glsl")
"""The ray-marching fragment shader (its ``DISPLAY_SHAPER`` filled in when it is made)."""
_STRETCH = gpu_shader_source("stretch.frag.glsl")
"""The fragment shader that stretches a coarser frame's colour over the bound framebuffer."""

_shader = None
_batch = None
_stretch = None
_volumes = weakref.WeakKeyDictionary()  # VolumeEVM -> _VolumeTextures
_refused = weakref.WeakKeyDictionary()  # VolumeEVM -> why the GPU refused its region texture
_tables = {}  # transfer-function version -> 1-D texture
_display = []  # the display table drawn last and its 3-D texture
_KEPT = 8
"""Transfer-function tables kept, and empty-space textures per VolumeEVM (the latest used)."""
_context = False


class _VolumeTextures:
    """One VolumeEVM's textures: the region, its gradients (None until a shaded frame needs
    them), and its empty-space blocks per (transfer function, mode, X-ray parameters)."""

    def __init__(self, vevm):
        self.region = _texture_3d(gpu_region(vevm), "RG32F")
        self.gradients = None
        self.occupancy = {}


# ---------------------------------------------------------------------------- context
def ensure_context():
    """Make sure the calling thread can draw: in background mode make the process's GPU
    context once (Blender 5.x: ``gpu.init()``; 4.5: a 4x4 Workbench render of a temporary
    scene), then check that a texture can be made.

    Raises
    ------
    GPUUnavailable
        When no GPU context can be made (no EGL, a worker thread).
    """
    global _context
    if _context:
        return
    try:
        if bpy.app.background:
            _probe()
            if hasattr(gpu, "init"):
                gpu.init()
            else:
                _workbench_render()
        gpu.types.GPUTexture((1, 1), format="R32F")
    except (SystemError, RuntimeError) as error:
        raise GPUUnavailable(f"no GPU context ({error})") from error
    _context = True


_PROBE = """
import bpy, gpu
if hasattr(gpu, "init"):
    gpu.init()
else:
    render = bpy.context.scene.render
    render.engine = "BLENDER_WORKBENCH"
    render.resolution_x = render.resolution_y = 4
    bpy.ops.render.render()
gpu.types.GPUTexture((1, 1), format="R32F")
"""
"""What :func:`ensure_context` does in background mode, for a process of its own."""


def _probe():
    """Make a GPU context in another Blender process first: without EGL, making one crashes
    Blender (a segmentation fault, not an exception), which must not take this process down.

    Raises
    ------
    RuntimeError
        When that process fails.
    """
    if bpy.app.binary_path:  # Blender
        command = [bpy.app.binary_path, "--background", "--factory-startup",
                   "--python-exit-code", "1", "--python-expr", _PROBE]
    else:  # the bpy module
        command = [sys.executable, "-c", _PROBE]
    try:
        run = subprocess.run(command, capture_output=True, text=True, timeout=300)
    except (OSError, subprocess.TimeoutExpired) as error:
        raise RuntimeError(f"a test process could not run: {error}") from error
    if run.returncode != 0:
        raise RuntimeError(f"a test process failed with exit code {run.returncode}")


def _workbench_render():
    """Render a 4x4 Workbench image of a temporary scene with a temporary camera: Blender 4.5
    keeps the GPU context it makes for the rest of the process."""
    scene = bpy.data.scenes.new("VolumeEVM GPU context")
    camera_data = bpy.data.cameras.new("VolumeEVM GPU context")
    camera = bpy.data.objects.new("VolumeEVM GPU context", camera_data)
    try:
        scene.collection.objects.link(camera)
        scene.camera = camera
        scene.render.engine = "BLENDER_WORKBENCH"
        scene.render.resolution_x = scene.render.resolution_y = 4
        scene.render.resolution_percentage = 100
        bpy.ops.render.render(scene=scene.name)
    finally:
        bpy.data.objects.remove(camera)
        bpy.data.cameras.remove(camera_data)
        bpy.data.scenes.remove(scene)


# ---------------------------------------------------------------------------- resources
def float_buffer(array):
    """A flat float32 ``gpu.types.Buffer`` sharing ``array``'s memory (a float32 C-contiguous
    copy where it is not one), to upload it or to read pixels into it: a NumPy array handed to
    ``Buffer`` is reinterpreted, not converted, and multi-dimensional Buffers come out
    transposed on Blender 4.5."""
    flat = np.ascontiguousarray(array, dtype=np.float32).ravel()
    return gpu.types.Buffer("FLOAT", flat.size, flat)


def _texture(size, texture_format, what, array=None):
    """A texture of ``size`` (x first), filled from ``array`` (x fastest) if given; a size or
    memory the GPU refuses raises :class:`VolumeEVMError` naming ``what``."""
    data = {} if array is None else {"data": float_buffer(array)}  # 4.5 refuses data=None
    try:
        return gpu.types.GPUTexture(size, format=texture_format, **data)
    except RuntimeError as error:
        raise _Refused(f"{what}: the GPU cannot hold a "
                             f"{'x'.join(str(n) for n in np.ravel(size))} "
                             f"{texture_format} texture ({error}); render a coarser level "
                             f"or a smaller image") from error


def _texture_3d(array, texture_format):
    """A 3D texture of a ``(Z, Y, X[, C])`` float32 array (x fastest)."""
    return _texture(array.shape[2::-1], texture_format, "vevm", array)


def _full_screen_shader(info, name, fragment, outputs):
    """Finish ``info`` (its samplers and uniforms declared) as a shader on the full-screen quad:
    the fragment stage ``fragment`` sees ``ndc`` in [-1, 1]² and writes ``outputs`` (``(type,
    name)`` pairs in slot order)."""
    interface = gpu.types.GPUStageInterfaceInfo(name)
    interface.smooth("VEC2", "ndc")
    info.vertex_in(0, "VEC2", "pos")
    info.vertex_out(interface)
    for slot, (kind, output) in enumerate(outputs):
        info.fragment_out(slot, kind, output)
    info.vertex_source(_VERTEX)
    info.fragment_source(fragment)
    return gpu.shader.create_from_info(info)


def _shader_and_batch():
    """The ray-marching shader and its full-screen quad, made once."""
    global _shader, _batch
    if _shader is None:
        info = gpu.types.GPUShaderCreateInfo()
        info.typedef_source(GPU_UNIFORMS_GLSL)
        info.uniform_buf(0, "VolumeParams", "params")
        info.sampler(0, "FLOAT_3D", "region")
        info.sampler(1, "FLOAT_3D", "occupancy")
        info.sampler(2, "FLOAT_1D", "tf_table")
        info.sampler(3, "FLOAT_2D", "depth_in")
        info.sampler(4, "FLOAT_3D", "gradient")
        info.sampler(5, "FLOAT_3D", "display_lut")
        fragment = _FRAGMENT.replace("DISPLAY_SHAPER", f"{display_lut.SHAPER:.6f}")
        _shader = _full_screen_shader(info, "volumeevm_dvr", fragment,
                                      (("VEC4", "out_color"), ("FLOAT", "out_depth")))
        _batch = batch_for_shader(_shader, "TRI_STRIP",
                                  {"pos": ((-1, -1), (1, -1), (-1, 1), (1, 1))})
    return _shader, _batch


def _stretch_shader():
    """The shader that draws a texture over the whole bound framebuffer, made once."""
    global _stretch
    if _stretch is None:
        info = gpu.types.GPUShaderCreateInfo()
        info.sampler(0, "FLOAT_2D", "image")
        _stretch = _full_screen_shader(info, "volumeevm_stretch", _STRETCH,
                                       (("VEC4", "out_color"),))
    return _stretch


def _tf_key(tf):
    """A transfer function's version: its control points, unit length and whether it is
    categorical (None for X-ray)."""
    return None if tf is None else (tf.points.tobytes(), tf.unit_length_mm,
                                    getattr(tf, "is_categorical", False))


def _table_texture(tf):
    """The 1-D transfer-function texture of ``tf``'s version (a few versions kept)."""
    key = _tf_key(tf)
    texture = _tables.pop(key, None)
    if texture is None:
        table = gpu_transfer_table(tf)[0]
        texture = _texture(len(table), "RGBA32F", "tf", table)
    _keep(_tables, key, texture)
    return texture


def _display_texture(table):
    """The 3-D texture of a display table (:mod:`.display_lut`), remade when the table is
    another array."""
    if not _display or _display[0] is not table:
        rgba = np.concatenate([table, np.ones(table.shape[:3] + (1,), np.float32)], axis=-1)
        _display[:] = [table, _texture_3d(rgba, "RGBA32F")]
    return _display[1]


def _keep(textures, key, texture):
    """Put ``texture`` under ``key`` as the most recently used, dropping the oldest beyond
    :data:`_KEPT`."""
    textures.pop(key, None)
    textures[key] = texture
    while len(textures) > _KEPT:
        textures.pop(next(iter(textures)))


def _volume_textures(vevm, shaded):
    """The textures of ``vevm`` (with its gradients when ``shaded``), made on first use; a
    VolumeEVM the GPU refused once is refused again at once (a viewport does not rebuild its
    region array at each draw)."""
    refused = _refused.get(vevm, {})  # shaded -> why (False: the region itself)
    why = refused.get(False) or refused.get(shaded)
    if why:
        raise _Refused(why)
    try:
        volume = _volumes.get(vevm)
        if volume is None:
            volume = _volumes[vevm] = _VolumeTextures(vevm)
        if shaded and volume.gradients is None:
            volume.gradients = _texture_3d(gpu_gradients(vevm), "RGBA32F")
    except _Refused as error:
        _refused.setdefault(vevm, {})[shaded] = str(error)
        raise
    return volume


def fitted_frame(vevm, camera, tf, **options):
    """The core's ``gpu_frame(vevm, camera, tf, **options)``, at the next coarser levels (each
    twice as coarse) while the GPU cannot hold the level's region texture (uploaded here, kept
    for :func:`draw`): a volume larger than the GPU's textures is drawn from a level that fits
    (``GPUFrame.level`` says which).

    Raises
    ------
    VolumeEVMError
        As ``gpu_frame``; when not even the coarsest level fits, the GPU's refusal.
    """
    frame = gpu_frame(vevm, camera, tf, **options)
    while not frame.vevm.evm.is_empty():
        try:
            _volume_textures(frame.vevm, frame.shaded)
            break
        except _Refused:
            if 2 * frame.level > max(vevm.shape):
                raise
            frame = gpu_frame(vevm, camera, tf, **{**options, "level": 2 * frame.level})
    return frame


def _textures(frame, tf, xray):
    """The region, occupancy and gradient textures of the frame's VolumeEVM, made on first
    use (the region texture stands for the gradients when the frame is not shaded: the shader
    then does not read them)."""
    volume = _volume_textures(frame.vevm, frame.shaded)
    key = (_tf_key(tf), frame.mode, xray)
    occupancy = volume.occupancy.get(key)
    if occupancy is None:
        blocks = gpu_occupancy(frame.vevm, tf, mode=frame.mode, xray_scale=xray[0],
                               xray_offset=xray[1])
        occupancy = _texture_3d(blocks, "R32F")
    _keep(volume.occupancy, key, occupancy)
    return volume.region, occupancy, volume.gradients if frame.shaded else volume.region


def free():
    """Drop every texture and the shaders (add-on unregistered, file loaded)."""
    global _shader, _batch, _stretch
    _volumes.clear()
    _refused.clear()
    _tables.clear()
    _display.clear()
    _shader = _batch = _stretch = None


# ---------------------------------------------------------------------------- drawing
@contextmanager
def restored_state(blend="NONE"):
    """Set the blend mode and switch depth test and depth writes off for a draw; put back what
    was set before, whatever happens."""
    saved = gpu.state.blend_get(), gpu.state.depth_test_get(), gpu.state.depth_mask_get()
    try:
        gpu.state.blend_set(blend)
        gpu.state.depth_test_set("NONE")
        gpu.state.depth_mask_set(False)
        yield
    finally:
        gpu.state.blend_set(saved[0])
        gpu.state.depth_test_set(saved[1])
        gpu.state.depth_mask_set(saved[2])


def draw(frame, tf, *, xray=(1.0, 0.0), blend="NONE", display=None):
    """Draw the volume of ``frame`` (the core's ``gpu_frame``) into the bound framebuffer: one
    full-screen quad, RGBA (premultiplied) to colour slot 0 and axial depth to slot 1.

    The one draw routine of the offscreen render and the viewport.

    Parameters
    ----------
    frame : GPUFrame
    tf : TransferFunction or None
        The frame's transfer function (None for X-ray).
    xray : (float, float)
        The frame's ``xray_scale`` and ``xray_offset`` (they select the occupancy blocks).
    blend : str
        ``gpu.state.blend_set`` mode for the draw: ``"NONE"`` offscreen (the values as
        computed), ``"ALPHA_PREMULT"`` over a viewport.
    display : (N, N, N, 3) ndarray, optional
        The display table (:mod:`.display_lut`) of a frame made with ``display=True``.
    """
    shader, batch = _shader_and_batch()
    region, occupancy, gradient = _textures(frame, tf, tuple(xray))
    depth = frame.depth_in  # where rays stop (axial), or none
    if depth is None:
        depth = np.full((1, 1), BACKGROUND_DEPTH, np.float32)
    depth_texture = _texture(depth.shape[::-1], "R32F", "depth_in", depth)
    uniforms = gpu.types.GPUUniformBuf(float_buffer(frame.uniforms))
    with restored_state(blend):
        shader.bind()
        shader.uniform_block("params", uniforms)
        shader.uniform_sampler("region", region)
        shader.uniform_sampler("occupancy", occupancy)
        shader.uniform_sampler("tf_table", _table_texture(tf))
        shader.uniform_sampler("depth_in", depth_texture)
        shader.uniform_sampler("gradient", gradient)
        shader.uniform_sampler("display_lut",
                               region if display is None else _display_texture(display))
        batch.draw(shader)


def draw_stretched(frame, tf, size, *, xray=(1.0, 0.0), display=None):
    """Draw ``frame`` at its own, coarser image ``size`` (width, height) into textures of that
    size, then stretch its colour over the whole bound framebuffer, premultiplied over what is
    there: the viewport's coarser frame while the view moves (a ray per block of pixels)."""
    width, height = size
    color = _texture((width, height), "RGBA16F", "viewport")
    depth = _texture((width, height), "R32F", "viewport")
    framebuffer = gpu.types.GPUFrameBuffer(color_slots=(color, depth))
    viewport = gpu.state.viewport_get()  # binding keeps the bound framebuffer's viewport
    with framebuffer.bind():
        gpu.state.viewport_set(0, 0, width, height)
        try:
            framebuffer.clear(color=(0.0, 0.0, 0.0, 0.0))
            draw(frame, tf, xray=xray, display=display)
        finally:
            gpu.state.viewport_set(*viewport)
    shader = _stretch_shader()
    _, batch = _shader_and_batch()
    with restored_state("ALPHA_PREMULT"):
        shader.bind()
        shader.uniform_sampler("image", color)
        batch.draw(shader)


def render_gpu(vevm, camera, tf, *, mode="over", depth_in=None, matrix_world=None,
               level="full", step_mm=None, termination=0.99, skip_empty=True,
               xray_scale=1.0, xray_offset=0.0, shading=None):
    """Render ``vevm`` seen by ``camera`` on the GPU: the core's ``render`` for the GPU.

    Same arguments and outputs as the core's ``render(..., method="raycast")`` (and the level
    drawn) with the options the GPU method has (``step_mm``, ``termination``, ``skip_empty``,
    X-ray's, ``shading``); the ray marcher samples as the reference does (module docstring).

    Returns
    -------
    rgba : (H, W, 4) ndarray of np.float32
        Premultiplied, row 0 at the top.
    depth : (H, W) ndarray of np.float32
        Axial depth of the first visible part, 1e10 where none.
    level : int
        The resolution level's factor drawn (1: full; ``level="auto"`` picks it per view,
        :func:`level_text` says it).

    Raises
    ------
    VolumeEVMError
        For bad input (the core's ``gpu_frame``), a volume larger than the GPU's textures at
        every level (a level that fits is drawn otherwise: :func:`fitted_frame`), an image
        larger than them, or a draw the driver dropped.
    GPUUnavailable
        When no GPU context can be made (the caller falls back to the CPU).
    """
    ensure_context()
    frame = fitted_frame(vevm, camera, tf, mode=mode, depth_in=depth_in,
                         matrix_world=matrix_world, level=level, step_mm=step_mm,
                         termination=termination, skip_empty=skip_empty, xray_scale=xray_scale,
                         xray_offset=xray_offset, shading=shading)
    h, w = camera.shape
    rgba = np.zeros((h, w, 4), np.float32)
    depth = np.full((h, w), BACKGROUND_DEPTH, np.float32)
    if frame.vevm.evm.is_empty():
        return rgba, depth, frame.level
    color_target = _texture((w, h), "RGBA32F", "camera")
    depth_target = _texture((w, h), "R32F", "camera")
    framebuffer = gpu.types.GPUFrameBuffer(color_slots=(color_target, depth_target))
    with framebuffer.bind():
        framebuffer.clear(color=(_SENTINEL, 0.0, 0.0, 0.0))
        draw(frame, tf, xray=(xray_scale, xray_offset))
        framebuffer.read_color(0, 0, w, h, 4, 0, "FLOAT", data=float_buffer(rgba))
        framebuffer.read_color(0, 0, w, h, 1, 1, "FLOAT", data=float_buffer(depth))
    if (depth == _SENTINEL).any():
        raise VolumeEVMError("the GPU dropped the volume's draw (its driver drew nothing); "
                             "render with a CPU method")
    return np.flipud(rgba).copy(), np.flipud(depth).copy(), frame.level


def level_text(level):
    """Which resolution level a draw showed, for the sidebar and the render's note: "" for
    the full level, else e.g. "level 2 (2× coarser voxels)"."""
    return "" if level == 1 else f"level {level} ({level}\u00d7 coarser voxels)"
