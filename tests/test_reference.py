"""Reference ray caster against closed forms, its own modes against each other, the boundary
policy, depth clipping and degenerate input."""

import json

import numpy as np
import pytest

from volumeevm_addon import (
    BACKGROUND_DEPTH,
    BLENDER_UNITS_PER_MM,
    Camera,
    Shading,
    TransferFunction,
    VolumeEVMError,
    index_to_physical,
)
from volumeevm_addon.rendering._reference import render_reference

BU = BLENDER_UNITS_PER_MM


def rotation(axis, angle):
    axis = np.asarray(axis, dtype=np.float64)
    axis /= np.linalg.norm(axis)
    x, y, z = axis
    c, s = np.cos(angle), np.sin(angle)
    return np.array([
        [c + x * x * (1 - c), x * y * (1 - c) - z * s, x * z * (1 - c) + y * s],
        [y * x * (1 - c) + z * s, c + y * y * (1 - c), y * z * (1 - c) - x * s],
        [z * x * (1 - c) - y * s, z * y * (1 - c) + x * s, c + z * z * (1 - c)],
    ])


def grid_matrix(spacing, origin=(0.0, 0.0, 0.0), rot=None, obj_translation=(0.0, 0.0, 0.0)):
    """index -> world: the object's matrix (rotation, translation) after mm -> BU scaling."""
    obj = np.eye(4)
    if rot is not None:
        obj[:3, :3] = rot
    obj[:3, 3] = obj_translation
    scale = np.diag([BU, BU, BU, 1.0])
    return obj @ scale @ index_to_physical(spacing, origin)


def constant_tf(alpha=0.2, rgb=(0.9, 0.6, 0.3), unit=1.0):
    return TransferFunction([(-1e6, *rgb, alpha), (1e6, *rgb, alpha)], unit_length_mm=unit)


def box_chords_mm(grid_to_world, shape, origins, directions, t_lo=None, t_hi=None):
    """Chord (mm) of each world ray with the volume's box, from the box's six world-space face
    planes (independent of the renderer's index-space slab test)."""
    a = grid_to_world[:3, :3]
    corner_lo = grid_to_world[:3, 3] + a @ np.full(3, -0.5)
    corner_hi = grid_to_world[:3, 3] + a @ (np.asarray(shape) - 0.5)
    tin = np.full(len(origins), -np.inf)
    tout = np.full(len(origins), np.inf)
    for ax in range(3):
        normal = np.cross(a[:, (ax + 1) % 3], a[:, (ax + 2) % 3])
        lo, hi = normal @ corner_lo, normal @ corner_hi
        lo, hi = min(lo, hi), max(lo, hi)
        po, pd = origins @ normal, directions @ normal
        with np.errstate(divide="ignore"):
            ta, tb = (lo - po) / pd, (hi - po) / pd
        tin = np.maximum(tin, np.minimum(ta, tb))
        tout = np.minimum(tout, np.maximum(ta, tb))
    if t_lo is not None:
        tin = np.maximum(tin, t_lo)
    if t_hi is not None:
        tout = np.minimum(tout, t_hi)
    chord_world = np.maximum(tout - tin, 0.0)
    mm_per_world = 1.0 / BU  # grid_to_world scales mm by BU and rotates only
    return chord_world * mm_per_world


# ---------------------------------------------------------------------------- closed forms
def test_homogeneous_box_orthographic_along_axis():
    shape, sp = (7, 9, 5), (0.7, 0.5, 1.3)
    g = grid_matrix(sp, origin=(1.0, -2.0, 0.5))
    tf = constant_tf(alpha=0.15)
    cam_m = np.eye(4)
    cam_m[:3, 3] = (g[:3, 3] + g[:3, :3] @ np.array([3.0, 4.0, 0.0]))[:2].tolist() + [1.0]
    cam = Camera.orthographic(cam_m, 0.008, resolution_x=40, resolution_y=32)
    rgba, depth = render_reference(np.full(shape, 5.0), None, g, sp, cam, tf, step_mm=0.4)
    o, d = cam.rays()
    chord = box_chords_mm(g, shape, o.reshape(-1, 3), d.reshape(-1, 3)).reshape(cam.shape)
    expected = 1.0 - (1.0 - 0.15) ** chord
    assert (chord > 0).sum() > 200 and (chord == 0).sum() > 100
    np.testing.assert_allclose(chord[chord > 0], 5 * 1.3, rtol=1e-12)
    np.testing.assert_allclose(rgba[..., 3], expected, rtol=0, atol=1e-6)
    np.testing.assert_allclose(rgba[..., :3], expected[..., None] * (0.9, 0.6, 0.3), atol=1e-6)
    # Depth: the box's top face (cell boundary), axial from the camera at z = 1.
    top = 1.0 - (0.5 + 4.5 * 1.3) * BU
    np.testing.assert_allclose(depth[chord > 0], top, rtol=1e-6)
    assert np.all(depth[chord == 0] == BACKGROUND_DEPTH)


