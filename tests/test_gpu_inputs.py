"""The GPU method's NumPy half (no GPU needed): the NDC-to-index matrix against the camera's own
rays, viewport matrices as a camera, window and axial depth, the region texture against the
reference's sampler, occupancy that never hides a contributing sample, the transfer-function
table and the uniform buffer's std140 layout."""

import re

import numpy as np
import pytest

from render_helpers import camera, const_tf
from volumeevm_addon import (
    BACKGROUND_DEPTH,
    EVM,
    GPU_UNIFORMS_GLSL,
    Camera,
    TransferFunction,
    VolumeEVM,
    VolumeEVMError,
    axial_from_window,
    camera_from_viewport,
    gpu_frame,
    gpu_gradients,
    gpu_occupancy,
    gpu_region,
    gpu_transfer_table,
    grid_to_world,
    phantoms,
    window_from_axial,
)
from volumeevm_addon.rendering._gpu_inputs import _FIELDS, GPU_BLOCK, GPU_TABLE_ROWS
from volumeevm_addon.rendering._rays import camera_rays
from volumeevm_addon.rendering._reference import _Sampler


def scene(seed=3, shape=(13, 11, 9), spacing=(0.8, 1.0, 1.3)):
    """Random densities in an irregular region, placed by a rotation and a translation."""
    rng = np.random.default_rng(seed)
    dens = rng.uniform(-200.0, 900.0, shape)
    mask = rng.uniform(size=shape) < 0.55
    v = VolumeEVM(EVM.from_mask(mask), dens[mask], shape=shape, spacing=spacing)
    angle = 0.4
    placement = np.eye(4)
    placement[:2, :2] = [[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]]
    placement[:3, 3] = (0.2, -0.1, 0.05)
    return v, placement, dens, mask


def pixel_ndc(cam):
    """NDC ``(x, y)`` of every pixel centre, row 0 at the top, flat."""
    h, w = cam.shape
    x = 2 * (np.arange(w) + 0.5) / w - 1
    y = 1 - 2 * (np.arange(h) + 0.5) / h
    return np.stack(np.broadcast_arrays(x[None, :], y[:, None]), -1).reshape(-1, 2)


CAMERAS = {
    "ortho": dict(kind="ORTHO", shift_x=0.1, pixel_aspect_y=1.2),
    "persp": dict(kind="PERSP", shift_y=-0.05, sensor_fit="VERTICAL"),
}


def view_camera(name, v, g):
    kw = dict(CAMERAS[name])
    return camera(kw.pop("kind"), g, v, (0.012, -0.02, 0.009), 0.03, res=(9, 7),
                  clip_end=5.0, **kw)


# ---------------------------------------------------------------------------- view
def pixel_rays(rays, ndc, dtype=np.float64):
    """Origins and directions of the rays of NDC points ``(m, 2)`` through the frame's maps."""
    h = np.concatenate([ndc, np.ones((len(ndc), 1))], 1).astype(dtype)
    return h @ rays[0].astype(dtype).T, h @ rays[1].astype(dtype).T


