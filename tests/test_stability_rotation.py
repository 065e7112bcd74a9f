"""Stability under rotation (``../shared/design/notes/dvr_evaluation.md`` §7.8), at CI size.

- S1: Marschner–Lobb rotated about y through 45° (the principal-axis switch of shear-warp and of
  axis-aligned splatting): per-frame RMSE to the reference, popping index, bias jump.
- S2: the same across a switch while the view turns about the (1, 1, 1) diagonal, where the
  slice family changes between all three axes.
- S6: a thin plate and a spherical shell seen from 0° to 90°: integrated alpha follows the
  reference's and no pixel the reference shows (alpha > 0.05) drops out.

Every method renders every frame, and so does the reference; the measures are
:mod:`volumeevm_addon.metrics`. Bounds are the measured values with modest headroom (stated at
each). ``raycast_navigate`` renders the same image as ``raycast`` and is not repeated.
"""

import numpy as np
import pytest

from render_helpers import centre, reference
from volumeevm_addon import BLENDER_UNITS_PER_MM as BU
from volumeevm_addon import Camera, TransferFunction, VolumeEVM, grid_to_world, phantoms, render
from volumeevm_addon.metrics import bias_jump, popping_index, rmse, temporal_errors

RES = 48
# Shear-warp's default (VolPack's one sample per slice, pre-classified) and the setting that
# removes its popping at the switch (module docstring of _shear_warp).
METHODS = {"shear_warp": ("shear_warp", {}),
           "shear_warp_fine": ("shear_warp", {"slices_per_voxel": 2}),
           "splat": ("splat", {}), "raycast": ("raycast", {})}
# Splatting's switch between sheet families, in S1 only: the hard switch (blend 0) and three
# sub-slabs per slab (linear reconstruction along the principal axis), alone and together.
SPLAT_SWITCH = {"splat_hard": ("splat", {"blend": 0.0}), "splat_fine": ("splat", {"substeps": 3}),
                "splat_hard_fine": ("splat", {"blend": 0.0, "substeps": 3})}
PULSE = TransferFunction([(0.0, 1, 1, 1, 0), (0.4, 1, 1, 1, 0), (0.5, 1, 0.8, 0.6, 0.3),
                          (0.6, 1, 1, 1, 0), (1.0, 1, 1, 1, 0)])
RAMP = TransferFunction([(0.0, 0.9, 0.7, 0.5, 0.0), (1.0, 0.9, 0.7, 0.5, 0.9)])


def orbit(vevm, g, direction, up):
    """Orthographic ``RES``^2 camera looking at the grid's centre from ``direction``."""
    c = centre(vevm, g)
    size = float(np.linalg.norm(np.array(vevm.shape) * vevm.spacing)) * BU
    d = np.asarray(direction, dtype=np.float64)
    return Camera.look_at(c + d / np.linalg.norm(d) * size, c, up, ortho_scale=1.02 * size,
                          resolution_x=RES, resolution_y=RES, clip_start=1e-4)


def sweep(vevm, tf, directions, up, methods=METHODS):
    """Images of every method and the reference, ``{name: (frames, H, W, 4)}``."""
    g = grid_to_world(vevm.spacing, (0.0, 0.0, 0.0))
    cams = [orbit(vevm, g, d, up) for d in directions]
    out = {"reference": np.array([reference(vevm, cam, tf, g)[0] for cam in cams])}
    for name, (method, options) in methods.items():
        out[name] = np.array([render(vevm, cam, tf, method=method, **options)[0]
                              for cam in cams])
    return out


def measures(images, angles, at):
    ref = images["reference"]
    return {name: {"rmse": max(rmse(a, b) for a, b in zip(frames, ref)),
                   "popping": popping_index(frames, ref),
                   "bias_jump": abs(bias_jump(angles, frames, ref, at=at)),
                   "temporal": float(temporal_errors(frames, ref).max())}
            for name, frames in images.items() if name != "reference"}


# ---------------------------------------------------------------------------- S1, S2
# 0.5 degree steps over 42..48: the switch and three frames either side of it, enough for the
# popping index (largest change against the reference's median change) and the bias jump.
S1_ANGLES = np.linspace(42.0, 48.0, 13)