@pytest.mark.parametrize("kind", ["ORTHO", "PERSP"])
def test_homogeneous_box_oblique(kind):
    shape, sp = (6, 8, 5), (1.0, 0.6, 1.4)
    g = grid_matrix(sp, origin=(-3.0, -2.0, -3.5), rot=rotation((1, 2, 3), 0.7),
                    obj_translation=(0.01, 0.0, 0.02))
    centre = g[:3, 3] + g[:3, :3] @ ((np.array(shape) - 1) / 2)
    cam_m = Camera.look_at(centre + (0.02, -0.025, 0.015), centre).matrix_world
    if kind == "ORTHO":
        cam = Camera.orthographic(cam_m, 0.016, resolution_x=36, resolution_y=30, shift_x=0.05,
                                  clip_start=0.001)
    else:
        cam = Camera.perspective(cam_m, 120.0, resolution_x=36, resolution_y=30, shift_y=-0.04,
                                 pixel_aspect_x=1.2, clip_start=0.001)
    tf = constant_tf(alpha=0.1)
    rgba, depth = render_reference(np.full(shape, 1.0), np.ones(shape, bool), g, sp, cam, tf,
                                   step_mm=0.5)
    o, d = cam.rays()
    chord = box_chords_mm(g, shape, o.reshape(-1, 3), d.reshape(-1, 3)).reshape(cam.shape)
    assert (chord > 0).sum() > 200 and (chord == 0).sum() > 50
    expected = 1.0 - 0.9 ** chord
    assert np.abs(rgba[..., 3] - expected).max() < 1e-6  # the contract asks < 1e-3


def test_opacity_reference_length_and_anisotropy():
    """alpha is per unit_length_mm; lengths are physical mm whatever the index spacing."""
    shape = (4, 4, 8)
    cam_m = np.eye(4)
    cam_m[:3, 3] = (1.5 * BU, 1.5 * BU, 1.0)
    for sp, unit in (((1.0, 1.0, 1.0), 1.0), ((1.0, 1.0, 2.5), 1.0), ((1.0, 1.0, 2.5), 4.0)):
        g = grid_matrix(sp)
        cam = Camera.orthographic(cam_m, 1.0 * BU, resolution_x=4, resolution_y=4)
        rgba, _ = render_reference(np.zeros(shape), None, g, sp, cam, constant_tf(0.3, unit=unit))
        np.testing.assert_allclose(rgba[..., 3], 1 - 0.7 ** (8 * sp[2] / unit), rtol=1e-6)


def _gaussian_xray_error(refine):
    """X-ray of a Gaussian blob (anisotropic voxels, rotated grid, oblique view) minus the
    closed-form line integral ``A·σ·√π·exp(-b²/σ²)`` of ``A·exp(-r²/σ²)``."""
    sp = np.array([0.8, 1.0, 1.25]) / refine
    shape = tuple(np.array((41, 33, 27)) * refine - (refine - 1))
    sigma, amp, scale = 4.0, 2.0, 0.06  # sigma in mm; optical depth at the centre 0.85
    centre_idx = (np.array(shape) - 1) / 2
    idx = np.stack(np.meshgrid(*[np.arange(n) for n in shape], indexing="ij"), axis=-1)
    r2 = (((idx - centre_idx) * sp) ** 2).sum(axis=-1)
    dens = amp * np.exp(-r2 / sigma**2)
    g = grid_matrix(sp, rot=rotation((0.2, 1.0, 0.4), 0.5))
    centre = g[:3, 3] + g[:3, :3] @ centre_idx
    cam = Camera.look_at(centre + np.array([0.3, -1.0, 0.6]) * 0.03, centre, ortho_scale=0.018,
                         resolution_x=32, resolution_y=32, clip_start=0.001)
    rgba, _ = render_reference(dens, None, g, sp, cam, None, mode="xray",
                               step_mm=0.1 / refine, xray_scale=scale)
    o, d = cam.rays()
    o, d = o.reshape(-1, 3), d.reshape(-1, 3)
    rel = centre - o
    b = np.linalg.norm(rel - (rel @ d[0])[:, None] * d, axis=1) / BU  # impact parameter, mm
    tau = scale * amp * sigma * np.sqrt(np.pi) * np.exp(-(b**2) / sigma**2)
    expected = (1.0 - np.exp(-tau)).reshape(cam.shape)
    # grey output
    np.testing.assert_array_equal(rgba[..., 0], rgba[..., 3])
    np.testing.assert_array_equal(rgba[..., 2], rgba[..., 3])
    assert expected.max() > 0.5
    return rgba[..., 3] - expected