@pytest.mark.parametrize("name", sorted(CAMERAS))
def test_pixel_rays_are_the_camera_rays(name):
    """Each pixel's ray is the camera's ray in index space, its parameter the axial depth less
    that of the grid's centre; the uniforms hold the maps (column-major mat4s)."""
    v, placement, _, _ = scene()
    g = grid_to_world(v.spacing, v.origin, matrix_world=placement)
    cam = view_camera(name, v, g)
    frame = gpu_frame(v, cam, const_tf(0.3), matrix_world=placement)
    np.testing.assert_allclose(frame.grid_to_world, g)
    centre = g[:3, :3] @ ((np.array(v.shape) - 1) / 2) + g[:3, 3]
    assert frame.axial_origin == pytest.approx(cam.axial_depth(centre))
    rays = camera_rays(cam, g, v.shape, None)
    o, d = pixel_rays(frame.rays, pixel_ndc(cam))
    for axial in (cam.clip_start, 0.05, 0.2):
        t_camera = (axial - rays.a0) / rays.kz
        np.testing.assert_allclose(o + (axial - frame.axial_origin) * d,
                                   rays.o + t_camera[:, None] * rays.d, atol=1e-9)
    u = frame.uniforms
    for m, rays_map in ((field(u, "ray_origin"), frame.rays[0]),
                        (field(u, "ray_direction"), frame.rays[1])):
        m = m.reshape(4, 4).T
        np.testing.assert_allclose(m[:3, :3], rays_map, rtol=1e-6, atol=1e-6)
        assert not m[3].any() and not m[:, 3].any()
    np.testing.assert_allclose(field(u, "clip")[:3], (cam.clip_start - frame.axial_origin,
                                                      cam.clip_end - frame.axial_origin,
                                                      frame.axial_origin), rtol=1e-6)


@pytest.mark.parametrize("name", sorted(CAMERAS))
def test_float32_rays_stay_within_1e5_voxel(name):
    """What the shader computes in float32 from the uniforms, far from the camera and with
    Blender's clip range: the samples in the volume within 1e-5 voxel of the float64 rays."""
    v, placement, _, _ = scene()
    g = grid_to_world(v.spacing, v.origin, matrix_world=placement)
    cam = camera("ORTHO" if name == "ortho" else "PERSP", g, v, (1.2, -2.0, 0.9), 0.03,
                 res=(9, 7), clip_end=100.0, lens_mm=4000.0)
    frame = gpu_frame(v, cam, const_tf(0.3), matrix_world=placement)
    u = frame.uniforms
    maps = np.stack([field(u, "ray_origin").reshape(4, 4).T[:3, :3],
                     field(u, "ray_direction").reshape(4, 4).T[:3, :3]])
    ndc = pixel_ndc(cam)
    o32, d32 = pixel_rays(maps, ndc, np.float32)
    o, d = pixel_rays(frame.rays, ndc)
    t = np.linspace(-0.01, 0.01, 11, dtype=np.float32)  # +-10 mm about the centre's depth
    p32 = o32[:, None] + t[None, :, None] * d32[:, None]
    p = o[:, None] + t.astype(np.float64)[None, :, None] * d[:, None]
    assert np.abs(p).max() < 40
    np.testing.assert_allclose(p32, p, atol=1e-5)


@pytest.mark.parametrize("kind", ["ORTHO", "PERSP"])
@pytest.mark.parametrize("fit", ["HORIZONTAL", "VERTICAL", "AUTO"])
def test_viewport_matrices_make_the_same_camera(kind, fit):
    """A camera's own projection and view matrices give back its projection and its rays."""
    base = Camera.look_at((0.3, -0.6, 0.4), (0.0, 0.1, 0.0), kind=kind, ortho_scale=0.7,
                          lens_mm=28.0, sensor_fit=fit, shift_x=0.12, shift_y=-0.07,
                          clip_start=0.05, clip_end=20.0, resolution_x=12, resolution_y=9,
                          pixel_aspect_x=1.0, pixel_aspect_y=1.3)
    view = camera_from_viewport(base.matrix_projection(), np.linalg.inv(base.matrix_world), 12, 9)
    assert view.projection == kind and view.shape == base.shape
    np.testing.assert_allclose(view.matrix_projection(), base.matrix_projection(), atol=1e-12)
    np.testing.assert_allclose(view.matrix_world, base.matrix_world, atol=1e-12)
    for a, b in zip(view.rays(), base.rays()):
        np.testing.assert_allclose(a, b, atol=1e-12)
    assert (view.clip_start, view.clip_end) == pytest.approx((0.05, 20.0))


