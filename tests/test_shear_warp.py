"""Shear-warp renderer: what is particular to it - closed forms (homogeneous box, exact column
maxima and sums), the blob and its quality settings against the reference, views along every
axis both ways, oblique, perspective, anisotropic voxels, the principal axis switch, the
intermediate image, runs and caches, depth in, an eye inside, bad input. What every method
keeps (EVM = dense, threads, odd sizes, over = under, early termination, a camera that sees
nothing, error bounds against the reference) is in test_render_contract.py."""

import json

import numpy as np
import pytest

from render_helpers import MODES, orbit_camera, reference
from volumeevm_addon import (
    Camera,
    TransferFunction,
    VolumeEVM,
    VolumeEVMError,
    grid_to_world,
    render,
)
from volumeevm_addon.model import BLENDER_UNITS_PER_MM
from volumeevm_addon.rendering import BACKGROUND_DEPTH
from volumeevm_addon.rendering._modes import Compositing
from volumeevm_addon.rendering._optics import optics
from volumeevm_addon.rendering._shear_warp import _composite, _layouts, _warp, render_shear_warp
from volumeevm_addon.rendering._shear_warp._layouts import region_layout
from volumeevm_addon.rendering._shear_warp._view import View

BU = BLENDER_UNITS_PER_MM


def centre_of(g, shape):
    return g[:3, :3] @ ((np.asarray(shape) - 1) / 2.0) + g[:3, 3]


def fine_reference(vevm, cam, tf, g, **kw):
    """The reference render with steps of a quarter of the smallest voxel side."""
    return reference(vevm, cam, tf, g, step_mm=min(vevm.spacing) / 4, **kw)


def xray_options(mode, scale):
    return {"xray_scale": scale} if mode == "xray" else {}


# ---------------------------------------------------------------------------- data
@pytest.fixture(scope="module")
def ct_head(data_dir):
    """The CT head at half resolution in x and y (128 x 128 x 108), region above -300 HU."""
    array = np.load(data_dir / "ct_head_invesalius.npy")[::2, ::2, :]
    spacing = np.array(json.loads((data_dir / "ct_head_invesalius.json").read_text())["spacing_mm"])
    return VolumeEVM.from_array(array, -300, spacing=tuple(spacing * (2, 2, 1)))


@pytest.fixture(scope="module")
def brain_half(data_dir):
    """brainsmall at half resolution (64 x 64 x 42, 2 mm voxels) for reference comparisons."""
    array = np.load(data_dir / "mr_brainsmall_volpack.npy")[::2, ::2, ::2]
    return VolumeEVM.from_array(array, 20, spacing=(2.0, 2.0, 2.0))


CT_BONE = TransferFunction.preset("ct_bone")
MRI = TransferFunction.preset("mri", data_range=(0, 202))


# ---------------------------------------------------------------------------- closed forms
def box_volume(shape=(14, 11, 9), box=((3, 11), (2, 9), (2, 7)), spacing=(0.8, 1.1, 1.4)):
    array = np.zeros(shape)
    (x0, x1), (y0, y1), (z0, z1) = box
    array[x0:x1, y0:y1, z0:z1] = 7.0
    return VolumeEVM.from_array(array, 1.0, spacing=spacing), np.array(box)


def constant_tf(alpha, rgb=(0.9, 0.6, 0.3), unit=1.0):
    return TransferFunction([(-10, *rgb, alpha), (10, *rgb, alpha)], unit_length_mm=unit)


def index_rays(cam, g):
    o, d = cam.rays()
    inv = np.linalg.inv(g)
    return o @ inv[:3, :3].T + inv[:3, 3], d @ inv[:3, :3].T


@pytest.mark.parametrize("direction", [(1, 0, 0), (-1, 0, 0), (0, 1, 0), (0, -1, 0), (0, 0, 1),
                                       (0, 0, -1)])
def test_box_along_each_axis_both_ways(direction):
    """Along an axis, rays inside the box's footprint composite exactly one sample per slice:
    alpha = 1 - (1 - a0)^(L/Δ0) with L the box's length in mm; depth = the box's front face."""
    vevm, box = box_volume()
    g = grid_to_world(vevm.spacing, (1.0, -2.0, 0.5))
    tf = constant_tf(0.12, unit=2.0)
    cam = orbit_camera(g, vevm.shape, vevm.spacing, direction, "ORTHO", res=(45, 38), zoom=1.3)
    axis = int(np.flatnonzero(direction)[0])
    length = (box[axis, 1] - box[axis, 0]) * vevm.spacing[axis]
    expected = 1 - (1 - 0.12) ** (length / 2.0)
    for mode in ("over", "under"):
        rgba, depth = render_shear_warp(vevm, cam, tf, g, mode=mode, termination=1.0)
        o, _ = index_rays(cam, g)
        others = [a for a in range(3) if a != axis]
        interior = np.ones(cam.shape, bool)
        for a in others:  # both warp taps on samples whose nearest voxel is in the box
            interior &= (o[..., a] >= box[a, 0]) & (o[..., a] <= box[a, 1] - 1)
        outside = np.zeros(cam.shape, bool)
        for a in others:
            outside |= (o[..., a] < box[a, 0] - 1) | (o[..., a] > box[a, 1])
        assert interior.sum() > 60 and outside.sum() > 100
        np.testing.assert_allclose(rgba[..., 3][interior], expected, atol=2e-6)
        colour = np.broadcast_to(expected * np.array([0.9, 0.6, 0.3]), (interior.sum(), 3))
        np.testing.assert_allclose(rgba[..., :3][interior], colour, atol=2e-6)
        assert np.all(rgba[outside] == 0) and np.all(depth[outside] == BACKGROUND_DEPTH)
        # Front face: the cell boundary of the first slice met.
        face = box[axis, 0] - 0.5 if direction[axis] < 0 else box[axis, 1] - 0.5
        front = np.zeros(3)
        front[axis] = face
        face_depth = cam.axial_depth(g[:3, :3] @ front + g[:3, 3])
        np.testing.assert_allclose(depth[interior], face_depth, rtol=1e-6)