def test_gaussian_blob_xray_against_line_integral():
    coarse = _gaussian_xray_error(1)
    fine = _gaussian_xray_error(2)
    # What is left is the grid's trilinear reconstruction error (sigma = 3.2 .. 5 voxels),
    # measured max 7.5e-3, RMSE 2.1e-3; it is second order: halving the voxels quarters it.
    assert np.abs(coarse).max() < 1e-2 and np.sqrt((coarse**2).mean()) < 3e-3
    assert np.abs(fine).max() < 0.3 * np.abs(coarse).max()
    assert np.sqrt((fine**2).mean()) < 0.3 * np.sqrt((coarse**2).mean())


def test_xray_is_exp_of_minus_sum_along_axis():
    """Orthographic along z through voxel centres: the integral of a piecewise-linear profile
    (clamped at the ends) in closed form."""
    rng = np.random.default_rng(3)
    shape, sp = (3, 3, 6), (1.0, 1.0, 0.5)
    dens = rng.uniform(0, 4, shape)
    g = grid_matrix(sp)
    cam_m = np.eye(4)
    cam_m[:3, 3] = (1.0 * BU, 1.0 * BU, 1.0)
    cam = Camera.orthographic(cam_m, 3 * BU, resolution_x=3, resolution_y=3)
    rgba, _ = render_reference(dens, None, g, sp, cam, None, mode="xray", step_mm=0.5 / 64,
                               xray_scale=0.3, xray_offset=0.0)
    # trapezoid over the centres plus half a voxel of the end values on each side
    col = dens * sp[2]
    integral = 0.5 * (col[..., :-1] + col[..., 1:]).sum(-1) + 0.5 * (col[..., 0] + col[..., -1])
    expected = 1 - np.exp(-0.3 * integral)
    # image row 0 is +y (top): pixel (row, col) sees voxel column (x=col, y=2-row)
    np.testing.assert_allclose(rgba[..., 3], expected.T[::-1], rtol=0, atol=1e-6)


def test_mip_is_the_maximum_along_rays():
    rng = np.random.default_rng(5)
    shape, sp = (6, 5, 7), (1.0, 1.0, 0.9)
    dens = rng.uniform(-100, 300, shape)
    mask = rng.random(shape) < 0.6
    g = grid_matrix(sp)
    cam_m = np.eye(4)
    cam_m[:3, 3] = (2.5 * BU, 2.0 * BU, 1.0)
    cam = Camera.orthographic(cam_m, 6 * BU, resolution_x=6, resolution_y=5)
    tf = TransferFunction([(-100, 0, 0, 0, 0.0), (300, 1, 0.5, 0.25, 1.0)])
    # 3 samples per voxel: the middle one sits on the voxel centre
    rgba, depth = render_reference(dens, mask, g, sp, cam, tf, mode="mip", step_mm=0.3)
    colmax = np.where(mask, dens, -np.inf).max(axis=2)  # (x, y)
    seen = np.isfinite(colmax)
    st = tf.evaluate(np.where(seen, colmax, -100))
    premultiplied = np.concatenate([st[..., :3] * st[..., 3:], st[..., 3:]], -1)
    expected = np.where(seen[..., None], premultiplied, 0)
    expected = expected.transpose(1, 0, 2)[::-1]  # to image rows (top = +y) and columns (x)
    np.testing.assert_allclose(rgba, expected, rtol=0, atol=1e-6)
    # depth of the (frontmost) maximum: the centre of the voxel that holds it, or the top of
    # its cell when the field is clamped above the centre (voxel above outside the region)
    kz = np.argmax(np.where(mask, dens, -np.inf), axis=2)
    above = np.take_along_axis(np.pad(mask, ((0, 0), (0, 0), (0, 1))), kz[..., None] + 1, 2)
    zmax = np.where(above[..., 0], kz, kz + 0.5).T[::-1]
    want = 1.0 - zmax * 0.9 * BU
    has = expected[..., 3] > 0
    np.testing.assert_allclose(depth[has], want[has], rtol=1e-6)
    assert np.all(depth[~has] == BACKGROUND_DEPTH)


