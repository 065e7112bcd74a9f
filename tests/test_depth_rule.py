"""The depth rule every renderer shares (:mod:`volumeevm_addon.rendering._depth`): the output
depth is that of the first sample whose opacity per unit length reaches ``VISIBLE_ALPHA``
(X-ray: whose attenuation does), so that it never comes from numerical dust. Tested per method:
samples just below the threshold give no depth, just above they give the depth of the region's
surface; and a camera perturbed by one ulp (the size of the difference between two BLAS
kernels) neither moves the depth nor makes a pixel appear or vanish, on the real CT head."""

import dataclasses
import json

import numpy as np
import pytest

from render_helpers import MODES, camera, const_tf, reference
from volumeevm_addon import (
    BACKGROUND_DEPTH,
    VISIBLE_ALPHA,
    TransferFunction,
    VolumeEVM,
    grid_to_world,
)
from volumeevm_addon import BLENDER_UNITS_PER_MM as BU
from volumeevm_addon.phantoms import box
from volumeevm_addon.rendering._depth import VISIBLE_OPTICAL_DEPTH, attenuates, visible
from volumeevm_addon.rendering._raycast import render_raycast, render_raycast_navigate
from volumeevm_addon.rendering._shear_warp import render_shear_warp
from volumeevm_addon.rendering._splat import render_splat
from volumeevm_addon.rendering._transfer import opacity_correction

METHODS = {
    "reference": lambda vevm, cam, tf, g, **kw: reference(vevm, cam, tf, g, **kw),
    "raycast": render_raycast,
    "raycast_navigate": render_raycast_navigate,
    "splat": render_splat,
    "shear_warp": render_shear_warp,
    "shear_warp_post": lambda *a, **kw: render_shear_warp(*a, classification="post", **kw),
    "shear_warp_2": lambda *a, **kw: render_shear_warp(*a, slices_per_voxel=2, **kw),
}
MARGIN = 0.1
"""Relative distance to the threshold of the "just below" and "just above" samples: float32
rounds ``1 - α`` to ``2**-24``, a few per mille of a per-step opacity near the threshold."""


# ---------------------------------------------------------------------------- the rule
@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_visible_is_a_threshold_on_opacity_per_unit_length(dtype):
    """Whatever a sample's length, it is visible exactly when its opacity per unit length is at
    least VISIBLE_ALPHA; a sample of length 0 never is; X-ray's form is the same threshold."""
    units = np.array([1e-6, 0.05, 0.5, 1.0, 2.5, 40.0])
    for factor, expected in ((1 - 1e-3, False), (1 + 1e-3, True)):
        alpha = opacity_correction(VISIBLE_ALPHA * factor, units).astype(dtype)
        assert visible(alpha, units).tolist() == [expected] * len(units)
        tau = (VISIBLE_OPTICAL_DEPTH * factor * units).astype(dtype)
        assert attenuates(tau, units).tolist() == [expected] * len(units)
    assert visible(np.float32(1.0), 1.0) and not visible(np.zeros(3, dtype), 0.0).any()
    assert not attenuates(np.zeros(3, dtype), 0.0).any()
    # Between float dust and what a display shows, and exact in both precisions.
    assert 2.0 ** -24 * 100 < VISIBLE_ALPHA < (1 / 255) / 100
    assert float(np.float32(VISIBLE_ALPHA)) == VISIBLE_ALPHA
    assert -np.expm1(-VISIBLE_OPTICAL_DEPTH) == pytest.approx(VISIBLE_ALPHA, rel=1e-12)


def block():
    """A homogeneous block (density 1) in a 14x12x10 grid of anisotropic voxels."""
    vol = box((14, 12, 10), (3, 2, 2), (11, 10, 8), spacing=(1.0, 1.25, 1.5))
    vevm = VolumeEVM.from_volume(vol, 0.5)
    return vevm, grid_to_world(vevm.spacing, vevm.origin)


@pytest.mark.parametrize("mode", MODES)
@pytest.mark.parametrize("method", sorted(METHODS))
def test_every_renderer_uses_the_threshold(method, mode):
    """Material just below the threshold is composited but gives no depth; just above, it gives
    the depth that opaque material gives (the region's surface), in every renderer."""
    vevm, g = block()
    cam = camera("ORTHO", g, vevm, (0.03, -0.05, 0.02), 0.02, res=(24, 20))
    render = METHODS[method]

    def run(level):
        if mode == "xray":  # attenuation μ = level per mm (density 1)
            return render(vevm, cam, const_tf(0.5), g, mode=mode, xray_scale=level)
        return render(vevm, cam, const_tf(level), g, mode=mode)

    threshold = VISIBLE_OPTICAL_DEPTH if mode == "xray" else VISIBLE_ALPHA
    opaque = 0.5 if mode != "xray" else 1.0
    rgba, depth = run(threshold * (1 - MARGIN))
    assert rgba[..., 3].max() > 0 and np.all(depth == BACKGROUND_DEPTH)
    rgba, depth = run(threshold * (1 + MARGIN))
    _, surface = run(opaque)
    assert (surface < BACKGROUND_DEPTH).sum() > 100
    np.testing.assert_array_equal(depth, surface)


