"""What the GPU ray marcher needs, computed with NumPy: the view, the volume, the transfer
function and the uniforms.

The GPU method (``blender/gpu_draw.py`` and ``gpu_textures.py``, through Blender's ``gpu``
module) marches every pixel's ray in a fragment shader. Everything that can be decided without
a GPU is decided here, in float64 and rounded to float32 once, so that it is tested without a
GPU and the Blender side only uploads arrays and draws:

- **View.** Two matrices take a pixel's normalised device coordinates (NDC, OpenGL's: ``x, y``
  in ``[-1, 1]`` across the image) to its ray in the volume's index space (voxel centres at
  integer indices): ``o + t·d`` is the point of axial depth ``a_c + t``, ``o = O·(x, y, 1)``
  and ``d = D·(x, y, 1)`` (both affine in ``x, y``: a perspective ray's direction, an
  orthographic ray's origin), with ``a_c`` the axial depth of the grid's centre. So ``t`` is
  axial depth itself, the clip range and ``depth_in`` cut the ray exactly where the CPU
  renderers cut it, and ``o`` lies near the volume: in float32 the samples stay within about
  1e-5 voxel of the float64 rays. (Unprojecting two depths through ``inv(projection)``, the
  textbook way, cancels terms of the size of the clip range: 4e-3 voxel of error along an
  orthographic ray with Blender's 0.1 to 100 clip range.) A 3D viewport's matrices become a
  :class:`Camera` too (:func:`camera_from_viewport`), so the viewport and F12 share every
  rule.
- **Depth.** A viewport's depth buffer holds *window* depth in ``[0, 1]``, a render's Z pass
  *axial* depth (:mod:`._camera`); :func:`axial_from_window` and :func:`window_from_axial`
  convert through the camera's projection.
- **Region** (:func:`gpu_region`): the boundary policy "clamp" (:mod:`._reference`) in one RG
  texture, ``(density · inside, inside)`` per voxel: a trilinear fetch gives both weighted sums,
  and their ratio is the interpolation renormalised over region voxels.
- **Gradients** (:func:`gpu_gradients`, for shading): the CPU methods' per-voxel gradients
  (:mod:`._gradients`, outside the region 0) in an RGBA texture; a trilinear fetch divided by
  the region texture's weight is the gradient interpolated as the CPU ray caster interpolates
  it, and the shader lights each sample with the headlight and fade of :mod:`._shading`.
- **Empty space** (:func:`gpu_occupancy`): one texel per block of ``8³`` voxels, 0 where a
  sample may contribute: the space-leaping blocks of the CPU ray caster (``_raycast._Blocks``:
  region voxels within one voxel, the transfer function not transparent on their density
  range widened by one row of the transfer-function table), so skipping never changes the
  image; elsewhere the distance in blocks to the nearest such block, so that a ray leaps the
  whole empty cube around it at once (on the CT head a third of the leaps of block-by-block
  leaping).
- **Transfer function** (:func:`gpu_transfer_table`): straight RGBA (opacity per
  ``unit_length_mm``) at :data:`GPU_TABLE_ROWS` values over its control points' range,
  interpolated linearly; the shader corrects the opacity for the length of each part.
- **Uniforms** (:func:`gpu_frame`): one uniform buffer in std140 layout (every field a ``vec4``
  or a column-major ``mat4``), declared for the shader by :data:`GPU_UNIFORMS_GLSL` from the
  same field list, so the two cannot drift apart.

Arrays for 3D textures are C-contiguous float32 in ``[z, y, x]`` order (x varies fastest, as
OpenGL reads a texture); 2D images for the GPU run bottom row first.
"""

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .._errors import VolumeEVMError
from .._jit import kernel
from .._memory import check_memory
from ..model._volume import grid_to_world
from . import _depth
from ._camera import BACKGROUND_DEPTH, Camera
from ._checks import (
    RAY_STEPS_PER_VOXEL,
    categorical,
    check_camera,
    check_mode,
    check_transfer_function,
    check_volumeevm,
    checked_affine,
    checked_categorical_level,
    checked_step_mm,
    checked_view,
    checked_xray,
    flag,
    positive_integer,
    positive_number,
)
from ._gradients import region_gradients
from ._levels import level_factor
from ._method import (
    Method,
    check_method_samples,
    keyword_options,
    one_set,
    step_quality,
    step_samples,
)
from ._shading import Lighting, checked_shading

__all__ = ["GPU_BLOCK", "GPU_TABLE_ROWS", "GPU_UNIFORMS_GLSL", "GPUFrame", "gpu_frame",
           "gpu_shader_source",
           "gpu_region", "gpu_gradients", "gpu_occupancy", "gpu_transfer_table",
           "camera_from_viewport", "axial_from_window", "window_from_axial", "GPU_METHOD"]