@pytest.fixture(scope="module")
def ml():
    return VolumeEVM.from_volume(phantoms.marschner_lobb(41), -1.0)


@pytest.fixture(scope="module")
def s1(ml):
    th = np.radians(S1_ANGLES)
    dirs = np.stack([np.sin(th), np.zeros_like(th), np.cos(th)], axis=1)
    images = sweep(ml, PULSE, dirs, up=(0.0, 1.0, 0.0), methods=METHODS | SPLAT_SWITCH)
    return measures(images, S1_ANGLES, 45.0)


# Measured (ML 41^3, pulse, 48^2, 42..48 degrees): max per-frame RMSE, popping index, |bias jump|:
# shear-warp 0.048, 2.92, 0.016 (2 slices per voxel: 0.047, 1.34, 0.004), splatting 0.016,
# 1.63, 0.0001 (its sheet families cross-faded near the switch; a hard switch measured 0.029,
# 3.4, 0.017), ray casting 0.0023, 1.18, 0.0001. (Over 40..50 degrees in 21 frames shear-warp
# measured the same.)
S1_BOUNDS = {"shear_warp": (0.055, 3.5, 0.022), "shear_warp_fine": (0.053, 1.8, 0.007),
             "splat": (0.02, 2.0, 0.002), "raycast": (0.003, 2.0, 0.001)}


@pytest.mark.parametrize("method", METHODS)
def test_s1_rotation_through_45_degrees(s1, method):
    assert _within(s1[method], S1_BOUNDS[method])


# Measured, max per-frame RMSE / popping index / |bias jump| / max temporal error: hard switch
# 0.026 / 2.36 / 0.010 / 0.031 against the cross-fade's 0.016 / 1.63 / 0.0001 / 0.0051; three
# sub-slabs 0.0081 / 1.12 / 0.0002 / 0.0016, with the hard switch 0.011 / 1.03 / 0.0059 / 0.011.
def test_s1_splat_cross_fade_and_sub_slabs(s1):
    """The cross-fade between sheet families is what keeps splatting from popping at the
    switch (the hard switch jumps in luminance and frame to frame), and three sub-slabs per slab
    lower the error and the frame-to-frame change further, again only with the cross-fade."""
    hard, soft = s1["splat_hard"], s1["splat"]
    assert hard["popping"] > 2.1 and hard["bias_jump"] > 0.006 and hard["temporal"] > 0.02
    assert soft["rmse"] < hard["rmse"] and soft["temporal"] < 0.007
    fine, hard_fine = s1["splat_fine"], s1["splat_hard_fine"]
    assert fine["rmse"] < 0.01 and fine["popping"] < 1.4 and fine["bias_jump"] < 0.001
    assert fine["temporal"] < 0.0025 < 0.008 < hard_fine["temporal"]


def _within(got, bound):
    return got["rmse"] < bound[0] and got["popping"] < bound[1] and got["bias_jump"] < bound[2]


def diagonal_view(phi):
    """View direction at ``phi`` degrees on the circle of directions perpendicular to the
    (1, 1, 1) diagonal: its largest component (the principal axis) changes every 60 degrees,
    through x, y and z."""
    u = np.array([1.0, -1.0, 0.0]) / np.sqrt(2)
    v = np.array([1.0, 1.0, -2.0]) / np.sqrt(6)
    p = np.radians(phi)
    return np.cos(p) * u + np.sin(p) * v


# |x| = |z| at phi = 60 degrees (the switch from x to z slices): 57..63 in 1 degree steps.
S2_SWITCH = 60.0
S2_ANGLES = np.linspace(S2_SWITCH - 3.0, S2_SWITCH + 3.0, 7)


@pytest.fixture(scope="module")
def s2(ml):
    dirs = [diagonal_view(phi) for phi in S2_ANGLES]
    return measures(sweep(ml, PULSE, dirs, up=(1.0, 1.0, 1.0)), S2_ANGLES, S2_SWITCH)