def test_orthographic_viewport_clipping_behind_the_eye():
    """Blender's orthographic viewport clips from behind its eye: the camera moves back to the
    near plane, and window depths mean the same world points through both."""
    base = Camera.look_at((0.0, -2.0, 0.0), (0.0, 0.0, 0.0), ortho_scale=3.0, clip_start=0.0,
                          clip_end=10.0, resolution_x=8, resolution_y=8)
    p = base.matrix_projection()
    near, far = -10.0, 10.0  # Blender: -clip_end .. clip_end
    p[2, 2], p[2, 3] = -2.0 / (far - near), -(far + near) / (far - near)
    view = camera_from_viewport(p, np.linalg.inv(base.matrix_world), 8, 8)
    assert view.clip_start == 0.0 and view.clip_end == pytest.approx(20.0)
    np.testing.assert_allclose(view.position, base.position - 10.0 * base.forward)
    np.testing.assert_allclose(view.matrix_projection()[:2], p[:2], atol=1e-12)
    for w in (0.0, 0.25, 0.5, 0.9):
        eye_z = ((2 * w - 1) - p[2, 3]) / p[2, 2]  # the eye-space z at that window depth
        world = base.position + (-eye_z) * base.forward
        assert view.axial_depth(world) == pytest.approx(axial_from_window(w, view))
        assert window_from_axial(view.axial_depth(world), view) == pytest.approx(w)


@pytest.mark.parametrize("kind", ["ORTHO", "PERSP"])
def test_window_and_axial_depth(kind):
    cam = Camera.look_at((0.0, 0.0, 1.0), (0.0, 0.0, 0.0), kind=kind, ortho_scale=2.0,
                         clip_start=0.05, clip_end=30.0, resolution_x=4, resolution_y=4)
    axial = np.array([0.05, 0.07, 0.3, 1.0, 7.5, 30.0])
    window = window_from_axial(axial, cam)
    # Through the projection matrix: a point at that axial depth on the view axis.
    eye = np.stack([np.zeros(6), np.zeros(6), -axial, np.ones(6)], 1) @ cam.matrix_projection().T
    np.testing.assert_allclose(window, 0.5 * (eye[:, 2] / eye[:, 3] + 1), atol=1e-12)
    assert window[0] == pytest.approx(0.0) and window[-1] == pytest.approx(1.0)
    np.testing.assert_allclose(axial_from_window(window[:-1], cam), axial[:-1], rtol=1e-9)
    assert axial_from_window(1.0, cam) == BACKGROUND_DEPTH
    assert window_from_axial(BACKGROUND_DEPTH, cam) == 1.0
    assert window_from_axial(0.0, cam) == 0.0
    with pytest.raises(VolumeEVMError, match="window_depth"):
        axial_from_window([0.5, 1.5], cam)
    with pytest.raises(VolumeEVMError, match="window_depth"):
        axial_from_window([np.nan], cam)
    with pytest.raises(VolumeEVMError, match="axial_depth"):
        window_from_axial([np.nan], cam)


def test_viewport_matrices_checked():
    cam = Camera.perspective(np.eye(4), 50.0, resolution_x=4, resolution_y=4)
    p = cam.matrix_projection()
    with pytest.raises(VolumeEVMError, match="projection"):
        camera_from_viewport(np.eye(3), np.eye(4), 4, 4)
    bad = p.copy()
    bad[3] = (0, 0, 1, 1)
    with pytest.raises(VolumeEVMError, match="projection"):
        camera_from_viewport(bad, np.eye(4), 4, 4)
    with pytest.raises(VolumeEVMError, match="view_matrix"):
        camera_from_viewport(p, np.zeros((4, 4)), 4, 4)
    with pytest.raises(VolumeEVMError, match="width"):
        camera_from_viewport(p, np.eye(4), 0, 4)