GPU_BLOCK = 8
"""Edge in voxels of the occupancy blocks (empty-space skipping)."""
GPU_TABLE_ROWS = 4096
"""Rows of the transfer-function table (the CPU ray caster's lookup-table size)."""

_MODE_CODES = {"over": 0, "under": 0, "xray": 1, "mip": 2}
"""The shader's compositing: front to back (``"under"`` too: the same image up to rounding,
composited without early termination), X-ray attenuation, or the maximum along the ray."""

_FIELDS = (
    ("ray_origin", "mat4", "index-space ray point o = (m * vec4(ndc, 1, 0)).xyz at t = 0"),
    ("ray_direction", "mat4", "index-space d = (m * vec4(ndc, 1, 0)).xyz per unit of t"),
    ("grid", "vec4", "voxels along x, y, z; block edge in voxels"),
    ("blocks", "vec4", "blocks along x, y, z; 1 to skip empty blocks"),
    ("spacing", "vec4", "voxel size along x, y, z (mm); largest step (mm)"),
    ("clip", "vec4", "t of clip_start and of clip_end; axial depth at t = 0; 0"),
    ("compositing", "vec4", "mode code; termination; xray_scale, xray_offset"),
    ("table", "vec4", "table: first value, rows per data unit, rows; unit_length_mm"),
    ("image", "vec4", "width, height; 1 when depth_in is given; 1 for a display"),
    ("normal", "mat4", "index-space gradient g to world normal (m * vec4(g, 0)).xyz"),
    ("to_world", "mat4", "index-space direction d to world (m * vec4(d, 0)).xyz"),
    ("shading", "vec4", "Blinn-Phong ambient, diffuse, specular, shininess"),
    ("fade", "vec4", "gradient magnitudes where shading fades in, from, to; 1 when shaded; 0"),
    ("labels", "vec4", "1 for a categorical function (nearest voxel, exact rows); 0, 0, 0"),
)
_FLOATS = {"vec4": 4, "mat4": 16}


def _glsl_struct():
    """The GLSL declaration of the uniform block (struct ``VolumeParams``), the mode codes and
    the constants of the depth rule (float32 values, written exactly)."""
    lines = [f"const int MODE_{name.upper()} = {code};"
             for name, code in _MODE_CODES.items() if name != "under"]
    lines += [f"const float {name} = {float(np.float32(value))!r};" for name, value in (
        ("VISIBLE_ALPHA", _depth.VISIBLE_ALPHA),
        ("VISIBLE_OPTICAL_DEPTH", _depth.VISIBLE_OPTICAL_DEPTH),
        ("BACKGROUND_DEPTH", BACKGROUND_DEPTH))]
    lines.append("struct VolumeParams {")
    lines += [f"  {kind} {name};  /* {what} */" for name, kind, what in _FIELDS]
    lines.append("};")
    return "\n".join(lines) + "\n"


GPU_UNIFORMS_GLSL = _glsl_struct()
"""GLSL source declaring ``struct VolumeParams`` (the fields of :attr:`GPUFrame.uniforms`, in
order), the mode codes ``MODE_OVER``, ``MODE_XRAY`` and ``MODE_MIP`` (its ``compositing.x``)
and the constants ``VISIBLE_ALPHA``, ``VISIBLE_OPTICAL_DEPTH`` and ``BACKGROUND_DEPTH``."""


def _pack(values):
    """The std140 bytes of the fields, as float32: every field a ``vec4`` or a ``mat4`` (four
    column ``vec4`` s), so the layout has no padding."""
    out = []
    for name, kind, _ in _FIELDS:
        v = np.asarray(values[name], dtype=np.float64)
        if kind == "mat4":
            v = v.T  # column-major
        if v.size != _FLOATS[kind]:
            raise AssertionError(f"uniform {name}: {v.size} floats for a {kind}")
        out.append(v.ravel())
    return np.concatenate(out).astype(np.float32)