# ---------------------------------------------------------------------------- modes, policy
def _random_scene(seed=0, shape=(9, 8, 7), sp=(0.9, 1.1, 1.6)):
    rng = np.random.default_rng(seed)
    dens = rng.uniform(0, 100, shape)
    mask = rng.random(shape) < 0.7
    g = grid_matrix(sp, rot=rotation((1, -1, 2), 0.4))
    centre = g[:3, 3] + g[:3, :3] @ ((np.array(shape) - 1) / 2)
    cam = Camera.look_at(centre + (0.012, -0.03, 0.02), centre, kind="PERSP", lens_mm=60.0,
                         resolution_x=28, resolution_y=24, clip_start=0.001)
    tf = TransferFunction([(0, 0.1, 0.2, 0.9, 0.0), (40, 0.9, 0.3, 0.1, 0.2),
                           (100, 1.0, 1.0, 0.8, 0.6)])
    return dens, mask, g, np.array(sp), cam, tf


@pytest.mark.parametrize("kind", ["ORTHO", "PERSP"])
def test_shading_of_a_linear_ramp(kind):
    """f = 3 i - 2 k on a rotated grid with anisotropic voxels: the gradient is constant, its
    world direction is R · (3/sx, 0, -2/sz); every sample gets the same Blinn–Phong factor."""
    shape, sp = (6, 5, 7), np.array([0.6, 1.0, 1.5])
    i, j, k = np.meshgrid(*[np.arange(n) for n in shape], indexing="ij")
    dens = 3.0 * i - 2.0 * k
    rot = rotation((1, 1, 0.3), 0.6)
    g = grid_matrix(sp, rot=rot)
    centre = g[:3, 3] + g[:3, :3] @ ((np.array(shape) - 1) / 2)
    cam_m = Camera.look_at(centre + np.array([0.2, -1.0, 0.5]) * 0.03, centre).matrix_world
    cam = (Camera.orthographic(cam_m, 0.012, resolution_x=12, resolution_y=10, clip_start=1e-3)
           if kind == "ORTHO" else
           Camera.perspective(cam_m, 120.0, resolution_x=12, resolution_y=10, clip_start=1e-3))
    rgb = np.array([0.8, 0.5, 0.2])
    tf = constant_tf(alpha=0.3, rgb=tuple(rgb))
    shade = Shading(ambient=0.2, diffuse=0.6, specular=0.25, shininess=8.0, fade_to=0.0,
                    fade_from=0.0)  # no fade: every gradient lit fully
    rgba, _ = render_reference(dens, None, g, sp, cam, tf, step_mm=0.5, shading=shade)
    normal = rot @ (np.array([3.0, 0.0, -2.0]) / sp)
    normal /= np.linalg.norm(normal)
    _, d = cam.rays()
    cos = np.abs(d @ normal)
    want = np.minimum(rgb * (0.2 + 0.6 * cos[..., None]) + 0.25 * cos[..., None] ** 8, 1.0)
    seen = rgba[..., 3] > 0.1
    assert seen.sum() > 40
    np.testing.assert_allclose(rgba[seen][:, :3] / rgba[seen][:, 3:], want[seen], rtol=1e-5)
    assert np.ptp(cos[seen]) > 0.01 or kind == "ORTHO"


@pytest.mark.parametrize("shading", [None, Shading()])
def test_over_equals_under(shading):
    dens, mask, g, sp, cam, tf = _random_scene()
    a, da = render_reference(dens, mask, g, sp, cam, tf, mode="over", step_mm=0.3, shading=shading)
    b, db = render_reference(dens, mask, g, sp, cam, tf, mode="under", step_mm=0.3, shading=shading)
    assert a[..., 3].max() > 0.5
    np.testing.assert_allclose(a, b, rtol=0, atol=1e-6)
    np.testing.assert_array_equal(da, db)