QUALITY = [{}, {"slices_per_voxel": 2, "classification": "post"}, {"slices_per_voxel": 4}]


@pytest.mark.parametrize("quality", QUALITY)
@pytest.mark.parametrize("kind", ["ORTHO", "PERSP"])
@pytest.mark.parametrize("direction", [(0.45, -0.3, 1.0), (-0.2, 0.35, -1.0)])
def test_box_oblique_opacity_correction(kind, direction, quality):
    """Rays crossing both faces of the box perpendicular to the principal axis get
    ``slices_per_voxel`` samples per slice, each corrected for the physical step along that ray
    (anisotropic voxels, perspective: per ray): alpha = 1 - (1 - a0)^(chord/Δ0) exactly, chord
    in mm, up to the box's side faces (clamp policy: renormalised weights), with pre- or
    post-classification."""
    vevm, box = box_volume(shape=(26, 22, 10), box=((2, 24), (2, 20), (3, 8)),
                           spacing=(0.7, 0.9, 1.6))
    g = grid_to_world(vevm.spacing, (0.0, 0.0, 0.0))
    tf = constant_tf(0.2)
    cam = orbit_camera(g, vevm.shape, vevm.spacing, direction, kind, res=(50, 42), zoom=1.1,
                       distance=2.5, lens=60.0)
    rgba, _ = render_shear_warp(vevm, cam, tf, g, termination=1.0, **quality)
    o, d = index_rays(cam, g)
    c = 2  # the principal axis for both directions
    t_lo = (box[c, 0] - 0.5 - o[..., c]) / d[..., c]
    t_hi = (box[c, 1] - 0.5 - o[..., c]) / d[..., c]
    chord = np.abs(t_hi - t_lo) * np.linalg.norm(d * vevm.spacing, axis=-1)
    inner = np.ones(cam.shape, bool)
    for a in (0, 1):
        for t in (t_lo, t_hi):
            x = o[..., a] + t * d[..., a]
            # The warp reads intermediate rays up to 1 voxel away; on those, every sample's
            # nearest voxel is in the box, so the clamp policy gives it the full opacity.
            inner &= (x >= box[a, 0] + 0.5) & (x <= box[a, 1] - 1.5 - 1e-6)
    assert inner.sum() > 80
    # Perspective: the warp blends neighbouring rays of slightly different chords (~5e-6).
    atol = 3e-6 if kind == "ORTHO" else 2e-5
    np.testing.assert_allclose(rgba[..., 3][inner], 1 - 0.8 ** chord[inner], atol=atol)
    ref, _ = fine_reference(vevm, cam, tf, g, mode="over")
    assert np.abs(rgba - ref).mean() < 0.012


def gaussian_blob(shape=(41, 33, 27), spacing=(0.8, 1.0, 1.25), sigma=6.0, peak=100.0):
    c = (np.array(shape) - 1) / 2
    idx = np.stack(np.meshgrid(*[np.arange(n) for n in shape], indexing="ij"), axis=-1)
    r2 = (((idx - c) * spacing) ** 2).sum(axis=-1)
    return VolumeEVM.from_array(peak * np.exp(-r2 / sigma**2), 1.0, spacing=spacing)


BLOB_TF = TransferFunction([(0, 1.0, 0.5, 0.2, 0.0), (100, 0.2, 0.6, 1.0, 0.3)])
# Mean absolute error against the reference (premultiplied RGBA), measured 0.0001-0.0012 on the
# blob and 0.001-0.006 on brainsmall; the bounds are about twice that. (The brainsmall bounds
# per mode are also shear-warp's in test_render_contract.py's REFERENCE_BOUNDS.)
BLOB_MAE = {"over": 0.001, "under": 0.001, "xray": 0.0025, "mip": 0.0004}
BRAIN_MAE = {"over": 0.012, "under": 0.012, "xray": 0.008, "mip": 0.005}


@pytest.mark.parametrize("kind", ["ORTHO", "PERSP"])
@pytest.mark.parametrize("mode", MODES)
def test_gaussian_blob_against_reference(mode, kind):
    vevm = gaussian_blob()
    g = grid_to_world(vevm.spacing, (0.0, 0.0, 0.0))
    cam = orbit_camera(g, vevm.shape, vevm.spacing, (0.5, -1.0, 0.35), kind)
    opts = xray_options(mode, 0.01)
    rgba, depth = render_shear_warp(vevm, cam, BLOB_TF, g, mode=mode, termination=1.0, **opts)
    ref, ref_depth = fine_reference(vevm, cam, BLOB_TF, g, mode=mode, **opts)
    assert ref[..., 3].max() > 0.2
    assert np.abs(rgba - ref).mean() < BLOB_MAE[mode]
    assert np.isfinite(rgba).all() and np.isfinite(depth).all()