# ---------------------------------------------------------------------------- view and depth
def camera_from_viewport(projection, view_matrix, width, height):
    """The :class:`Camera` a 3D viewport renders through, from its matrices.

    A viewport's projection may be off-centre and its pixels non-square; the camera made here
    has the same projection matrix (:meth:`Camera.matrix_projection`), its image width spanned
    by the view plane (``sensor_fit="HORIZONTAL"``), the off-centre part as lens shift and the
    aspect as pixel aspect. An orthographic viewport may clip in front of the eye (Blender's
    does, from ``-clip_end``); the camera is then moved back along its axis to the near plane,
    so axial depths count from there.

    Parameters
    ----------
    projection : (4, 4) array_like
        The viewport's projection matrix (``RegionView3D.window_matrix``,
        ``gpu.matrix.get_projection_matrix()``): OpenGL clip space from eye space.
    view_matrix : (4, 4) array_like
        World to eye space (``RegionView3D.view_matrix``), rigid.
    width, height : int
        The viewport's size in pixels.

    Returns
    -------
    Camera
        Orthographic or perspective as ``projection`` is, ``resolution_x, resolution_y = width,
        height`` at 100 %.

    Raises
    ------
    VolumeEVMError
        If ``projection`` is neither an OpenGL orthographic nor a perspective matrix (naming
        it), ``view_matrix`` is not an invertible affine matrix, or the size is not two
        positive integers.

    Examples
    --------
    >>> cam = Camera.perspective(np.eye(4), 35.0, resolution_x=8, resolution_y=6, shift_x=0.1)
    >>> view = camera_from_viewport(cam.matrix_projection(), np.eye(4), 8, 6)
    >>> bool(np.allclose(view.matrix_projection(), cam.matrix_projection()))
    True
    """
    p = _checked_4x4("projection", projection)
    v = checked_affine("view_matrix", view_matrix, invertible=True)
    width = positive_integer("width", width)
    height = positive_integer("height", height)
    ortho = np.allclose(p[3], (0.0, 0.0, 0.0, 1.0))
    if not ortho and not np.allclose(p[3], (0.0, 0.0, -1.0, 0.0)):
        raise VolumeEVMError(f"projection: last row must be (0, 0, 0, 1) (orthographic) or "
                             f"(0, 0, -1, 0) (perspective), got {p[3]}")
    if p[0, 0] <= 0 or p[1, 1] <= 0 or p[2, 2] == 0 or p[0, 1] or p[1, 0] or p[2, 0] or p[2, 1]:
        raise VolumeEVMError("projection: not an OpenGL orthographic or perspective matrix")
    matrix_world = np.linalg.inv(v)
    if ortho:
        # x_ndc = P00·x + P03 over the view plane: its edges sit at x_ndc = -1 and 1.
        xmin, xmax = (-1 - p[0, 3]) / p[0, 0], (1 - p[0, 3]) / p[0, 0]
        ymin, ymax = (-1 - p[1, 3]) / p[1, 1], (1 - p[1, 3]) / p[1, 1]
        near, far = (p[2, 3] + 1) / p[2, 2], (p[2, 3] - 1) / p[2, 2]  # axial depth at z_ndc ∓1
        if near < 0:  # move back to the near plane
            matrix_world = matrix_world.copy()
            axis = matrix_world[:3, 2] / np.linalg.norm(matrix_world[:3, 2])
            matrix_world[:3, 3] -= near * axis
            near, far = 0.0, far - near
        size, options = xmax - xmin, {"ortho_scale": xmax - xmin}
    else:
        # x_ndc = (P00·x + P02·z) / -z at unit distance (z = -1): the edges at -1 and 1.
        xmin, xmax = (-1 + p[0, 2]) / p[0, 0], (1 + p[0, 2]) / p[0, 0]
        ymin, ymax = (-1 + p[1, 2]) / p[1, 1], (1 + p[1, 2]) / p[1, 1]
        near = p[2, 3] / (p[2, 2] - 1)
        far = p[2, 3] / (p[2, 2] + 1)
        size, options = xmax - xmin, {"lens_mm": 36.0 / (xmax - xmin), "sensor_width": 36.0}
    ycor = (ymax - ymin) * width / (height * size)
    return Camera("ORTHO" if ortho else "PERSP", matrix_world, sensor_fit="HORIZONTAL",
                  shift_x=0.5 * (xmin + xmax) / size, shift_y=0.5 * (ymin + ymax) / size,
                  clip_start=near, clip_end=far, resolution_x=width, resolution_y=height,
                  pixel_aspect_x=1.0, pixel_aspect_y=ycor, **options)


def _checked_4x4(name, matrix):
    """``matrix`` as a finite 4x4 float64 array (any last row)."""
    try:
        m = np.asarray(matrix, dtype=np.float64)
    except (TypeError, ValueError) as error:
        raise VolumeEVMError(f"{name}: expected a 4x4 matrix of numbers, got "
                             f"{type(matrix).__name__}") from error
    if m.shape != (4, 4) or not np.isfinite(m).all():
        raise VolumeEVMError(f"{name}: expected a finite 4x4 matrix, got shape {m.shape}")
    return m


