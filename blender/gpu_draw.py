"""Direct volume rendering on the GPU through Blender's own ``gpu`` module: the shaders, one
draw routine, and the offscreen render read back.

The core computes everything but the drawing (``gpu_frame``: checks, the pixel rays, the std140
uniforms; the textures' arrays, uploaded by :mod:`.gpu_textures`); this module draws one
full-screen quad whose fragment shader (``volumeevm_addon/rendering/shaders/dvr.frag.glsl``,
read with the core's :func:`gpu_shader_source`: the shader text is data beside the core's GPU
inputs) marches the pixel's ray:

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

The shaders are made once per process and freed by :func:`free` (with the textures); drawing
saves and restores the GPU state it changes. :func:`draw` is the one draw routine of the
offscreen render (:func:`render_gpu`, after :func:`.gpu_context.ensure_context`) and of the
viewport (:mod:`.gpu_viewport`).
"""

from contextlib import contextmanager

import gpu
import numpy as np
from gpu_extras.batch import batch_for_shader

from ..volumeevm_addon import VolumeEVMError
from ..volumeevm_addon.rendering import (
    BACKGROUND_DEPTH,
    GPU_UNIFORMS_GLSL,
    gpu_shader_source,
    methods,
)
from . import display_lut, gpu_context, gpu_textures

#: The method's name among Render VolumeEVM's methods (:data:`.dvr.METHODS`): the core's GPU
#: record (its options, quality and CPU fallback).
METHOD = next(name for name, record in methods().items() if record.gpu)

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


def free():
    """Drop the shaders and every texture (:func:`.gpu_textures.free`): add-on unregistered,
    file loaded."""
    global _shader, _batch, _stretch
    gpu_textures.free()
    _shader = _batch = _stretch = None


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
    region, occupancy, gradient = gpu_textures.frame_textures(frame, tf, tuple(xray))
    depth = frame.depth_in  # where rays stop (axial), or none
    if depth is None:
        depth = np.full((1, 1), BACKGROUND_DEPTH, np.float32)
    depth_texture = gpu_textures.texture(depth.shape[::-1], "R32F", "depth_in", depth)
    uniforms = gpu.types.GPUUniformBuf(gpu_textures.float_buffer(frame.uniforms))
    with restored_state(blend):
        shader.bind()
        shader.uniform_block("params", uniforms)
        shader.uniform_sampler("region", region)
        shader.uniform_sampler("occupancy", occupancy)
        shader.uniform_sampler("tf_table", gpu_textures.table_texture(tf))
        shader.uniform_sampler("depth_in", depth_texture)
        shader.uniform_sampler("gradient", gradient)
        shader.uniform_sampler("display_lut", region if display is None
                               else gpu_textures.display_texture(display))
        batch.draw(shader)


def draw_stretched(frame, tf, size, *, xray=(1.0, 0.0), display=None):
    """Draw ``frame`` at its own, coarser image ``size`` (width, height) into textures of that
    size, then stretch its colour over the whole bound framebuffer, premultiplied over what is
    there: the viewport's coarser frame while the view moves (a ray per block of pixels)."""
    width, height = size
    color = gpu_textures.texture((width, height), "RGBA16F", "viewport")
    depth = gpu_textures.texture((width, height), "R32F", "viewport")
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
        every level (a level that fits is drawn otherwise:
        :func:`.gpu_textures.fitted_frame`), an image larger than them, or a draw the driver
        dropped.
    GPUUnavailable
        When no GPU context can be made (:mod:`.gpu_context`; the caller falls back to the
        CPU).
    """
    gpu_context.ensure_context()
    frame = gpu_textures.fitted_frame(vevm, camera, tf, mode=mode, depth_in=depth_in,
                                      matrix_world=matrix_world, level=level, step_mm=step_mm,
                                      termination=termination, skip_empty=skip_empty,
                                      xray_scale=xray_scale, xray_offset=xray_offset,
                                      shading=shading)
    h, w = camera.shape
    rgba = np.zeros((h, w, 4), np.float32)
    depth = np.full((h, w), BACKGROUND_DEPTH, np.float32)
    if frame.vevm.evm.is_empty():
        return rgba, depth, frame.level
    color_target = gpu_textures.texture((w, h), "RGBA32F", "camera")
    depth_target = gpu_textures.texture((w, h), "R32F", "camera")
    framebuffer = gpu.types.GPUFrameBuffer(color_slots=(color_target, depth_target))
    with framebuffer.bind():
        framebuffer.clear(color=(_SENTINEL, 0.0, 0.0, 0.0))
        draw(frame, tf, xray=(xray_scale, xray_offset))
        framebuffer.read_color(0, 0, w, h, 4, 0, "FLOAT", data=gpu_textures.float_buffer(rgba))
        framebuffer.read_color(0, 0, w, h, 1, 1, "FLOAT", data=gpu_textures.float_buffer(depth))
    if (depth == _SENTINEL).any():
        raise VolumeEVMError("the GPU dropped the volume's draw (its driver drew nothing); "
                             "render with a CPU method")
    return np.flipud(rgba).copy(), np.flipud(depth).copy(), frame.level


def level_text(level):
    """Which resolution level a draw showed, for the sidebar and the render's note: "" for
    the full level, else e.g. "level 2 (2× coarser voxels)"."""
    return "" if level == 1 else f"level {level} ({level}\u00d7 coarser voxels)"