def rotation(axis, angle):
    x, y, z = np.asarray(axis, dtype=np.float64) / np.linalg.norm(axis)
    c, s = np.cos(angle), np.sin(angle)
    return np.array([
        [c + x * x * (1 - c), x * y * (1 - c) - z * s, x * z * (1 - c) + y * s],
        [y * x * (1 - c) + z * s, c + y * y * (1 - c), y * z * (1 - c) - x * s],
        [z * x * (1 - c) - y * s, z * y * (1 - c) + x * s, c + z * z * (1 - c)],
    ])


@pytest.mark.parametrize("kind", ["ORTHO", "PERSP"])
def test_render_entry_point_rotated_object(kind):
    """Through render(): origin, orientation and a rotated, moved object (grid axes not along
    the world's), against the reference through the same entry point."""
    blob = gaussian_blob()
    orientation = rotation((0.0, 0.0, 1.0), 0.3)
    vevm = VolumeEVM.from_array(blob.to_dense(), 1.0, spacing=blob.spacing,
                                origin=(-10.0, 5.0, 2.0), orientation=orientation)
    placement = np.eye(4)
    placement[:3, :3] = rotation((1.0, 2.0, 3.0), 0.7)
    placement[:3, 3] = (0.02, -0.01, 0.03)
    g = grid_to_world(vevm.spacing, vevm.origin, vevm.orientation, placement)
    cam = orbit_camera(g, vevm.shape, vevm.spacing, (0.2, -1.0, 0.5), kind)
    rgba, depth = render(vevm, cam, BLOB_TF, matrix_world=placement, termination=1.0)
    direct, _ = render_shear_warp(vevm, cam, BLOB_TF, g, termination=1.0)
    ref, _ = render(vevm, cam, BLOB_TF, method="reference", matrix_world=placement, step_mm=0.2)
    np.testing.assert_array_equal(rgba, direct)
    assert ref[..., 3].max() > 0.5
    assert np.abs(rgba - ref).mean() < BLOB_MAE["over"]


@pytest.mark.parametrize("kind", ["ORTHO", "PERSP"])
def test_intermediate_scale_zoomed_in(kind):
    """Zoomed in (about 3 image pixels per voxel), a finer intermediate image gets closer to
    the reference and a coarser one further (blob, measured ortho 0.0063 / 0.0022 / 0.0015,
    perspective 0.0032 / 0.0013 / 0.0009 for scales 0.5 / 1 / 2); dense = EVM at every scale."""
    vevm = gaussian_blob()
    g = grid_to_world(vevm.spacing, (0.0, 0.0, 0.0))
    cam = orbit_camera(g, vevm.shape, vevm.spacing, (0.5, -1.0, 0.35), kind, res=(64, 48),
                       zoom=0.4, lens=100.0)
    ref, _ = fine_reference(vevm, cam, BLOB_TF, g, mode="over")
    errors = []
    for scale in (0.5, 1.0, 2.0):
        rgba, depth = render_shear_warp(vevm, cam, BLOB_TF, g, termination=1.0,
                                        intermediate_scale=scale)
        dense, dense_depth = render_shear_warp(vevm, cam, BLOB_TF, g, termination=1.0,
                                               intermediate_scale=scale, skip_empty=False)
        assert np.abs(rgba - dense).max() <= 1e-6
        np.testing.assert_array_equal(depth, dense_depth)
        errors.append(np.abs(rgba - ref).mean())
    assert errors[0] > 1.5 * errors[1] and errors[2] < 0.8 * errors[1]


@pytest.mark.parametrize("kind", ["ORTHO", "PERSP"])
def test_quality_settings_against_reference(brain_half, kind):
    """Two samples per slice with post-classification: closer to the reference than the default
    in "over" (brainsmall, mean absolute error measured ortho 0.0059 -> 0.0034, perspective
    0.0031 -> 0.0015; shaded 0.0060 -> 0.0043 and 0.0030 -> 0.0019), within the default's
    bounds in every mode (X-ray 0.0032 / 0.0015, MIP 0.0024 / 0.0012); dense = EVM."""
    vevm = brain_half
    g = grid_to_world(vevm.spacing, (0.0, 0.0, 0.0))
    cam = orbit_camera(g, vevm.shape, vevm.spacing, (0.5, -1.0, 0.35), kind, res=(52, 44))
    fine = {"slices_per_voxel": 2, "classification": "post"}
    for mode, shading in (("over", None), ("over", True), ("xray", None), ("mip", None)):
        opts = dict(shading=shading, **xray_options(mode, 0.002))
        ref, _ = fine_reference(vevm, cam, MRI, g, mode=mode, **opts)
        opts.update(mode=mode, termination=1.0)
        rgba, depth = render_shear_warp(vevm, cam, MRI, g, **fine, **opts)
        dense, dense_depth = render_shear_warp(vevm, cam, MRI, g, skip_empty=False, **fine,
                                               **opts)
        assert np.abs(rgba - dense).max() <= 1e-6
        np.testing.assert_array_equal(depth, dense_depth)
        error = np.abs(rgba - ref).mean()
        if mode == "over":
            default, _ = render_shear_warp(vevm, cam, MRI, g, **opts)
            assert error < 0.8 * np.abs(default - ref).mean()  # measured ratios 0.51-0.72
        assert error < BRAIN_MAE[mode] / 2