def axial_from_window(window_depth, camera):
    """Axial depth of window depths of ``camera``'s projection.

    Window depth is what a depth buffer holds: ``(z_ndc + 1) / 2``, 0 on the near clip plane and
    1 on the far one. A depth buffer's 1 (nothing drawn) becomes
    :data:`~volumeevm_addon.rendering.BACKGROUND_DEPTH`, as in a render's Z pass.

    Parameters
    ----------
    window_depth : array_like
        Window depths in ``[0, 1]``, any shape.
    camera : Camera
        Whose projection wrote them (:meth:`Camera.matrix_projection`).

    Returns
    -------
    ndarray of np.float64
        Axial depth in Blender units, the shape of ``window_depth``.

    Raises
    ------
    VolumeEVMError
        If a window depth is NaN or outside ``[0, 1]``.

    Examples
    --------
    >>> cam = Camera.perspective(np.eye(4), 50.0, clip_start=0.1, clip_end=100.0)
    >>> axial_from_window([0.0, 0.5, 1.0], cam).round(6).tolist()
    [0.1, 0.1998, 10000000000.0]
    """
    w = np.asarray(window_depth, dtype=np.float64)
    if np.isnan(w).any() or (w < 0).any() or (w > 1).any():
        raise VolumeEVMError("window_depth: window depths must lie in [0, 1]")
    p = camera.matrix_projection()
    z = 2.0 * w - 1.0
    # z_ndc = (P22·ze + P23) / (P32·ze + P33), solved for the eye-space ze = -axial.
    axial = -(p[2, 3] - p[3, 3] * z) / (p[3, 2] * z - p[2, 2])
    return np.where(w < 1.0, axial, BACKGROUND_DEPTH)


def window_from_axial(axial_depth, camera):
    """Window depth (``[0, 1]``, what a depth buffer holds) of axial depths, for ``camera``.

    Depths beyond the far clip plane (:data:`~volumeevm_addon.rendering.BACKGROUND_DEPTH`
    included) give 1, depths before the near one 0.

    Parameters
    ----------
    axial_depth : array_like
        Axial depth in Blender units, any shape.
    camera : Camera
        Whose projection the depth buffer has (:meth:`Camera.matrix_projection`).

    Returns
    -------
    ndarray of np.float64
        The shape of ``axial_depth``.

    Raises
    ------
    VolumeEVMError
        If an axial depth is NaN.

    Examples
    --------
    >>> cam = Camera.orthographic(np.eye(4), 2.0, clip_start=0.0, clip_end=10.0)
    >>> window_from_axial([0.0, 5.0, 1e10], cam).tolist()
    [0.0, 0.5, 1.0]
    """
    a = np.asarray(axial_depth, dtype=np.float64)
    if np.isnan(a).any():
        raise VolumeEVMError("axial_depth: NaN depths")
    a = np.clip(a, camera.clip_start, camera.clip_end)
    p = camera.matrix_projection()
    z = (p[2, 3] - p[2, 2] * a) / (p[3, 3] - p[3, 2] * a)
    return np.clip(0.5 * (z + 1.0), 0.0, 1.0)


# ---------------------------------------------------------------------------- volume and tf
def gpu_region(vevm):
    """The region's densities and membership as one RG texture: ``(density · inside, inside)``.

    A trilinear fetch of it at an index-space point ``p`` gives ``(Σ w·d·r, Σ w·r)`` over the 8
    neighbours (``r`` = 1 for region voxels); their ratio is the density renormalised over the
    region's voxels, the boundary policy "clamp" of :mod:`._reference` (clamp-to-edge at the
    grid's faces is the same rule). ``inside`` at the voxel nearest ``p`` says whether ``p``'s
    cell belongs to the region.

    Parameters
    ----------
    vevm : VolumeEVM

    Returns
    -------
    (Z, Y, X, 2) ndarray of np.float32
        C-contiguous, x fastest (a texture of size ``(X, Y, Z)``); 0 outside the region.

    Raises
    ------
    VolumeEVMError
        If ``vevm`` is not a VolumeEVM, or the array would not fit in the memory available.
    """
    nx, ny, nz = _checked_grid(vevm, 9, "texture")
    out = np.zeros((nz, ny, nx, 2), np.float32)
    _fill_region(vevm.evm.to_mask(vevm.shape), np.asarray(vevm.table(0), dtype=np.float32), out)
    return out