@pytest.mark.parametrize("mode", ["over", "under", "xray", "mip"])
def test_skipping_empty_pieces_changes_nothing(mode, monkeypatch):
    """Pieces outside the VoI or where the transfer function is transparent are not sampled;
    sampling them anyway gives the bit-identical image."""
    from volumeevm_addon.rendering import _reference

    dens, mask, g, sp, cam, tf = _random_scene(11)
    tf = TransferFunction([(0, 0.1, 0.2, 0.9, 0.0), (50, 0.9, 0.3, 0.1, 0.0),
                           (70, 1.0, 1.0, 0.8, 0.6)])  # transparent below 50
    kw = dict(mode=mode, step_mm=0.3, shading=mode == "over", xray_offset=40.0, xray_scale=0.05)
    fast = render_reference(dens, mask, g, sp, cam, tf, **kw)
    plan = _reference._plan
    monkeypatch.setattr(_reference, "_plan",
                        lambda *a: plan(*a[:-1], lambda p: np.ones(len(p), bool)))
    slow = render_reference(dens, mask, g, sp, cam, tf, **kw)
    assert fast[0][..., 3].max() > 0.1
    np.testing.assert_array_equal(fast[0], slow[0])
    np.testing.assert_array_equal(fast[1], slow[1])


@pytest.mark.parametrize("kind", ["ORTHO", "PERSP"])
def test_symmetric_view_gives_a_mirrored_image(kind):
    rng = np.random.default_rng(12)
    shape, sp = (8, 6, 7), (0.8, 1.0, 1.2)
    dens = rng.uniform(0, 100, shape)
    dens = 0.5 * (dens + dens[::-1])  # symmetric under x -> -x about the centre
    mask = rng.random(shape) < 0.8
    mask = mask & mask[::-1]
    g = grid_matrix(sp)
    centre = g[:3, 3] + g[:3, :3] @ ((np.array(shape) - 1) / 2)
    # In the symmetry plane x = centre.
    m = Camera.look_at(centre + (0.0, -0.03, 0.01), centre).matrix_world
    cam = (Camera.orthographic(m, 0.012, resolution_x=20, resolution_y=16, clip_start=1e-3)
           if kind == "ORTHO" else
           Camera.perspective(m, 80.0, resolution_x=20, resolution_y=16, clip_start=1e-3))
    _, _, _, _, _, tf = _random_scene()
    rgba, depth = render_reference(dens, mask, g, sp, cam, tf, step_mm=0.2, shading=True)
    assert rgba[..., 3].max() > 0.3
    np.testing.assert_allclose(rgba, rgba[:, ::-1], rtol=0, atol=1e-6)
    np.testing.assert_allclose(depth, depth[:, ::-1], rtol=1e-6)


def test_step_convergence():
    """Halving the step changes the image by < 1e-4 RMSE at 1/10 voxel, and the changes shrink
    faster than linearly (masks and kinks are cut exactly, only smooth pieces are sampled)."""
    dens, mask, g, sp, cam, tf = _random_scene(1)
    a, b, c = (render_reference(dens, mask, g, sp, cam, tf, step_mm=s)[0] for s in (0.2, 0.1, 0.05))
    d1 = np.sqrt(((a - b) ** 2).mean())
    d2 = np.sqrt(((b - c) ** 2).mean())
    assert d2 < 1e-4  # measured 3.4e-5
    assert d1 > 2.5 * d2  # measured 3.5x


@pytest.mark.parametrize("mode", ["over", "xray", "mip"])
@pytest.mark.parametrize("shading", [None, True])
def test_mask_equals_cropped_volume(mode, shading):
    """Outside the region is transparent and never read: masking out x >= 4 gives the image of
    the volume cropped to x < 4, whatever the masked-out densities are."""
    dens, _, g, sp, cam, tf = _random_scene(2)
    mask = np.zeros(dens.shape, bool)
    mask[:4] = True
    noisy = dens.copy()
    noisy[4:] = np.random.default_rng(9).uniform(-1e4, 1e4, noisy[4:].shape)
    kw = dict(mode=mode, step_mm=0.25, shading=shading, xray_scale=0.01)
    a, da = render_reference(noisy, mask, g, sp, cam, tf, **kw)
    b, db = render_reference(dens[:4], None, g, sp, cam, tf, **kw)
    assert a[..., 3].max() > 0.2
    np.testing.assert_allclose(a, b, rtol=0, atol=1e-6)
    np.testing.assert_allclose(da, db, rtol=1e-6)