def marschner_lobb(n=41, fm=6.0, a=0.25):
    """The Marschner–Lobb test signal on ``n``^3 voxels over [-1, 1]^3, values in [0, 1]."""
    x = np.linspace(-1.0, 1.0, n)
    px, py, pz = np.meshgrid(x, x, x, indexing="ij")
    rho = np.cos(2 * np.pi * fm * np.cos(np.pi * np.hypot(px, py) / 2))
    return (1 - np.sin(np.pi * pz / 2) + a * (1 + rho)) / (2 * (1 + a))


# A narrow pulse: opacity 0 -> 0.3 per mm -> 0 over densities 0.4 - 0.5 - 0.6.
PULSE = TransferFunction([(0.0, 1, 1, 1, 0), (0.4, 1, 1, 1, 0), (0.5, 1, 0.8, 0.6, 0.3),
                          (0.6, 1, 1, 1, 0), (1.0, 1, 1, 1, 0)])


def test_marschner_lobb_quality_settings():
    """Marschner–Lobb 41^3 with a narrow pulse, 64^2, 30 degrees about y: RMSE to the reference
    (premultiplied RGBA) measured 0.0386 (default), 0.0261 (post), 0.0246 (post, 4 slices per
    voxel), 0.0128 (post, 4 slices, intermediate_scale 2)."""
    vevm = VolumeEVM.from_array(marschner_lobb(), -1.0)
    g = grid_to_world(vevm.spacing, (0.0, 0.0, 0.0))
    th = np.radians(30.0)
    cam = orbit_camera(g, vevm.shape, vevm.spacing, (np.sin(th), 0.0, np.cos(th)), "ORTHO",
                       res=(64, 64), distance=1.0, zoom=1.02)
    ref, _ = fine_reference(vevm, cam, PULSE, g, mode="over")
    errors = [np.sqrt(np.mean((render_shear_warp(vevm, cam, PULSE, g, **q)[0] - ref) ** 2))
              for q in ({}, {"classification": "post"},
                        {"classification": "post", "slices_per_voxel": 4},
                        {"classification": "post", "slices_per_voxel": 4,
                         "intermediate_scale": 2.0})]
    assert 0.03 < errors[0] < 0.045
    assert errors[1] < 0.75 * errors[0] and errors[2] < errors[1]
    assert errors[3] < 0.016


@pytest.mark.parametrize("kind", ["ORTHO", "PERSP"])
def test_shading_against_reference(brain_half, kind):
    """Pre-classified Blinn–Phong headlight: close to the reference's shaded image (measured
    0.006 / 0.003), far closer than the unshaded image is (0.030 / 0.017); dense = EVM."""
    vevm = brain_half
    g = grid_to_world(vevm.spacing, (0.0, 0.0, 0.0))
    cam = orbit_camera(g, vevm.shape, vevm.spacing, (0.5, -1.0, 0.35), kind, res=(52, 44))
    shaded, _ = render_shear_warp(vevm, cam, MRI, g, termination=1.0, shading=True)
    plain, _ = render_shear_warp(vevm, cam, MRI, g, termination=1.0)
    dense, _ = render_shear_warp(vevm, cam, MRI, g, termination=1.0, skip_empty=False,
                                 shading={"ambient": 0.3, "diffuse": 0.7})
    ref, _ = fine_reference(vevm, cam, MRI, g, mode="over", shading=True)
    assert np.abs(plain - ref).mean() > 0.015
    assert np.abs(shaded - ref).mean() < 0.01
    assert np.abs(shaded - dense).max() <= 1e-6


def test_principal_axis_switch_at_45_degrees(brain_half):
    """Across the switch from slicing along y to slicing along x the error to the reference
    stays put and the image changes no more than between neighbouring angles on one side
    (measured: 0.0030 across, 0.0040 at 44.5 -> 44.9 degrees)."""
    vevm = brain_half
    g = grid_to_world(vevm.spacing, (0.0, 0.0, 0.0))
    frames, axes = [], []
    for deg in (44.5, 44.9, 45.1):
        th = np.radians(deg)
        cam = orbit_camera(g, vevm.shape, vevm.spacing, (np.sin(th), -np.cos(th), 0.25), "ORTHO",
                           res=(64, 48))
        rgba, _ = render_shear_warp(vevm, cam, MRI, g, termination=1.0)
        ref, _ = fine_reference(vevm, cam, MRI, g, mode="over")
        assert np.abs(rgba - ref).mean() < 0.009
        frames.append(rgba)
        axes.append(View.principal_axis(vevm, cam, g))
    assert axes == [1, 1, 0]
    same_axis = np.abs(frames[1] - frames[0]).mean()
    across = np.abs(frames[2] - frames[1]).mean()
    assert across < 1.5 * same_axis


@pytest.mark.parametrize("axis", [0, 1, 2])
def test_runs_are_the_table_in_order(brain_half, axis):
    """The runs read from the EVM's boxes cover exactly the region's voxels of each scanline,
    and their positions number the densities table of the axis in its order."""
    layout = region_layout(brain_half, axis)
    runs = layout.runs
    grid = np.full(layout.shape, np.nan)
    for line in range(layout.shape[0] * runs.lines):
        s, a = divmod(line, runs.lines)
        for r in range(runs.starts[line], runs.starts[line + 1]):
            grid[s, a, runs.lo[r]:runs.hi[r]] = layout.values[runs.pos[r] + 1:
                                                              runs.pos[r] + 1 + runs.hi[r]
                                                              - runs.lo[r]]
    dense = np.transpose(brain_half.to_dense(), layout.axes)
    mask = np.transpose(brain_half.evm.to_mask(brain_half.shape), layout.axes)
    np.testing.assert_array_equal(np.isfinite(grid), mask)
    np.testing.assert_array_equal(grid[mask], dense[mask])
    assert runs.pos[-1] + runs.hi[-1] - runs.lo[-1] == brain_half.voxel_count