def gpu_gradients(vevm):
    """Shading's per-voxel gradients as one RGBA texture: ``(gx, gy, gz, 0)`` per voxel, the
    index-space gradient of :func:`._gradients.region_gradients` (0 outside the region).

    A trilinear fetch of it divided by the weight of :func:`gpu_region`'s fetch at the same
    point is the gradient interpolated over the region's voxels, as the CPU ray caster
    interpolates it.

    Parameters
    ----------
    vevm : VolumeEVM

    Returns
    -------
    (Z, Y, X, 4) ndarray of np.float32
        C-contiguous, x fastest (a texture of size ``(X, Y, Z)``).

    Raises
    ------
    VolumeEVMError
        If ``vevm`` is not a VolumeEVM, or the arrays would not fit in the memory available.
    """
    nx, ny, nz = _checked_grid(vevm, 44, "gradient texture")
    padded = np.pad(gpu_region(vevm), ((1, 1), (1, 1), (1, 1), (0, 0)))
    grads = np.zeros((3, nz, ny, nx), np.float32)  # along z, y, x
    region_gradients(padded[..., 0], padded[..., 1], grads)
    del padded
    out = np.zeros((nz, ny, nx, 4), np.float32)
    for c in range(3):
        out[..., c] = grads[2 - c]
    return out


def _checked_grid(vevm, bytes_per_voxel, what):
    """The grid's voxels along x, y, z, once ``vevm`` is checked and ``bytes_per_voxel`` of
    its grid fit in the memory available (``what``: the GPU array they make)."""
    check_volumeevm(vevm)
    nx, ny, nz = (int(n) for n in vevm.shape)
    check_memory(bytes_per_voxel * nx * ny * nz, f"the GPU {what} of {nx}x{ny}x{nz} voxels",
                 source="vevm", advice="render a coarser level (level='auto' or an integer)")
    return nx, ny, nz


@kernel
def _fill_region(mask, dens, out):
    """Write ``(density, 1)`` of each region voxel into ``out`` (indexed ``[z, y, x]``): one
    pass over the region ``mask`` in C order ``[x, y, z]``, the order of the densities ``dens``
    of the table of order "xyz"."""
    nx, ny, nz = mask.shape
    k = 0
    for x in range(nx):
        for y in range(ny):
            for z in range(nz):
                if mask[x, y, z]:
                    out[z, y, x, 0] = dens[k]
                    out[z, y, x, 1] = 1.0
                    k += 1


def gpu_transfer_table(tf):
    """The transfer function as the GPU's 1-D table: straight RGBA at :data:`GPU_TABLE_ROWS`
    values (a categorical function: at its integers, a row per label) over its control points'
    range (outside of which it is constant).

    Parameters
    ----------
    tf : TransferFunction or None
        None (X-ray) gives a transparent table.

    Returns
    -------
    table : (rows, 4) ndarray of np.float32
        Row ``i`` is the value ``lo + i·(hi - lo)/(rows - 1)``; opacity per ``unit_length_mm``.
    lo, hi : float
        The values of the first and last rows.

    Raises
    ------
    VolumeEVMError
        If ``tf`` is not a TransferFunction.
    """
    if tf is None:
        return np.zeros((GPU_TABLE_ROWS, 4), np.float32), 0.0, 1.0
    check_transfer_function(tf, "over")
    lo, hi = _table_range(tf)
    table = tf.straight_table(lo=lo, hi=hi, n=tf.lut_size(GPU_TABLE_ROWS))
    return np.ascontiguousarray(table, dtype=np.float32), lo, hi


def _table_range(tf):
    """The values of the table's first and last rows (the control points' range; one more data
    unit for a single point)."""
    if tf is None:
        return 0.0, 1.0
    lo, hi = tf.value_range
    return lo, (hi if hi > lo else lo + 1.0)