def test_outside_voxels_are_transparent():
    """A single voxel in the region renders as its cell only: pixels whose rays miss the cell
    see nothing, even though every other voxel is dense."""
    shape, sp = (5, 5, 5), (1.0, 1.0, 1.0)
    dens = np.full(shape, 50.0)
    mask = np.zeros(shape, bool)
    mask[2, 2, 2] = True
    g = grid_matrix(sp)
    cam_m = np.eye(4)
    cam_m[:3, 3] = (2 * BU, 2 * BU, 1.0)
    cam = Camera.orthographic(cam_m, 5 * BU, resolution_x=10, resolution_y=10)
    rgba, depth = render_reference(dens, mask, g, sp, cam, constant_tf(0.5), step_mm=0.1)
    inside = np.zeros((10, 10), bool)
    inside[4:6, 4:6] = True  # pixels whose centres fall in x, y in [1.5, 2.5]
    np.testing.assert_allclose(rgba[inside, 3], 0.5, rtol=1e-6)
    assert np.all(rgba[~inside] == 0)
    np.testing.assert_allclose(depth[inside], 1.0 - 2.5 * BU, rtol=1e-7)


# ---------------------------------------------------------------------------- depth
def test_depth_in_plane_cuts_the_box_exactly():
    shape, sp = (6, 6, 10), (1.0, 1.0, 1.0)
    g = grid_matrix(sp)
    cam_m = np.eye(4)
    cam_m[:3, 3] = (2.5 * BU, 2.5 * BU, 1.0)
    cam = Camera.orthographic(cam_m, 6 * BU, resolution_x=12, resolution_y=12)
    tf = constant_tf(0.2)
    entry = 1.0 - 9.5 * BU
    plane = np.full(cam.shape, BACKGROUND_DEPTH)
    plane[:, :6] = entry + 3.3 * BU  # geometry 3.3 mm inside the box on the left half
    plane[:2] = entry - 1 * BU  # in front of the volume on the top rows
    rgba, depth = render_reference(np.zeros(shape), None, g, sp, cam, tf, depth_in=plane)
    np.testing.assert_allclose(rgba[2:, :6, 3], 1 - 0.8**3.3, rtol=1e-6)
    np.testing.assert_allclose(rgba[2:, 6:, 3], 1 - 0.8**10, rtol=1e-6)
    assert np.all(rgba[:2] == 0) and np.all(depth[:2] == BACKGROUND_DEPTH)
    np.testing.assert_allclose(depth[2:], entry, rtol=1e-7)


def test_depth_in_hides_what_is_behind():
    dens, mask, g, sp, cam, tf = _random_scene(4)
    o, d = cam.rays()
    plane = cam.axial_depth(g[:3, 3] + g[:3, :3] @ ((np.array(dens.shape) - 1) / 2))
    depth_in = np.full(cam.shape, plane)
    a, _ = render_reference(dens, mask, g, sp, cam, tf, step_mm=0.3, depth_in=depth_in)
    # Changing every voxel whose cell lies entirely behind the plane (more than one voxel
    # diagonal behind it, so no sample in front interpolates it) changes nothing.
    idx = np.stack(np.meshgrid(*[np.arange(n) for n in dens.shape], indexing="ij"), -1)
    world = idx @ g[:3, :3].T + g[:3, 3]
    behind = cam.axial_depth(world) > plane + np.linalg.norm(g[:3, :3] @ np.ones(3)) * 1.01
    assert behind.sum() > 20
    changed = dens.copy()
    changed[behind] = 1e4
    b, _ = render_reference(changed, mask, g, sp, cam, tf, step_mm=0.3, depth_in=depth_in)
    np.testing.assert_array_equal(a, b)
    full, _ = render_reference(changed, mask, g, sp, cam, tf, step_mm=0.3)
    assert np.abs(full - b).max() > 0.05  # without the plane the change shows
    # geometry far behind the volume changes nothing either
    c, _ = render_reference(dens, mask, g, sp, cam, tf, step_mm=0.3,
                            depth_in=np.full(cam.shape, 1e10))
    d0, _ = render_reference(dens, mask, g, sp, cam, tf, step_mm=0.3)
    np.testing.assert_array_equal(c, d0)