def test_axis_cache_is_reused(brain_half):
    """What depends only on the principal axis is built once; a camera move along the same
    axis and another transfer function reuse it."""
    vevm = VolumeEVM.from_array(brain_half.to_dense(), 20, spacing=brain_half.spacing)
    g = grid_to_world(vevm.spacing, (0.0, 0.0, 0.0))
    first = orbit_camera(g, vevm.shape, vevm.spacing, (0.3, -1.0, 0.2), "ORTHO", res=(16, 12))
    moved = orbit_camera(g, vevm.shape, vevm.spacing, (-0.2, -1.0, 0.4), "PERSP", res=(16, 12))
    render_shear_warp(vevm, first, MRI, g)
    layout = region_layout(vevm, 1)  # the one the render kept in vevm.cache

    def kept(part):
        return [key[2:] for key in vevm.cache.keys() if key[:2] == ("shear_warp", part)]

    render_shear_warp(vevm, moved, MRI, g)
    render_shear_warp(vevm, moved, CT_BONE, g)
    assert kept("layout") == [(1,)] and region_layout(vevm, 1) is layout
    assert len(kept("classes")) == 2


def composited_slice(rows, lut, f, g):
    """The intermediate image of one sample of a one-slice volume, translated by fractions
    ``f`` (rows) and ``g`` (columns), composited "over" onto nothing by the compositing kernel:
    the voxels' table ``rows`` (0: outside the region) index ``lut`` (channels first), read
    through the runs of the region; the image covers the slice and a margin around it."""
    n, m = rows.shape
    runs = _layouts.Runs(n, m, *_layouts.mask_runs(rows[None] > 0))
    voxels = _composite.Voxels(np.r_[0, rows.ravel()].astype(np.int32),
                               np.ascontiguousarray(lut[:4].T), 4)
    beta_a, beta_b = 3.0 + f, -2.0 + g
    origin = (-6, 0)  # the image starts 3 rows and 2 columns before the slice
    plan = _composite.Plan(np.zeros(1, np.int64), np.full(1, -1), np.ones(1, np.float32),
                           np.zeros(1, np.float32), np.ones(1), np.array([beta_a]),
                           np.array([beta_b]), np.zeros(1), np.zeros(1), np.zeros(1),
                           np.zeros(1, np.int32), np.zeros(1, bool))
    optical = optics(None, Compositing("over"), None, lut=False)
    tables = _composite.Tables(False, lut[:4].T.copy(), np.zeros((65, 3), np.float32), 0.0, 0.0,
                               64.0, _composite._light(None, optical), np.float32(0.0))
    size = (n + 4, m + 4)
    frame = _composite.Frame(origin[0], origin[1], np.zeros((0, 0), np.float32),
                             np.float32(-np.inf), np.float32(np.inf),
                             np.zeros((0, 0), np.float32), np.zeros(size + (4,), np.float32),
                             np.full(size, _composite.NEVER, np.int32),
                             np.zeros((0, 0), np.int32))
    _composite.composite(0, 1, size[0], plan, runs, runs, voxels, optical, tables, frame)
    return frame.image, origin, (beta_a, beta_b)


@pytest.mark.parametrize("f, g", [(0.0, 0.0), (0.3, 0.7), (0.5, 0.49), (0.999, 0.5)])
def test_translated_slice_is_the_bilinear_resampling(f, g):
    """The compositing kernel's resampling of a translated slice (taps read through the runs,
    beyond the slice's region too) equals the four-weight bilinear of the table's channels,
    clamp policy included."""
    rng = np.random.default_rng(7)
    lut = np.zeros((5, 65), np.float32)
    lut[:4, 1:] = rng.random((4, 64), dtype=np.float32)
    lut[4, 1:] = 1.0
    rows = rng.integers(0, 65, (9, 11)).astype(np.int16)  # 0: outside voxels inside the box
    image, origin, (beta_a, beta_b) = composited_slice(rows, lut, f, g)
    f32, g32 = np.float32(f), np.float32(g)
    # The same samples by NumPy: the four taps of each intermediate pixel, outside voxels 0.
    padded = np.zeros((rows.shape[0] + 6, rows.shape[1] + 6), np.int64)
    padded[3:-3, 3:-3] = rows
    src = np.take(lut, padded, axis=1)
    i = np.arange(image.shape[0]) + origin[0] + int(np.floor(beta_a)) + 3
    j = np.arange(image.shape[1]) + origin[1] + int(np.floor(beta_b)) + 3
    taps = [src[:, i[:, None] + a, j[None, :] + b] for a in (0, 1) for b in (0, 1)]
    weights = [(1 - f32) * (1 - g32), (1 - f32) * g32, f32 * (1 - g32), f32 * g32]
    expect = sum(t * w for t, w in zip(taps, weights))
    expect_inside = padded[i[:, None] + int(f32 >= 0.5), j[None, :] + int(g32 >= 0.5)] > 0
    expect = np.where(expect_inside, expect[:4] / np.maximum(expect[4], 1e-30), 0.0)
    np.testing.assert_array_equal(image[..., 3] > 0, expect_inside)
    np.testing.assert_allclose(image, np.moveaxis(expect, 0, -1), atol=1e-6)