# ---------------------------------------------------------------------------- volume and tf
def trilinear_clamped(tex, p):
    """What a GPU's linear filter with clamp-to-edge returns at index-space points ``p``
    (m, 3) of a ``(Z, Y, X, C)`` texture (float64 weights)."""
    n = np.array(tex.shape[2::-1])
    lo = np.floor(p)
    f = p - lo
    out = 0.0
    for corner in np.ndindex(2, 2, 2):
        c = np.asarray(corner)
        idx = np.clip(lo + c, 0, n - 1).astype(int)
        w = np.prod(np.where(c == 1, f, 1 - f), axis=1)
        out = out + w[:, None] * tex[idx[:, 2], idx[:, 1], idx[:, 0]]
    return out


def test_region_texture_is_the_clamp_policy():
    """Layout ``[z, y, x]``, and the filtered ratio equals the reference's renormalised
    interpolation wherever the sample's cell is in the region."""
    v, _, dens, mask = scene()
    tex = gpu_region(v)
    assert tex.dtype == np.float32 and tex.flags.c_contiguous
    assert tex.shape == v.shape[::-1] + (2,)
    np.testing.assert_array_equal(tex[..., 1].transpose(2, 1, 0), mask)
    np.testing.assert_allclose(tex[..., 0].transpose(2, 1, 0), np.where(mask, dens, 0),
                               rtol=1e-7)
    rng = np.random.default_rng(1)
    p = rng.uniform(-0.5, np.array(v.shape) - 0.5, (4000, 3))
    fetched = trilinear_clamped(tex.astype(np.float64), p)
    cell = np.clip(np.floor(p + 0.5), 0, np.array(v.shape) - 1).astype(int)
    inside_gpu = tex[cell[:, 2], cell[:, 1], cell[:, 0], 1] > 0.5
    inside, value, _ = _Sampler(np.where(mask, dens, 0), mask, mask, False)(p)
    np.testing.assert_array_equal(inside_gpu, inside)
    assert inside.sum() > 1500
    np.testing.assert_allclose(fetched[inside, 0] / fetched[inside, 1], value[inside],
                               rtol=1e-5, atol=1e-3)


def test_gradient_texture_is_the_reference_gradient():
    """Layout ``[z, y, x]`` with x, y, z gradients in RGB: the filtered texture over the region
    texture's weight is the reference's interpolated gradient (the 3x3x3 Sobel over region
    voxels) wherever the sample's cell is in the region."""
    v, _, dens, mask = scene()
    tex = gpu_gradients(v)
    assert tex.dtype == np.float32 and tex.flags.c_contiguous
    assert tex.shape == v.shape[::-1] + (4,) and not tex[..., 3].any()
    rng = np.random.default_rng(2)
    p = rng.uniform(-0.5, np.array(v.shape) - 0.5, (4000, 3))
    weight = trilinear_clamped(gpu_region(v).astype(np.float64), p)[:, 1]
    fetched = trilinear_clamped(tex.astype(np.float64), p)[:, :3]
    inside, _, grad = _Sampler(np.where(mask, dens, 0), mask, mask, True)(p)
    assert inside.sum() > 1500
    np.testing.assert_allclose(fetched[inside] / weight[inside, None], grad[inside],
                               rtol=1e-5, atol=1e-3)


def test_transfer_table_is_the_straight_table():
    tf = TransferFunction.preset("ct_bone")
    table, lo, hi = gpu_transfer_table(tf)
    assert (lo, hi) == tf.value_range
    assert table.shape == (GPU_TABLE_ROWS, 4) and table.dtype == np.float32
    np.testing.assert_allclose(table, tf.straight_table(lo=lo, hi=hi, n=GPU_TABLE_ROWS),
                               atol=1e-7)
    # Linear interpolation in the table (the shader's) is within a row of the function.
    values = np.random.default_rng(0).uniform(-1500, 3500, 2000)
    x = np.clip((values - lo) * (GPU_TABLE_ROWS - 1) / (hi - lo), 0, GPU_TABLE_ROWS - 1)
    i = np.minimum(x.astype(int), GPU_TABLE_ROWS - 2)
    lerp = table[i] + (x - i)[:, None] * (table[i + 1] - table[i])
    np.testing.assert_allclose(lerp, tf.evaluate(values), atol=1e-6)
    single = TransferFunction([(5.0, 1, 1, 1, 0.5)])
    assert gpu_transfer_table(single)[1:] == (5.0, 6.0)
    assert not gpu_transfer_table(None)[0].any()
    with pytest.raises(VolumeEVMError, match="tf"):
        gpu_transfer_table("ct_bone")