# ---------------------------------------------------------------------------- degenerate
def test_empty_mask_and_camera_that_sees_nothing():
    dens, mask, g, sp, cam, tf = _random_scene(6)
    rgba, depth = render_reference(dens, np.zeros(dens.shape, bool), g, sp, cam, tf)
    assert rgba.shape == cam.shape + (4,) and rgba.dtype == np.float32
    assert np.all(rgba == 0) and np.all(depth == BACKGROUND_DEPTH) and depth.dtype == np.float32
    away = cam.matrix_world.copy()
    away[:3, :3] = away[:3, :3] @ rotation((0, 1, 0), np.pi)  # look the other way
    cam2 = Camera.perspective(away, 60.0, resolution_x=16, resolution_y=12, clip_start=0.001)
    for mode in ("over", "under", "xray", "mip"):
        rgba, depth = render_reference(dens, mask, g, sp, cam2, tf, mode=mode)
        assert np.all(rgba == 0) and np.all(depth == BACKGROUND_DEPTH)


def test_camera_inside_the_volume():
    shape, sp = (10, 10, 10), (1.0, 1.0, 1.0)
    g = grid_matrix(sp)
    centre = g[:3, 3] + g[:3, :3] @ np.array([4.2, 4.6, 4.4])
    cam = Camera.look_at(centre, centre + (1.0, 0.3, 0.2), kind="PERSP", lens_mm=20.0,
                         resolution_x=16, resolution_y=16, clip_start=0.5 * BU)
    rgba, depth = render_reference(np.zeros(shape), None, g, sp, cam, constant_tf(0.1),
                                   step_mm=0.5)
    o, d = cam.rays()
    o, d = o.reshape(-1, 3), d.reshape(-1, 3)
    t_near = 0.5 * BU / (d @ cam.forward)
    chord = box_chords_mm(g, shape, o, d, t_lo=t_near).reshape(cam.shape)
    np.testing.assert_allclose(rgba[..., 3], 1 - 0.9**chord, rtol=0, atol=1e-6)
    np.testing.assert_allclose(depth, 0.5 * BU, rtol=1e-6)  # everything starts at the near clip


def test_single_voxel_volume():
    g = grid_matrix((2.0, 2.0, 2.0))
    cam_m = np.eye(4)
    cam_m[:3, 3] = (0.0, 0.0, 1.0)
    cam = Camera.orthographic(cam_m, 4 * BU, resolution_x=4, resolution_y=4)
    rgba, depth = render_reference(np.ones((1, 1, 1)), None, g, (2.0, 2.0, 2.0), cam,
                                   constant_tf(0.5))
    np.testing.assert_allclose(rgba[1:3, 1:3, 3], 0.75, rtol=1e-6)
    assert rgba[0, 0, 3] == 0 and rgba[3, 3, 3] == 0


@pytest.mark.parametrize("change, match", [
    (dict(depth_in=np.full((24, 28), np.nan)), "depth_in: .*NaN"),
    (dict(depth_in=np.ones((3, 3))), "depth_in: shape"),
    (dict(densities=np.full((2, 2, 2), np.nan)), "densities: NaN"),
    (dict(densities=np.ones((2, 2))), "densities: expected"),
    (dict(mask=np.ones((2, 2, 2), bool)), "mask: shape"),
    (dict(mask=np.ones((9, 8, 7))), "mask: expected a bool"),
    (dict(grid_to_world=np.eye(3)), "grid_to_world"),
    (dict(grid_to_world=np.zeros((4, 4))), "grid_to_world"),
    (dict(spacing=(1.0, 0.0, 1.0)), "spacing"),
    (dict(camera="camera"), "camera"),
    (dict(tf=None), "tf"),
    (dict(mode="dvr"), "mode"),
    (dict(step_mm=0.0), "step_mm"),
    (dict(shading="phong"), "shading"),
    (dict(shading=dict(ambient=-1.0)), "shading.ambient"),
    (dict(shading=dict(ambient="bright")), "shading.ambient: expected a number"),
    (dict(shading=dict(gloss=1.0)), "unknown keys"),
    (dict(boundary="zero"), "boundary"),
    (dict(xray_scale=-1.0), "xray_scale"),
    (dict(xray_offset=np.inf), "xray_scale/xray_offset"),
    (dict(chunk_rays=0), "chunk_rays"),
])
def test_invalid_input(change, match):
    dens, mask, g, sp, cam, tf = _random_scene()
    kw = dict(densities=dens, mask=mask, grid_to_world=g, spacing=sp, camera=cam, tf=tf)
    kw.update(change)
    args = [kw.pop(n) for n in ("densities", "mask", "grid_to_world", "spacing", "camera", "tf")]
    with pytest.raises(VolumeEVMError, match=match):
        render_reference(*args, **kw)