def test_warp_chunks_do_not_change_the_image(brain_half, monkeypatch):
    """The warp's pixels computed a few at a time (chunks not a multiple of an image row)
    give the image and depth computed all at once."""
    g = grid_to_world(brain_half.spacing, (0.0, 0.0, 0.0))
    cam = orbit_camera(g, brain_half.shape, brain_half.spacing, (0.4, -1.0, 0.3), "ORTHO",
                       res=(37, 29))
    rgba, depth = render_shear_warp(brain_half, cam, MRI, g)
    monkeypatch.setattr(_warp, "_WARP_CHUNK", 100)
    rgba_chunked, depth_chunked = render_shear_warp(brain_half, cam, MRI, g)
    np.testing.assert_array_equal(rgba_chunked, rgba)
    np.testing.assert_array_equal(depth_chunked, depth)


# ---------------------------------------------------------------------------- intermediate origin
def test_span_and_shift_move_indices_only():
    """A slice's samples over the intermediate image (first tap, fraction) are the same for any
    integer origin: only the array indices of the span move with it."""
    rng = np.random.default_rng(11)
    for trial in range(400):
        alpha = 1.0 if trial % 2 else float(rng.uniform(0.3, 1.0))
        beta = float(rng.uniform(-60, 60))
        if trial % 5 == 0:
            beta = float(np.round(beta)) + [0.0, 1e-15, -1e-15][trial % 3]  # near an integer
        t0 = int(rng.integers(-5, 40))
        t1 = t0 + int(rng.integers(1, 30))
        origin = int(rng.integers(-80, 80))
        lo, hi = int(rng.integers(-5, 20)), int(rng.integers(30, 120))
        span = _composite.span(t0, t1, alpha, beta, origin, lo, hi)
        for k in (1, 2, 7, -3):
            moved = _composite.span(t0, t1, alpha, beta, origin - k, lo + k, hi + k)
            assert (span[1] <= span[0]) == (moved[1] <= moved[0])
            if span[1] <= span[0]:
                continue
            assert (moved[0], moved[1]) == (span[0] + k, span[1] + k)
            taps = [_composite.tap(p + origin, alpha, beta, False) for p in range(*span)]
            moved_taps = [_composite.tap(p + origin - k, alpha, beta, False) for p in range(*moved)]
            assert moved_taps == taps


ORIGIN_CASES = [(mode, {}) for mode in MODES] + [
    ("over", {"classification": "post", "shading": True}),
    ("over", {"slices_per_voxel": 2}),
    ("under", {"intermediate_scale": 1.5}),
    ("over", {"depth_in": "middle", "termination": 0.9}),
]


@pytest.mark.parametrize("mode, options", ORIGIN_CASES,
                         ids=[mode + "".join(f"-{k}" for k in opts) for mode, opts in ORIGIN_CASES])
@pytest.mark.parametrize("kind", ["ORTHO", "PERSP"])
def test_intermediate_origin_moves_nothing(ct_head, monkeypatch, kind, mode, options):
    """Starting the intermediate image a whole number of pixels earlier (odd and even: a
    rounding of halves to even would depend on the parity) changes neither the image nor the
    depth, bit for bit: only the indices move. (The region's path and the dense path start
    it at different places, so the exactness contract depends on this.)"""
    g = grid_to_world(ct_head.spacing, (0.0, 0.0, 0.0))
    cam = orbit_camera(g, ct_head.shape, ct_head.spacing, (0.4, -1.0, 0.3), kind, res=(56, 44))
    opts = dict(options, **xray_options(mode, 0.002))
    if opts.get("depth_in") == "middle":
        _, depth = render_shear_warp(ct_head, cam, CT_BONE, g)
        opts["depth_in"] = np.full(cam.shape, np.median(depth[depth < BACKGROUND_DEPTH]))
    rgba, depth = render_shear_warp(ct_head, cam, CT_BONE, g, mode=mode, **opts)
    assert rgba[..., 3].max() > 0.3 and (depth < BACKGROUND_DEPTH).sum() > 200
    extent = View.extent
    for shift in ((1, 0), (2, 7)):
        def earlier(foot, img, shift=shift):
            origin, size = extent(foot, img)
            return origin - shift, (size[0] + shift[0] + 2, size[1] + shift[1] + 3)

        monkeypatch.setattr(View, "extent", staticmethod(earlier))
        moved_rgba, moved_depth = render_shear_warp(ct_head, cam, CT_BONE, g, mode=mode, **opts)
        np.testing.assert_array_equal(moved_rgba, rgba)
        np.testing.assert_array_equal(moved_depth, depth)


# ---------------------------------------------------------------------------- modes
def aligned_camera(g, shape, spacing, axis, sign):
    """Orthographic camera along ``sign`` times grid ``axis`` with one pixel per voxel, pixel
    centres on the voxel centres; returns the camera and per pixel the voxel (i, j, k) column."""
    others = [a for a in range(3) if a != axis]
    w, h = shape[others[0]], shape[others[1]]
    centre = centre_of(g, shape)
    forward = np.zeros(3)
    forward[axis] = sign
    up = np.zeros(3)
    up[others[1]] = 1.0
    scale = max(w * spacing[others[0]], h * spacing[others[1]]) * BU
    cam = Camera.look_at(centre - forward * 0.5, centre, up=up, ortho_scale=scale,
                         resolution_x=w, resolution_y=h, clip_start=0.001)
    o, _ = index_rays(cam, g)
    cols = np.rint(o[..., others]).astype(int)
    assert np.abs(o[..., others] - cols).max() < 1e-6
    return cam, others, cols


