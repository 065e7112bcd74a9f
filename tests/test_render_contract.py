"""The contracts every renderer keeps, stated once over methods x modes x camera kinds: an empty
region or a camera that sees nothing gives a transparent image and background depth, over equals
under and early termination stays within ``1 - termination``, ``depth_in`` stops rays, a camera
inside the volume works, and the VolumeEVM renders exactly like the dense grid with everything
outside the region transparent. A bound that belongs to one method stays in a dict keyed by method.

What only one method does (sheets, blocks, the shear and the warp) stays in its own file.
"""

import json

import numpy as np
import pytest

from render_helpers import MODES, XRAY, camera, centre, const_tf, reference
from volumeevm_addon import (
    BACKGROUND_DEPTH,
    EVM,
    Camera,
    TransferFunction,
    VolumeEVM,
    grid_to_world,
)
from volumeevm_addon.phantoms import box_chords_mm
from volumeevm_addon.rendering._raycast import render_raycast, render_raycast_navigate
from volumeevm_addon.rendering._shear_warp import render_shear_warp
from volumeevm_addon.rendering._splat import render_splat

RENDER = {"raycast": render_raycast, "raycast_navigate": render_raycast_navigate,
          "splat": render_splat, "shear_warp": render_shear_warp}
KINDS = ("ORTHO", "PERSP")


@pytest.fixture(scope="module")
def ct(data_dir):
    """The CT head downsampled 4x4x3 (64x64x36), with its JSON spacing."""
    meta = json.loads((data_dir / "ct_head_invesalius.json").read_text())
    a = np.load(data_dir / "ct_head_invesalius.npy")[::4, ::4, ::3]
    return a, tuple(np.array(meta["spacing_mm"]) * (4, 4, 3))


def region(ct, threshold, preset):
    a, sp = ct
    v = VolumeEVM.from_array(a, threshold, spacing=sp)
    return v, grid_to_world(v.spacing, v.origin), TransferFunction.preset(preset)


@pytest.fixture(scope="module")
def skin(ct):
    """The skin: the region above -300 HU."""
    return region(ct, -300, "ct_skin")


@pytest.fixture(scope="module")
def bone(ct):
    """The bone: the region above 150 HU."""
    return region(ct, 150, "ct_bone")


def mode_options(mode):
    return XRAY if mode == "xray" else {}


# ---------------------------------------------------------------------------- EVM = dense
# Each method and the settings that change how it walks the region.
VARIANTS = {"raycast": ("raycast", {}), "raycast_navigate": ("raycast_navigate", {}),
            "splat": ("splat", {}), "splat 3 sub-slabs": ("splat", {"substeps": 3}),
            "shear_warp": ("shear_warp", {})}


@pytest.mark.parametrize("kind", KINDS)
@pytest.mark.parametrize("mode", MODES)
@pytest.mark.parametrize("variant", VARIANTS)
def test_evm_equals_dense(bone, variant, mode, kind):
    """Skipping empty space over the region gives the render of every voxel of the grid with
    the region as a mask."""
    v, g, tf = bone
    method, options = VARIANTS[variant]
    cam = camera(kind, g, v, (0.3, -0.5, 0.2), 0.3)
    kw = dict(mode_options(mode), mode=mode, **options)
    r1, d1 = RENDER[method](v, cam, tf, g, **kw)
    r0, d0 = RENDER[method](v, cam, tf, g, skip_empty=False, **kw)
    assert r1[..., 3].max() > 0.5 and (r1[..., 3] == 0).sum() > 50
    np.testing.assert_allclose(r1, r0, rtol=0, atol=1e-6)
    np.testing.assert_array_equal(d1 == BACKGROUND_DEPTH, d0 == BACKGROUND_DEPTH)
    np.testing.assert_allclose(d1, d0, rtol=1e-6)


# ---------------------------------------------------------------------------- nothing to see
@pytest.mark.parametrize("kind", KINDS)
@pytest.mark.parametrize("mode", MODES)
@pytest.mark.parametrize("method", RENDER)
def test_empty_region_is_transparent(method, mode, kind):
    g = grid_to_world((1.0, 1.0, 1.0), (0, 0, 0))
    empty = VolumeEVM(EVM(), np.zeros(0), shape=(5, 4, 3))
    cam = camera(kind, g, empty, (0.01, -0.008, 0.006), 0.01, res=(9, 7))
    rgba, depth = RENDER[method](empty, cam, const_tf(0.5), g, mode=mode, **mode_options(mode))
    assert rgba.shape == (7, 9, 4) and rgba.dtype == np.float32 and rgba.max() == 0
    assert np.all(depth == BACKGROUND_DEPTH) and depth.dtype == np.float32