def test_nan_depth_in_single_pixel_raises():
    dens, mask, g, sp, cam, tf = _random_scene()
    depth_in = np.full(cam.shape, BACKGROUND_DEPTH)
    depth_in[3, 4] = np.nan
    with pytest.raises(VolumeEVMError, match="depth_in: 1 NaN"):
        render_reference(dens, mask, g, sp, cam, tf, depth_in=depth_in)


def test_shell_boundary_reads_one_voxel_around_the_region():
    """``boundary="shell"`` interpolates the true densities of the voxels next to the region
    (as a VolumeEVM storing a one-voxel shell could); voxels further out are never read."""
    dens, _, g, sp, cam, tf = _random_scene(8)
    mask = np.zeros(dens.shape, bool)
    mask[2:6, 1:6, 2:5] = True
    shell = np.zeros(dens.shape, bool)
    shell[1:7, 0:7, 1:6] = True
    far = ~shell
    changed = dens.copy()
    changed[far] = -5e3
    kw = dict(step_mm=0.25, boundary="shell", shading=True)
    a, da = render_reference(dens, mask, g, sp, cam, tf, **kw)
    b, db = render_reference(changed, mask, g, sp, cam, tf, **kw)
    np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(da, db)
    changed[shell & ~mask] = 100.0  # the shell itself is read
    c, _ = render_reference(changed, mask, g, sp, cam, tf, **kw)
    assert np.abs(c - a).max() > 0.05
    # with no outside voxels both policies are the same
    full = np.ones(dens.shape, bool)
    np.testing.assert_array_equal(
        render_reference(dens, full, g, sp, cam, tf, step_mm=0.25)[0],
        render_reference(dens, full, g, sp, cam, tf, step_mm=0.25, boundary="shell")[0])


# ---------------------------------------------------------------------------- real data
def test_ct_head_sanity(data_dir):
    """CT head (downsampled 8x8x4 to 32x32x27), ct_bone, region = voxels above -300 HU (the
    head without the air). Measured against the full dense render (premultiplied RGBA, mean
    absolute difference): "shell" 0.0000 (max 0.085), "clamp" 0.041 (max 1.0: isolated bright
    voxels and thin structures in air keep their full density and become opaque cells)."""
    meta = json.loads((data_dir / "ct_head_invesalius.json").read_text())
    vol = np.load(data_dir / "ct_head_invesalius.npy")[::8, ::8, ::4]  # 32 x 32 x 27
    sp = np.array(meta["spacing_mm"]) * (8, 8, 4)
    g = grid_matrix(sp)
    centre = g[:3, 3] + g[:3, :3] @ ((np.array(vol.shape) - 1) / 2)
    cam = Camera.look_at(centre + (0.0, -0.5, 0.0), centre, ortho_scale=0.3, resolution_x=40,
                         resolution_y=40)
    tf = TransferFunction.preset("ct_bone")
    mask = vol > -300
    full, _ = render_reference(vol, None, g, sp, cam, tf, step_mm=1.0)
    over, depth = render_reference(vol, mask, g, sp, cam, tf, step_mm=1.0, boundary="shell")
    under, _ = render_reference(vol, mask, g, sp, cam, tf, mode="under", step_mm=1.0,
                                boundary="shell")
    clamp, _ = render_reference(vol, mask, g, sp, cam, tf, step_mm=1.0)
    np.testing.assert_allclose(over, under, atol=1e-6)
    assert 0.1 < (over[..., 3] > 0.5).mean() < 0.9  # a skull fills part of the view
    assert np.all(over[..., :3] <= over[..., 3:] + 1e-6)  # premultiplied
    assert np.abs(full - over).mean() < 1e-3
    assert 0.02 < np.abs(full - clamp).mean() < 0.08
    # Depth lies within the head's axial extent.
    hit = depth < BACKGROUND_DEPTH
    y_extent = vol.shape[1] * sp[1] * BU
    assert hit.mean() > 0.1
    assert np.all(np.abs(depth[hit] - 0.5) < y_extent / 2 + 1e-6)