@pytest.mark.parametrize("axis,sign", [(0, 1), (1, -1), (2, 1), (2, -1)])
def test_mip_and_xray_are_column_max_and_sum(brain_half, axis, sign):
    """Along an axis with pixels on voxel centres, MIP is the classified maximum of each voxel
    column of the region, and X-ray is 1 - exp(-Σ μ Δ) over it."""
    vevm = brain_half
    g = grid_to_world(vevm.spacing, (0.0, 0.0, 0.0))
    cam, others, cols = aligned_camera(g, vevm.shape, vevm.spacing, axis, sign)
    dense = np.moveaxis(vevm.to_dense().astype(np.float64), axis, -1)
    mask = np.moveaxis(vevm.evm.to_mask(vevm.shape), axis, -1)
    columns = dense[cols[..., 0], cols[..., 1]]
    inside = mask[cols[..., 0], cols[..., 1]]
    peak = np.where(inside, columns, -np.inf).max(axis=-1)
    seen = np.isfinite(peak)
    straight = MRI.evaluate(np.where(seen, peak, 0.0))
    expected = np.where(seen[..., None], straight * straight[..., 3:4], 0.0)
    expected[..., 3] = np.where(seen, straight[..., 3], 0.0)
    mip, _ = render_shear_warp(vevm, cam, MRI, g, mode="mip")
    assert seen.sum() > 500
    np.testing.assert_allclose(mip, expected, atol=1e-6)

    offset, scale = 30.0, 0.004
    tau = (scale * np.maximum(columns - offset, 0) * inside).sum(axis=-1) * vevm.spacing[axis]
    xray, _ = render_shear_warp(vevm, cam, None, g, mode="xray", xray_scale=scale,
                                xray_offset=offset)
    assert tau.max() > 0.5
    np.testing.assert_allclose(xray, np.repeat((1 - np.exp(-tau))[..., None], 4, axis=-1),
                               atol=2e-6)


# ---------------------------------------------------------------------------- depth
@pytest.mark.parametrize("mode", MODES)
def test_opaque_plane_hides_what_is_behind(brain_half, mode):
    """depth_in at the boundary between two slices (view along an axis) gives exactly the
    image of the region cut to the slices in front of it; in front of everything, nothing."""
    vevm = brain_half
    g = grid_to_world(vevm.spacing, (0.0, 0.0, 0.0))
    cam, _, _ = aligned_camera(g, vevm.shape, vevm.spacing, 2, -1)  # looking down -z
    cut = 20  # keep slices z >= cut
    plane = np.zeros(3)
    plane[2] = cut - 0.5
    plane_depth = cam.axial_depth(g[:3, :3] @ plane + g[:3, 3])
    depth_in = np.full(cam.shape, plane_depth)
    opts = xray_options(mode, 0.002)
    rgba, depth = render_shear_warp(vevm, cam, MRI, g, mode=mode, depth_in=depth_in, **opts)
    front = vevm.clip((0, 0, cut), vevm.shape)
    want, want_depth = render_shear_warp(front, cam, MRI, g, mode=mode, **opts)
    whole, _ = render_shear_warp(vevm, cam, MRI, g, mode=mode, **opts)
    assert np.abs(whole - want).max() > 0.05  # the part behind the plane shows without it
    assert np.abs(rgba - want).max() <= 1e-6
    np.testing.assert_array_equal(depth, want_depth)
    assert np.all(depth[depth < BACKGROUND_DEPTH] <= plane_depth)
    # A plane in front of the volume hides all of it, an oblique and perspective view too.
    pcam = orbit_camera(g, vevm.shape, vevm.spacing, (0.3, -1.0, 0.5), "PERSP")
    rgba, depth = render_shear_warp(vevm, pcam, MRI, g, mode=mode,
                                    depth_in=np.full(pcam.shape, 0.01), **opts)
    assert np.all(rgba == 0) and np.all(depth == BACKGROUND_DEPTH)


def test_depth_in_slanted_against_reference(brain_half):
    """A non-constant depth buffer (a slanted wall through the volume) stops rays like the
    reference does, up to the sampling of the cut."""
    vevm = brain_half
    g = grid_to_world(vevm.spacing, (0.0, 0.0, 0.0))
    cam = orbit_camera(g, vevm.shape, vevm.spacing, (0.4, -1.0, 0.2), "ORTHO", res=(52, 44))
    centre_depth = cam.axial_depth(centre_of(g, vevm.shape))
    cols = np.arange(cam.shape[1])
    depth_in = np.broadcast_to(centre_depth + (cols - cols.mean()) * 0.0015, cam.shape).copy()
    rgba, _ = render_shear_warp(vevm, cam, MRI, g, depth_in=depth_in, termination=1.0)
    ref, _ = fine_reference(vevm, cam, MRI, g, mode="over", depth_in=depth_in)
    unclipped, _ = render_shear_warp(vevm, cam, MRI, g, termination=1.0)
    assert np.abs(unclipped - ref).mean() > 0.02
    assert np.abs(rgba - ref).mean() < 0.008