def gpu_occupancy(vevm, tf, *, mode="over", xray_scale=1.0, xray_offset=0.0):
    """Where samples may contribute, by blocks of :data:`GPU_BLOCK`³ voxels: the empty-space
    texture of the GPU's space leaping.

    A block may contribute when a region voxel lies within one voxel of its cells and (over,
    under) the transfer function is not transparent on their densities widened by one table
    row, (X-ray) some density attenuates; MIP needs only the region (the CPU ray caster's
    space-leaping blocks, kept in ``vevm.cache`` and shared with it). A sample whose cell lies
    in another block adds exactly nothing, so skipping never changes the image.

    Parameters
    ----------
    vevm : VolumeEVM
    tf : TransferFunction or None
        None for X-ray.
    mode : {"over", "under", "xray", "mip"}, optional
    xray_scale, xray_offset : float, optional
        X-ray's attenuation per mm per data unit and density of zero attenuation.

    Returns
    -------
    (BZ, BY, BX) ndarray of np.float32
        Per block (x fastest, ``B = ceil(n / GPU_BLOCK)`` per axis): 0 where samples may
        contribute, else the Chebyshev distance ``r >= 1`` in blocks to the nearest such block
        (every block within ``r - 1`` of it is empty too); ``max(B)`` when there is none.

    Raises
    ------
    VolumeEVMError
        For a bad ``vevm``, ``mode``, ``tf`` or X-ray parameters.

    Examples
    --------
    >>> from volumeevm_addon import VolumeEVM, phantoms
    >>> vevm = VolumeEVM.from_volume(phantoms.box((40, 8, 8), lo=(0, 0, 0), hi=(4, 4, 4)), 0.5)
    >>> gpu_occupancy(vevm, None, mode="xray")[0, 0].tolist()
    [0.0, 1.0, 2.0, 3.0, 4.0]
    """
    check_volumeevm(vevm)
    check_mode(mode)
    check_transfer_function(tf, mode)
    xray_scale, xray_offset = checked_xray(xray_scale, xray_offset)
    nb = -(-np.asarray(vevm.shape, dtype=np.int64) // GPU_BLOCK)
    if vevm.evm.is_empty():
        return np.full(tuple(nb[::-1]), float(nb.max()), np.float32)
    from ._raycast import _Blocks  # the ray caster loads on first use, as render() loads it

    blocks = vevm.cache.get(("raycast", "blocks", GPU_BLOCK, 1),
                            lambda: _Blocks(vevm, GPU_BLOCK, 1))
    lo, hi = _table_range(tf)
    rows = GPU_TABLE_ROWS if tf is None else tf.lut_size(GPU_TABLE_ROWS)
    visible = blocks.visible(mode, tf, (hi - lo) / (rows - 1), xray_scale,
                             xray_offset)
    visible = visible.reshape(tuple(nb + 2))[1:-1, 1:-1, 1:-1]  # drop the padding
    return np.ascontiguousarray(_empty_distance(visible).transpose(2, 1, 0))


def _empty_distance(visible):
    """Chebyshev distance (float32, in blocks) of every block to the nearest ``visible`` one:
    0 on them, ``max(shape)`` everywhere when there is none."""
    limit = max(visible.shape)
    distance = np.full(visible.shape, float(limit), np.float32)
    distance[visible] = 0.0
    reached = visible.copy()
    for r in range(1, limit):
        if reached.all() or not reached.any():
            break
        grown = reached.copy()
        for axis in range(3):  # the 26-neighbourhood, one axis at a time
            step = grown.copy()
            lower = [slice(None)] * 3
            upper = [slice(None)] * 3
            lower[axis], upper[axis] = slice(0, -1), slice(1, None)
            step[tuple(lower)] |= grown[tuple(upper)]
            step[tuple(upper)] |= grown[tuple(lower)]
            grown = step
        distance[grown & ~reached] = r
        reached = grown
    return distance


# ---------------------------------------------------------------------------- one frame
@dataclass(frozen=True, eq=False)
class GPUFrame:
    """One GPU render's inputs, checked: the VolumeEVM to upload (the level chosen), its
    placement, the uniforms and the scene depth.

    Attributes
    ----------
    vevm : VolumeEVM
        The VolumeEVM rendered: the one given, or its coarser level.
    grid_to_world : (4, 4) ndarray of np.float64
        Its voxel-centre indices to world.
    rays : (2, 3, 3) ndarray of np.float64
        The pixel rays in index space: ``o = rays[0] @ (x, y, 1)`` and ``d = rays[1] @ (x, y,
        1)`` for NDC ``(x, y)``, the point ``o + t·d`` at axial depth ``axial_origin + t``.
    axial_origin : float
        The axial depth at ``t = 0``: that of the grid's centre.
    uniforms : (N,) ndarray of np.float32
        The uniform buffer (std140, declared by :data:`GPU_UNIFORMS_GLSL`).
    depth_in : (H, W) ndarray of np.float32 or None
        Axial depth where rays stop, bottom row first (an OpenGL texture), or None.
    mode : str
        The compositing mode asked for.
    shaded : bool
        Whether the shader lights the samples (it then reads :func:`gpu_gradients`).
    level : int
        The resolution level's factor: 1 for the full level, ``k`` for voxels ``k`` times
        coarser (level "auto" picks it per view).
    """

    vevm: object
    grid_to_world: np.ndarray
    rays: np.ndarray
    axial_origin: float
    uniforms: np.ndarray
    depth_in: object
    mode: str
    shaded: bool
    level: int


def gpu_frame(vevm, camera, tf, *, mode="over", depth_in=None, matrix_world=None, level="full",
              step_mm=None, termination=0.99, skip_empty=True, xray_scale=1.0,
              xray_offset=0.0, display=False, shading=None):
    """Check one GPU render's settings and compute its uniforms (what :func:`render` does before
    it renders, for the GPU).

    The shader then marches each pixel's ray as the reference samples it (module docstring of
    :mod:`._reference`): clipped to the volume's box, the clip range and ``depth_in``, cut
    into equal parts no longer than ``step_mm``, each sampled at its midpoint (trilinear,
    boundary policy "clamp", post-classified, opacity corrected for the length of the part
    that lies in region cells: cut at cell boundaries as the CPU ray caster cuts it, so the
    region's surface is placed exactly), lit with ``shading`` (the gradients of
    :func:`gpu_gradients` interpolated the same way, the headlight and fade of
    :mod:`._shading`), composited front to back with early termination; the output depth is
    where the first visible part enters the region (:mod:`._depth`).

    Parameters
    ----------
    vevm : VolumeEVM
    camera : Camera
        The render's camera, or a viewport's (:func:`camera_from_viewport`).
    tf : TransferFunction or None
        None only for ``mode="xray"``.
    mode : {"over", "under", "xray", "mip"}, optional
        As for :func:`~volumeevm_addon.render`; ``"under"`` composites front to back without
        early termination (the same image up to rounding).
    depth_in : (H, W) array_like, optional
        Axial depth (Blender units) where rays stop, row 0 at the top; 1e10 for none.
    matrix_world : (4, 4) array_like, optional
        The volume object's placement (identity by default).
    level : {"full", "auto"} or int, optional
        Resolution level, as for :func:`~volumeevm_addon.render`.
    step_mm : float, optional
        Largest part of a ray in mm (default: half the smallest voxel size of the level).
    termination : float, optional
        Over: a ray stops once this opaque (1: never).
    skip_empty : bool, optional
        Skip blocks where nothing can be seen (the same image, faster).
    xray_scale, xray_offset : float, optional
        X-ray's attenuation per mm per data unit and density of zero attenuation.
    display : bool, optional
        Draw for a 3D viewport's display: the shader maps the straight colour through the
        display table it is given (the scene's colour management: a 3D viewport draws add-ons
        after the scene's view transform) and premultiplies it again. False (default):
        scene-linear, as every renderer returns it.
    shading : None, True, dict or Shading, optional
        Gradient shading for ``"over"`` and ``"under"`` (:class:`._shading.Shading`, as for
        the CPU methods; ignored by ``"xray"`` and ``"mip"``): the shader then reads
        :func:`gpu_gradients`' texture.

    Returns
    -------
    GPUFrame

    Raises
    ------
    VolumeEVMError
        For a bad VolumeEVM, camera, transfer function, mode, placement, level, step,
        termination, flag, X-ray parameter, shading or ``depth_in`` (naming it), or a step
        that would take more than ``MAX_SAMPLES`` samples.
    """
    check_camera(camera)
    level = checked_categorical_level(tf, mode, level, {"shading": shading})
    shading = checked_shading(shading)
    check_volumeevm(vevm)
    if step_mm is not None:
        step_mm = positive_number("step_mm", step_mm)
    if matrix_world is not None:
        matrix_world = checked_affine("matrix_world", matrix_world)
    to_world = grid_to_world(vevm.spacing, vevm.origin, vevm.orientation, matrix_world)
    factor = level_factor(level, vevm.shape, to_world, camera)
    if factor > 1:
        vevm = vevm.level(factor)
        to_world = grid_to_world(vevm.spacing, vevm.origin, vevm.orientation, matrix_world)
        step_mm = None if step_mm is None else step_mm * factor
    g, depth_in, compositing = checked_view(vevm, camera, tf, to_world, mode, depth_in,
                                            termination, xray_scale, xray_offset)
    spacing = np.asarray(vevm.spacing, dtype=np.float64)
    step = checked_step_mm(step_mm, spacing, RAY_STEPS_PER_VOXEL)
    check_method_samples(GPU_METHOD, vevm, camera, g, {"step_mm": step})
    skip_empty = flag("skip_empty", skip_empty)
    display = flag("display", display)
    rays, axial_origin = _pixel_rays(camera, g, vevm.shape)
    lighting = Lighting.of_view(shading if mode in ("over", "under") else None, g, tf)
    lo, hi = _table_range(tf)
    rows = GPU_TABLE_ROWS if tf is None else tf.lut_size(GPU_TABLE_ROWS)
    n = np.asarray(vevm.shape, dtype=np.float64)
    h, w = camera.shape
    uniforms = _pack({
        "ray_origin": _mat4(rays[0]),
        "ray_direction": _mat4(rays[1]),
        "grid": (*n, GPU_BLOCK),
        "blocks": (*np.ceil(n / GPU_BLOCK), float(skip_empty)),
        "spacing": (*spacing, step),
        "clip": (camera.clip_start - axial_origin, camera.clip_end - axial_origin,
                 axial_origin, 0.0),
        "compositing": (_MODE_CODES[mode], compositing.termination if mode == "over" else 1.0,
                        compositing.xray_scale, compositing.xray_offset),
        "table": (lo, (rows - 1) / (hi - lo), rows, 1.0 if tf is None else tf.unit_length_mm),
        "image": (w, h, float(depth_in is not None), float(display)),
        "normal": _mat4(np.zeros((3, 3)) if lighting is None else lighting.inv_t),
        "to_world": _mat4(g[:3, :3]),
        "shading": (0.0,) * 4 if lighting is None else lighting.weights()[:4],
        "fade": (0.0, 0.0, 0.0, 0.0) if lighting is None else (*lighting.fade, 1.0, 0.0),
        "labels": (float(categorical(tf, mode)), 0.0, 0.0, 0.0),
    })
    if depth_in is not None:
        depth_in = np.ascontiguousarray(np.flipud(np.minimum(depth_in, BACKGROUND_DEPTH)),
                                        dtype=np.float32)
    return GPUFrame(vevm, g, rays, axial_origin, uniforms, depth_in, mode, lighting is not None,
                    factor)


def _pixel_rays(camera, grid_to_world, shape):
    """The affine maps from a pixel's NDC ``(x, y, 1)`` to its ray in index space, ``(2, 3,
    3)``: origin (at the axial depth of the grid's centre) and direction (one Blender unit of
    axial depth), and that axial depth."""
    xmin, xmax, ymin, ymax = camera.viewplane
    # Camera-space view-plane point of NDC (x, y): (hx·x + cx, hy·y + cy).
    plane = np.array([[0.5 * (xmax - xmin), 0.0, 0.5 * (xmax + xmin)],
                      [0.0, 0.5 * (ymax - ymin), 0.5 * (ymax + ymin)],
                      [0.0, 0.0, 0.0]])
    axes = camera.matrix_world[:3, :3]
    forward = np.zeros((3, 3))
    forward[:, 2] = camera.forward
    if camera.is_ortho:  # origin on the camera plane, one direction
        origin = axes @ plane
        origin[:, 2] += camera.position
        direction = forward
    else:  # origin at the camera, direction through the plane at unit distance
        plane[2, 2] = -1.0
        origin = np.zeros((3, 3))
        origin[:, 2] = camera.position
        direction = axes @ plane
    centre = grid_to_world[:3, :3] @ ((np.asarray(shape, dtype=np.float64) - 1) / 2.0)
    axial_origin = float(camera.axial_depth(centre + grid_to_world[:3, 3]))
    to_index = np.linalg.inv(grid_to_world)
    origin = to_index[:3, :3] @ (origin + axial_origin * direction)
    origin[:, 2] += to_index[:3, 3]  # the constant column is a point, the others directions
    return np.stack([origin, to_index[:3, :3] @ direction]), axial_origin


def _mat4(m3):
    """A 3x3 matrix in the upper left of a 4x4 of zeros (a ``mat4`` uniform applied to
    ``vec4(x, y, 1, 0)``)."""
    m = np.zeros((4, 4))
    m[:3, :3] = m3
    return m


def gpu_shader_source(name):
    """The GLSL text of one of the GPU method's shaders, kept as files in ``shaders/`` beside
    this module (data for the Blender side, which compiles them; the core never does).

    Parameters
    ----------
    name : str
        The file's name: ``"dvr.vert.glsl"``, ``"dvr.frag.glsl"`` or ``"stretch.frag.glsl"``.

    Returns
    -------
    str
        The shader's source.

    Raises
    ------
    VolumeEVMError
        If ``name`` is not one of the shaders.
    """
    folder = Path(__file__).resolve().parent / "shaders"
    names = sorted(path.name for path in folder.glob("*.glsl"))
    if name not in names:
        raise VolumeEVMError(f"name: no shader {name!r}; the shaders are {', '.join(names)}")
    return (folder / name).read_text(encoding="utf-8")


GPU_METHOD = Method(
    name="gpu", label="GPU",
    description="Ray casting on the graphics card through Blender's gpu module (the CPU ray "
                "caster where no GPU context can be made)",
    render=None,  # drawn on the Blender side (blender/gpu_draw.py) from gpu_frame's arrays
    options=keyword_options(gpu_frame, besides=("matrix_world", "level", "display")),
    memory=None,  # each array is checked as it is made (gpu_region, gpu_gradients)
    tables_to_build=one_set, check_samples=step_samples(RAY_STEPS_PER_VOXEL),
    quality=step_quality(RAY_STEPS_PER_VOXEL), gpu=True, fallback="raycast", categorical=True)
"""The GPU ray marcher: its options are :func:`gpu_frame`'s, its quality the ray caster's."""