@pytest.mark.parametrize("where", ["away", "beside"])
@pytest.mark.parametrize("kind", KINDS)
@pytest.mark.parametrize("mode", MODES)
@pytest.mark.parametrize("method", RENDER)
def test_camera_that_sees_nothing(skin, method, mode, kind, where):
    """Looking away from the volume (it is behind the camera) or beside it (outside the field
    of view; shear-warp's perspective rays parallel to the slices once made inf * 0 there)."""
    v, g, tf = skin
    c = centre(v, g)
    eye, target = {"away": (c + (0.3, 0, 0), c + (0.6, 0, 0)),
                   "beside": (c + (0, -0.6, 0), c + (0.3, -0.6, 0))}[where]
    cam = Camera.look_at(eye, target, kind=kind, ortho_scale=0.1, resolution_x=7, resolution_y=5)
    rgba, depth = RENDER[method](v, cam, tf, g, mode=mode, **mode_options(mode))
    assert rgba.shape == (5, 7, 4) and rgba.max() == 0 and np.all(depth == BACKGROUND_DEPTH)


# ---------------------------------------------------------------------------- compositing
@pytest.mark.parametrize("kind", KINDS)
@pytest.mark.parametrize("method", RENDER)
def test_over_equals_under_and_early_termination_bound(skin, method, kind):
    v, g, tf = skin
    render = RENDER[method]
    cam = camera(kind, g, v, (0.3, -0.5, 0.2), 0.3)
    full, dfull = render(v, cam, tf, g, termination=1.0)
    under, dunder = render(v, cam, tf, g, mode="under")
    np.testing.assert_allclose(under, full, atol=2e-5)
    np.testing.assert_allclose(dunder, dfull, rtol=1e-6)
    for thr in (0.95, 0.9, 0.8, 0.5):
        ert, dert = render(v, cam, tf, g, termination=thr)
        diff = np.abs(ert - full)
        assert diff.max() <= 1 - thr + 1e-6
        stopped = ert[..., 3] >= thr
        assert stopped.sum() > 100 and diff[stopped].max() > 1e-3  # it did stop early
        np.testing.assert_array_equal(dert, dfull)


# ---------------------------------------------------------------------------- depth
# How far the depth may move when a plane cuts the rays: rays keep their first hit exactly,
# splats within float32 rounding. (shear_warp's own test checks it on the brain, per mode.)
DEPTH_RTOL = {"raycast": 0.0, "raycast_navigate": 0.0, "splat": 1e-6}


@pytest.mark.parametrize("kind", KINDS)
@pytest.mark.parametrize("method", list(DEPTH_RTOL))
def test_opaque_plane_hides_what_is_behind(method, kind):
    render = RENDER[method]
    shape, sp = (8, 8, 8), (1.0, 1.0, 1.0)
    v = VolumeEVM.from_array(np.full(shape, 3.0), 0, spacing=sp)
    g = grid_to_world(sp, (0, 0, 0))
    cam = camera(kind, g, v, (0.0, 0.0, 0.02), 0.012, up=(0, 1, 0))  # down -z at the top
    tf = const_tf(0.1)
    free, dfree = render(v, cam, tf, g, termination=1.0)
    top = dfree[dfree < 1e9].min()
    plane = np.full(cam.shape, top + 0.003)  # 3 mm into the volume (axial)
    plane[:, : cam.shape[1] // 2] = 1e10  # left half: no geometry
    rgba, depth = render(v, cam, tf, g, depth_in=plane, termination=1.0)
    left, right = np.s_[:, : cam.shape[1] // 2], np.s_[:, cam.shape[1] // 2:]
    np.testing.assert_array_equal(rgba[left], free[left])
    # Behind the plane nothing counts: the chord is that of the box cut at z = 7.5 - 3 voxels.
    chord = box_chords_mm(cam, g, (0, 0, 5), (8, 8, 8))
    assert (chord[right] > 2.9).sum() > 100
    np.testing.assert_allclose(rgba[right][..., 3], 1 - 0.9 ** chord[right], atol=1e-5)
    np.testing.assert_allclose(depth, dfree, rtol=DEPTH_RTOL[method], atol=0)
    # A plane in front of the volume hides it all.
    rgba, depth = render(v, cam, tf, g, depth_in=np.full(cam.shape, top - 1e-4))
    assert rgba.max() == 0 and np.all(depth == BACKGROUND_DEPTH)


# ---------------------------------------------------------------------------- camera inside
# Mean |error| against the reference, and the options: rays sample at 1 mm; splats behind the
# camera are dropped and footprints near it cut at ``max_footprint_px``.
INSIDE = {"raycast": (0.012, {"step_mm": 1.0}),  # measured 0.007
          "raycast_navigate": (0.012, {"step_mm": 1.0}),
          "splat": (0.03, {})}  # measured 0.016


@pytest.mark.parametrize("method", list(INSIDE))
def test_camera_inside_the_volume(skin, method):
    v, g, tf = skin
    bound, options = INSIDE[method]
    c = centre(v, g)
    cam = Camera.look_at(c, c + (0.05, 0.1, 0.0), kind="PERSP", lens_mm=20.0, resolution_x=24,
                         resolution_y=20, clip_start=1e-3)
    rgba, depth = RENDER[method](v, cam, tf, g, **options)
    rr, _ = reference(v, cam, tf, g)
    assert np.isfinite(rgba).all() and rr[..., 3].mean() > 0.3
    assert np.abs(rgba - rr).mean() < bound
    assert np.all(depth[depth < 1e9] >= 1e-3 - 1e-7)  # nothing before the near clip