@pytest.mark.parametrize("where", ["inside", "inside_wide", "inside_ortho", "beside_long_side"])
def test_perspective_eye_inside_or_beside(brain_half, where):
    """A perspective eye inside the volume, also with a 120-degree field of view (rays along
    all six axis directions: one pass each); an orthographic camera whose near clip cuts the
    volume; an eye beside a long volume, within its slab range along the axis most parallel to
    the eye-to-centre vector, picks an axis it is outside of, so every ray is rendered."""
    g = grid_to_world(brain_half.spacing, (0.0, 0.0, 0.0))
    centre = centre_of(g, brain_half.shape)
    if where.startswith("inside"):
        vevm = brain_half
        eye, target = centre + (0.01, -0.005, 0.0), centre + (0.03, 0.03, 0.01)
    else:  # a 12 x 12 x 40 voxel column seen from beside its lower part
        vevm = brain_half.clip((26, 26, 1), (38, 38, 41))
        eye, target = centre + (-0.029, 0.001, -0.037), centre + (0.001, 0.001, 0.001)
    # inside_ortho: the near clip plane cuts the volume
    lens = {"inside": 30.0, "inside_wide": 10.0}.get(where, 12.0)
    cam = Camera.look_at(eye, target, kind="ORTHO" if where == "inside_ortho" else "PERSP",
                         ortho_scale=0.08, lens_mm=lens, resolution_x=48, resolution_y=40,
                         clip_start=0.001)
    rgba, _ = render_shear_warp(vevm, cam, MRI, g, termination=1.0)
    ref, _ = fine_reference(vevm, cam, MRI, g, mode="over")
    assert ref[..., 3].mean() > 0.1
    # measured 0.016, 0.023, 0.020 and 0.0075; one pass along the forward axis gives 0.089 for
    # the wide view, and choosing the axis from the eye-to-centre vector alone 0.025 beside the
    # column (the parts behind the slab range missing)
    bound = {"inside": 0.025, "inside_wide": 0.035, "inside_ortho": 0.03,
             "beside_long_side": 0.012}[where]
    assert np.abs(rgba - ref).mean() < bound


# ---------------------------------------------------------------------------- degenerate input
def test_single_voxel():
    array = np.zeros((5, 6, 7))
    array[2, 3, 4] = 5.0
    vevm = VolumeEVM.from_array(array, 1.0, spacing=(1.0, 0.5, 0.5))
    g = grid_to_world(vevm.spacing, (0.0, 0.0, 0.0))
    tf = constant_tf(0.3)
    cam, _, _ = aligned_camera(g, vevm.shape, vevm.spacing, 0, 1)
    rgba, depth = render_shear_warp(vevm, cam, tf, g, termination=1.0)
    lit = rgba[..., 3] > 0
    assert lit.sum() == 1
    np.testing.assert_allclose(rgba[..., 3].max(), 0.3, atol=1e-6)  # 1 mm along x
    assert np.all(depth[~lit] == BACKGROUND_DEPTH) and np.all(depth[lit] < 1)


def test_bad_input(brain_half):
    g = grid_to_world(brain_half.spacing, (0.0, 0.0, 0.0))
    cam = orbit_camera(g, brain_half.shape, brain_half.spacing, (1, 0, 0), "ORTHO", res=(8, 6))
    with pytest.raises(VolumeEVMError, match="mode"):
        render_shear_warp(brain_half, cam, MRI, g, mode="add")
    with pytest.raises(VolumeEVMError, match="depth_in: shape"):
        render_shear_warp(brain_half, cam, MRI, g, depth_in=np.ones((5, 5)))
    with pytest.raises(VolumeEVMError, match="depth_in: 1 NaN"):
        depth_in = np.ones(cam.shape)
        depth_in[2, 3] = np.nan
        render_shear_warp(brain_half, cam, MRI, g, depth_in=depth_in)
    with pytest.raises(VolumeEVMError, match="termination"):
        render_shear_warp(brain_half, cam, MRI, g, termination=0.0)
    with pytest.raises(VolumeEVMError, match="intermediate_scale"):
        render_shear_warp(brain_half, cam, MRI, g, intermediate_scale=0)
    with pytest.raises(VolumeEVMError, match="slices_per_voxel"):
        render_shear_warp(brain_half, cam, MRI, g, slices_per_voxel=5)
    with pytest.raises(VolumeEVMError, match="classification"):
        render_shear_warp(brain_half, cam, MRI, g, classification="both")
    for lut_size in (1, "abc", None, 2.5):
        with pytest.raises(VolumeEVMError, match="lut_size"):
            render_shear_warp(brain_half, cam, MRI, g, lut_size=lut_size)
    with pytest.raises(VolumeEVMError, match="skip_empty"):
        render_shear_warp(brain_half, cam, MRI, g, skip_empty="yes")
    with pytest.raises(VolumeEVMError, match="xray_scale"):
        render_shear_warp(brain_half, cam, None, g, mode="xray", xray_scale=-1.0)
    with pytest.raises(VolumeEVMError, match="tf"):
        render_shear_warp(brain_half, cam, None, g, mode="over")
    with pytest.raises(VolumeEVMError, match="shading: unknown"):
        render_shear_warp(brain_half, cam, MRI, g, shading={"glow": 1.0})
    with pytest.raises(VolumeEVMError, match="camera"):
        render_shear_warp(brain_half, "camera", MRI, g)
    with pytest.raises(VolumeEVMError, match="grid_to_world"):
        render_shear_warp(brain_half, cam, MRI, np.zeros((4, 4)))