# Measured at 1 degree steps over 57..63: shear-warp 0.054, 1.99, 0.011 (2 slices per voxel:
# 0.051, 3.27, 0.0045: its jumps are not at the switch but image-plane aliasing of the
# intermediate image, one ray per voxel; at 0.5 degree steps its popping index reached 5.0),
# splatting 0.012, 1.31, 0.001, ray casting 0.0021, 1.37, 0.0002.
S2_BOUNDS = {"shear_warp": (0.06, 4.5, 0.014), "shear_warp_fine": (0.057, 6.0, 0.005),
             "splat": (0.016, 1.8, 0.002), "raycast": (0.003, 2.0, 0.001)}


@pytest.mark.parametrize("method", METHODS)
def test_s2_rotation_about_the_diagonal(s2, method):
    assert _within(s2[method], S2_BOUNDS[method])


# ---------------------------------------------------------------------------- S6
S6_ANGLES = np.linspace(0.0, 90.0, 7)


def thin_objects():
    """A one-voxel plate perpendicular to x through the centre and a one-voxel spherical shell
    of radius 12 voxels, 33^3, antialiased (:mod:`volumeevm_addon.phantoms`, values in
    [0, 1])."""
    shape = (33, 33, 33)
    return {"plate": VolumeEVM.from_volume(phantoms.thin_plate(shape, (1.0, 0.0, 0.0)), -1.0),
            "shell": VolumeEVM.from_volume(phantoms.shell(shape, 12.0), -1.0)}


@pytest.fixture(scope="module")
def s6():
    """Per object and method: max relative deviation of integrated alpha from the
    reference's over the sweep, and the number of drop-out pixels."""
    out = {}
    for name, vevm in thin_objects().items():
        th = np.radians(S6_ANGLES)  # 0: face-on (along the plate's normal x), 90: edge-on
        dirs = np.stack([np.cos(th), np.sin(th), np.zeros_like(th)], axis=1)
        images = sweep(vevm, RAMP, dirs, up=(0.0, 0.0, 1.0))
        ref = images["reference"]
        total = ref[..., 3].sum(axis=(1, 2))
        shown = ref[..., 3] > 0.05
        out[name] = {m: {"deviation": float(np.abs(f[..., 3].sum(axis=(1, 2)) / total - 1).max()),
                         "dropouts": int((shown & (f[..., 3] <= 0)).sum())}
                     for m, f in images.items() if m != "reference"}
    return out


# Max relative deviation of integrated alpha, measured plate / shell: shear-warp 0.62 / 0.049
# (2 slices per voxel: 0.62 / 0.054), splatting 0.16 / 0.009, ray casting 0.058 / 0.003.
# Drop-outs: shear-warp's default 8 pixels on the shell at 45 degrees (one sample per slice
# then reads only voxel centres on the ray's diagonal, sqrt(2) apart, and misses the shell where
# it grazes; 28 on the plate at 10-degree steps); with 2 slices per voxel none.
# Shear-warp's 0.62 is a known failure (F14), not yet fixed: the plate exactly edge-on (90
# degrees; 85-89.9: 0.16-0.40) lies between the intermediate rays, which sit on voxel centres,
# so the composited image is 0, 1, 0 across it and the warp's tent holds half the reference's
# saturated band of about 1.9 voxels. Warping optical depth instead of opacity removes it
# (0.002 without early termination) but adds +0.004 of opacity bias on Marschner-Lobb and breaks
# early termination's error bound; intermediate_scale 2 leaves 0.24 at 90 degrees.
S6_BOUNDS = {"shear_warp": (0.7, 0.06), "shear_warp_fine": (0.7, 0.065),
             "splat": (0.2, 0.012), "raycast": (0.07, 0.004)}


@pytest.mark.parametrize("method", METHODS)
def test_s6_thin_plate_and_shell(s6, method):
    plate, shell = s6["plate"][method], s6["shell"][method]
    assert plate["deviation"] < S6_BOUNDS[method][0] and shell["deviation"] < S6_BOUNDS[method][1]
    dropouts = plate["dropouts"] + shell["dropouts"]
    assert dropouts <= 12 if method == "shear_warp" else dropouts == 0