@pytest.mark.parametrize("mode", ["over", "xray", "mip"])
def test_empty_space_never_hides_a_contributing_sample(mode):
    """A sample whose cell lies in an empty block is outside the region or classified
    transparent (through the table's interpolation, which the shader uses); an empty block's
    value is its Chebyshev distance to the nearest block that is not."""
    shape = (40, 36, 30)
    vol = phantoms.gaussian_blobs(shape, [(12, 12, 10), (28, 22, 20)], [5.0, 4.0], [900, 600])
    v = VolumeEVM.from_volume(vol, 150)
    tf = TransferFunction([(0, 1, 1, 1, 0.0), (250, 1, 1, 1, 0.0), (350, 1, 0.5, 0, 0.4),
                           (2000, 1, 1, 1, 0.9)])
    kw = {"xray_scale": 1e-3, "xray_offset": 300.0} if mode == "xray" else {}
    occ = gpu_occupancy(v, None if mode == "xray" else tf, mode=mode, **kw)
    nb = -(-np.array(shape) // GPU_BLOCK)
    assert occ.shape == tuple(nb[::-1]) and occ.dtype == np.float32
    visible = occ == 0
    assert 0 < visible.sum() < occ.size
    blocks = np.argwhere(visible)
    for b in np.argwhere(~visible):
        assert occ[tuple(b)] == np.abs(blocks - b).max(axis=1).min()
    tex = gpu_region(v).astype(np.float64)
    p = np.random.default_rng(2).uniform(-0.5, np.array(shape) - 0.5, (60000, 3))
    cell = np.clip(np.floor(p + 0.5), 0, np.array(shape) - 1).astype(int)
    block = cell // GPU_BLOCK
    hidden = occ[block[:, 2], block[:, 1], block[:, 0]] > 0
    inside = tex[cell[:, 2], cell[:, 1], cell[:, 0], 1] > 0.5
    fetched = trilinear_clamped(tex, p)
    value = fetched[:, 0] / np.where(fetched[:, 1] > 0, fetched[:, 1], 1)
    if mode == "over":
        table, lo, hi = gpu_transfer_table(tf)
        x = np.clip((value - lo) * (GPU_TABLE_ROWS - 1) / (hi - lo), 0, GPU_TABLE_ROWS - 1)
        i = np.minimum(x.astype(int), GPU_TABLE_ROWS - 2)
        alpha = table[i, 3] + (x - i) * (table[i + 1, 3] - table[i, 3])
        contributes = inside & (alpha > 0)
    elif mode == "xray":
        contributes = inside & (value > 300.0)
    else:
        contributes = inside
    assert contributes.sum() > 1000 and hidden.sum() > 1000
    assert not (hidden & contributes).any()


def test_occupancy_of_an_empty_region():
    v = VolumeEVM(EVM.from_mask(np.zeros((9, 9, 9), bool)), np.zeros(0), shape=(9, 9, 9))
    occ = gpu_occupancy(v, const_tf(0.5))
    assert occ.shape == (2, 2, 2) and (occ == 2).all()  # no block to reach: the whole grid
    assert not gpu_region(v).any()


# ---------------------------------------------------------------------------- uniforms
def field(uniforms, name):
    """The floats of one field of the packed uniforms."""
    offset = 0
    for field_name, kind, _ in _FIELDS:
        size = 16 if kind == "mat4" else 4
        if field_name == name:
            return uniforms[offset:offset + size]
        offset += size
    raise KeyError(name)


def test_uniform_block_layout():
    """The GLSL struct declares the packed fields in order, each a vec4 or a mat4 (std140 with
    no padding), and the packed values are the frame's settings."""
    declared = re.findall(r"^\s+(vec4|mat4) (\w+);", GPU_UNIFORMS_GLSL, re.M)
    assert declared == [(kind, name) for name, kind, _ in _FIELDS]
    for name, code in (("OVER", 0), ("XRAY", 1), ("MIP", 2)):
        assert f"const int MODE_{name} = {code};" in GPU_UNIFORMS_GLSL
    constants = dict(re.findall(r"const float (\w+) = (\S+);", GPU_UNIFORMS_GLSL))
    assert float(constants["VISIBLE_ALPHA"]) == 2.0 ** -16
    assert float(constants["VISIBLE_OPTICAL_DEPTH"]) == np.float32(-np.log1p(-2.0 ** -16))
    assert float(constants["BACKGROUND_DEPTH"]) == BACKGROUND_DEPTH
    vol = phantoms.box((20, 18, 10), lo=(2, 2, 2), hi=(15, 16, 8), density=300.0,
                       spacing=(0.5, 0.6, 1.5))
    v = VolumeEVM.from_volume(vol, 100)
    g = grid_to_world(v.spacing, v.origin)
    cam = camera("PERSP", g, v, (0.02, -0.03, 0.01), 0.0, res=(6, 5))
    tf = TransferFunction([(-100, 1, 1, 1, 0.0), (700, 1, 1, 1, 0.6)], unit_length_mm=2.0)
    depth_in = np.full(cam.shape, 0.04)
    depth_in[0, 0] = 7.0
    frame = gpu_frame(v, cam, tf, mode="mip", depth_in=depth_in, step_mm=0.2,
                      termination=0.9, skip_empty=False)
    u = frame.uniforms
    assert u.dtype == np.float32 and u.size == sum(16 if k == "mat4" else 4 for _, k, _ in _FIELDS)
    fields = {name: field(u, name) for name, _, _ in _FIELDS}
    np.testing.assert_array_equal(fields["grid"], (20, 18, 10, GPU_BLOCK))
    np.testing.assert_array_equal(fields["blocks"], (3, 3, 2, 0))
    np.testing.assert_allclose(fields["spacing"], (0.5, 0.6, 1.5, 0.2), rtol=1e-7)
    np.testing.assert_allclose(fields["compositing"], (2, 1.0, 1.0, 0.0), rtol=1e-7)
    np.testing.assert_allclose(fields["table"], (-100, 4095 / 800, 4096, 2.0), rtol=1e-7)
    np.testing.assert_array_equal(fields["image"], (6, 5, 1, 0))
    # depth_in goes bottom row first, float32.
    assert frame.depth_in.dtype == np.float32 and frame.depth_in[-1, 0] == 7.0
    over = field(gpu_frame(v, cam, tf, termination=0.9).uniforms, "compositing")
    assert over[0] == 0 and over[1] == np.float32(0.9)
    under = field(gpu_frame(v, cam, tf, mode="under", termination=0.9).uniforms, "compositing")
    assert tuple(under[:2]) == (0, 1)
    xray = field(gpu_frame(v, cam, None, mode="xray", xray_scale=0.5, xray_offset=-10.0).uniforms,
                 "compositing")
    np.testing.assert_array_equal(xray, (1, 1, 0.5, -10))
    assert gpu_frame(v, cam, tf).depth_in is None


def test_frame_level_and_default_step():
    """``level`` picks the VolumeEVM rendered, as ``render`` does; the default step is half the
    smallest voxel of that level, a given step is scaled by its factor."""
    vol = phantoms.box((64, 64, 64), lo=(8, 8, 8), hi=(56, 56, 56), density=1.0)
    v = VolumeEVM.from_volume(vol, 0.5)
    g = grid_to_world(v.spacing, v.origin)
    cam = camera("ORTHO", g, v, (0.0, -1.0, 0.0), 0.08, res=(16, 16))
    frame = gpu_frame(v, cam, const_tf(0.3), level="auto")
    assert frame.vevm.shape == (16, 16, 16) and frame.level == 4
    assert field(frame.uniforms, "spacing")[3] == 2.0  # half of a 4 mm voxel
    assert field(gpu_frame(v, cam, const_tf(0.3), level=2, step_mm=0.25).uniforms,
                 "spacing")[3] == 0.5
    assert gpu_frame(v, cam, const_tf(0.3)).vevm is v
    assert gpu_frame(v, cam, const_tf(0.3)).level == 1


def test_frame_checks_its_settings():
    v, _, _, _ = scene()
    g = grid_to_world(v.spacing, v.origin)
    cam = view_camera("ortho", v, g)
    tf = const_tf(0.3)
    cases = [
        (dict(camera="cam"), "camera"),
        (dict(vevm=np.zeros((3, 3, 3))), "vevm"),
        (dict(tf=None), "tf"),
        (dict(mode="sum"), "mode"),
        (dict(step_mm=0.0), "step_mm"),
        (dict(step_mm=1e-9), "step_mm"),
        (dict(termination=0.0), "termination"),
        (dict(skip_empty=1), "skip_empty"),
        (dict(level="half"), "level"),
        (dict(matrix_world=np.zeros((3, 3))), "matrix_world"),
        (dict(depth_in=np.zeros((2, 2))), "depth_in"),
        (dict(xray_scale=-1.0, mode="xray"), "xray_scale"),
    ]
    for change, name in cases:
        args = {"vevm": v, "camera": cam, "tf": tf, **change}
        with pytest.raises(VolumeEVMError, match=name):
            gpu_frame(args.pop("vevm"), args.pop("camera"), args.pop("tf"), **args)
    with pytest.raises(VolumeEVMError, match="vevm"):
        gpu_region("volume")
    with pytest.raises(VolumeEVMError, match="mode"):
        gpu_occupancy(v, tf, mode="sum")


def test_shading_uniforms():
    """Shaded over/under frames carry the view's normal matrix, the index-to-world map, the
    Blinn-Phong weights and the fade's magnitudes; X-ray and MIP frames are not shaded."""
    v, placement, _, _ = scene()
    g = grid_to_world(v.spacing, v.origin, v.orientation, placement)
    cam = camera("PERSP", g, v, (0.02, -0.03, 0.015), 0.0)
    tf = TransferFunction([(-200, 0.1, 0.3, 0.9, 0.0), (800, 1.0, 0.6, 0.2, 0.5)])
    frame = gpu_frame(v, cam, tf, matrix_world=placement,
                      shading=dict(specular=0.5, fade_from=0.01, fade_to=0.05))
    u = frame.uniforms
    assert frame.shaded
    matrix = field(u, "normal").reshape(4, 4).T  # column-major
    np.testing.assert_allclose(matrix[:3, :3], np.linalg.inv(g)[:3, :3].T, rtol=1e-6)
    matrix = field(u, "to_world").reshape(4, 4).T
    np.testing.assert_allclose(matrix[:3, :3], g[:3, :3], rtol=1e-6)
    np.testing.assert_allclose(field(u, "shading"), (0.3, 0.7, 0.5, 20.0))
    np.testing.assert_allclose(field(u, "fade"), (10.0, 50.0, 1.0, 0.0), rtol=1e-6)
    for mode, shading in (("over", None), ("mip", True)):
        frame = gpu_frame(v, cam, tf, mode=mode, matrix_world=placement, shading=shading)
        assert not frame.shaded and not field(frame.uniforms, "fade").any()