# ---------------------------------------------------------------------------- one ulp
@pytest.fixture(scope="module")
def ct_crop(data_dir):
    """A 48x48x48 crop of the CT head at half resolution in x and y, region above -300 HU."""
    meta = json.loads((data_dir / "ct_head_invesalius.json").read_text())
    array = np.load(data_dir / "ct_head_invesalius.npy")[::2, ::2, :][40:88, 40:88, 50:98]
    vevm = VolumeEVM.from_array(array, -300,
                                spacing=tuple(np.array(meta["spacing_mm"]) * (2, 2, 1)))
    return vevm, grid_to_world(vevm.spacing, vevm.origin)


def perturbed(cam, seed):
    """``cam`` with every entry of its matrix moved by one ulp: all up (seed None) or each up or
    down at random."""
    m = cam.matrix_world
    if seed is None:
        towards = np.inf
    else:
        towards = np.where(np.random.default_rng(seed).random(m.shape) < 0.5, np.inf, -np.inf)
    moved = np.nextafter(m, towards)
    moved[3] = m[3]  # (the projective row stays (0, 0, 0, 1))
    return dataclasses.replace(cam, matrix_world=moved)


def assert_same_depth(depth, other, slice_bu):
    """No pixel appears or vanishes, and none moves by more than 1 % of ``slice_bu``."""
    seen = depth < BACKGROUND_DEPTH
    np.testing.assert_array_equal(seen, other < BACKGROUND_DEPTH)
    assert np.abs(depth[seen] - other[seen]).max() <= 0.01 * slice_bu


@pytest.mark.parametrize("kind", ["ORTHO", "PERSP"])
@pytest.mark.parametrize("mode", MODES)
@pytest.mark.parametrize("method", sorted(METHODS))
def test_one_ulp_of_camera_changes_no_depth(ct_crop, method, mode, kind):
    """Moving every entry of the camera matrix by one ulp, up or at random, leaves the depth
    where it was (no pixel appears or vanishes) and the colour within float32 rounding."""
    vevm, g = ct_crop
    tf = TransferFunction.preset("ct_bone")
    cam = camera(kind, g, vevm, (0.04, -0.1, 0.03), 0.1, res=(28, 22))
    kw = {"xray_scale": 0.002} if mode == "xray" else {}
    rgba, depth = METHODS[method](vevm, cam, tf, g, mode=mode, **kw)
    assert (depth < BACKGROUND_DEPTH).sum() > 100
    for seed in (None, 7):
        other_rgba, other_depth = METHODS[method](vevm, perturbed(cam, seed), tf, g, mode=mode,
                                                  **kw)
        assert_same_depth(depth, other_depth, min(vevm.spacing) * BU)
        assert np.abs(rgba - other_rgba).max() <= 1e-5


@pytest.fixture(scope="module")
def ct_head(data_dir):
    """The CT head at half resolution in x and y (128 x 128 x 108), region above -300 HU: the
    volume and view of ``test_shear_warp.test_exactness_contract_real_volumes``."""
    meta = json.loads((data_dir / "ct_head_invesalius.json").read_text())
    array = np.load(data_dir / "ct_head_invesalius.npy")[::2, ::2, :]
    vevm = VolumeEVM.from_array(array, -300,
                                spacing=tuple(np.array(meta["spacing_mm"]) * (2, 2, 1)))
    return vevm, grid_to_world(vevm.spacing, (0.0, 0.0, 0.0))


@pytest.mark.parametrize("seed", [None, 1, 2, 3, 4, 5])
@pytest.mark.parametrize("mode", MODES)
def test_one_ulp_shear_warp_ct_head_stays_exact(ct_head, mode, seed):
    """The view where a BLAS kernel's ulp made shear-warp's depth differ between the region's
    path and the dense path: under every one-ulp perturbation both paths agree exactly (RGBA
    and depth) and the depth stays where the unperturbed camera has it."""
    vevm, g = ct_head
    tf = TransferFunction.preset("ct_bone")
    size = np.linalg.norm(np.asarray(vevm.shape) * vevm.spacing) * BU
    way = np.array([0.4, -1.0, 0.3])
    cam = camera("ORTHO", g, vevm, way / np.linalg.norm(way) * size * 1.5, size * 0.9,
                 res=(56, 44))
    kw = {"xray_scale": 0.002} if mode == "xray" else {}
    _, depth = render_shear_warp(vevm, cam, tf, g, mode=mode, **kw)
    moved = perturbed(cam, seed)
    rgba, other = render_shear_warp(vevm, moved, tf, g, mode=mode, **kw)
    dense_rgba, dense_depth = render_shear_warp(vevm, moved, tf, g, mode=mode, skip_empty=False,
                                                **kw)
    assert np.abs(rgba - dense_rgba).max() <= 1e-6
    np.testing.assert_array_equal(other, dense_depth)
    assert_same_depth(depth, other, min(vevm.spacing) * BU)
