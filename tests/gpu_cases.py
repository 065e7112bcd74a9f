"""The scenes the GPU tests render: built the same way by the GPU runner (a Blender process,
``gpu_runner.py``) and by the tests that compare its images with the NumPy reference."""

import json

import numpy as np

from render_helpers import camera, const_tf
from volumeevm_addon import EVM, TransferFunction, VolumeEVM, grid_to_world, phantoms

CT_CROP = (slice(64, 192), slice(48, 176), slice(30, 80))  # 128 x 128 x 50 voxels of the CT head
BLOB = dict(centres=[(20.0, 20.0, 20.0)], sigmas=4.0, amplitudes=1.0)
BLOB_K = 2 / (4.0 * np.sqrt(np.pi))  # peak optical depth 2
BOX = dict(lo=(8, 6, 9), hi=(24, 20, 21))
BOX_ALPHA = 0.1


def box():
    vol = phantoms.box((32, 28, 30), density=1.0, spacing=(0.8, 1.0, 1.3), **BOX)
    return VolumeEVM.from_volume(vol, 0.5)


def blobs():
    return VolumeEVM.from_volume(phantoms.gaussian_blobs((40, 40, 40), **BLOB), 1e-6)


def head(data_dir):
    meta = json.loads((data_dir / "ct_head_invesalius.json").read_text())
    array = np.load(data_dir / "ct_head_invesalius.npy")[CT_CROP]
    return VolumeEVM.from_array(array, 300, spacing=meta["spacing_mm"])


def long_box():
    """``(vevm, camera, tf, options)``: a box 16,400 voxels long, longer than a GPU's 3D
    textures (llvmpipe's 2048, most GPUs' 16,384), seen from the side at its full level."""
    vol = phantoms.box((16400, 4, 4), density=1.0, spacing=(0.1, 10.0, 10.0), lo=(0, 1, 1),
                       hi=(16400, 3, 3))
    v = VolumeEVM.from_volume(vol, 0.5)
    g = grid_to_world(v.spacing, v.origin)
    cam = camera("ORTHO", g, v, (0.0, -0.5, 0.0), 0.2, res=(64, 32))
    return v, cam, const_tf(0.3), {"level": "full", "step_mm": 0.05, "termination": 1.0}


def irregular():
    """Random densities in a random region (half its voxels): the region's boundary policy
    everywhere."""
    rng = np.random.default_rng(3)
    shape = (17, 15, 12)
    dens = rng.uniform(-200.0, 900.0, shape)
    mask = rng.uniform(size=shape) < 0.5
    return VolumeEVM(EVM.from_mask(mask), dens[mask], shape=shape, spacing=(0.8, 1.0, 1.3))


def two_labels():
    """Red label 1 beside blue label 3 (label 2, green, absent), both in one band."""
    a = np.zeros((14, 12, 10), np.uint8)
    a[2:7, 2:10, 2:8] = 1
    a[7:12, 2:10, 2:8] = 3
    a[5:9, 4:7, 0:2] = 3
    return VolumeEVM.from_array(a, 1, upper=3, spacing=(0.8, 1.0, 1.3))


RED_GREEN_BLUE = {1: (1.0, 0.0, 0.0, 0.6), 2: (0.0, 1.0, 0.0, 0.6), 3: (0.0, 0.0, 1.0, 0.6)}
LIVER_COLOURS = {84: (1.0, 0.0, 0.0, 0.3), 85: (0.0, 1.0, 0.0, 0.6), 127: (0.0, 0.0, 1.0, 0.2),
                 255: (1.0, 1.0, 0.0, 0.05)}


def liver(data_dir):
    """The liver label map at every 5th voxel in x and y, 3rd in z, all labels in one band."""
    meta = json.loads((data_dir / "seg_liver_cgal.json").read_text())
    a = np.load(data_dir / "seg_liver_cgal.npy")[::5, ::5, ::3]
    return VolumeEVM.from_array(a, 1, upper=255,
                                spacing=tuple(np.array(meta["spacing_mm"]) * (5, 5, 3)))


def ramp_tf():
    return TransferFunction([(-200, 0.1, 0.3, 0.9, 0.0), (300, 1.0, 0.6, 0.2, 0.5),
                             (900, 1.0, 1.0, 1.0, 0.9)])


HEAD_STEP_MM = 0.48
"""The CT head's step at the Render settings' quality 1 (half its smallest voxel, rounded)."""

SKULL_TF = ((2.0, 0.9, 0.8, 0.7, 0.0), (3.0, 0.95, 0.85, 0.7, 0.15), (5.5, 1.0, 1.0, 1.0, 0.6))
"""The sample skull's bone (its densities run 0 .. 5.4): a transfer function's points."""


def depth_plane(cam, vevm, g):
    """Axial depth (H, W) of a plane tilted across the volume: it cuts every ray through it."""
    centre = g[:3, :3] @ ((np.array(vevm.shape) - 1) / 2.0) + g[:3, 3]
    a = float(cam.axial_depth(centre))
    h, w = cam.shape
    ramp = np.linspace(-1.0, 1.0, w)[None, :] + 0.5 * np.linspace(-1.0, 1.0, h)[:, None]
    return a + 0.008 * ramp


def case(name, data_dir):
    """``(vevm, camera, tf, options)`` of the case ``name`` (one of :data:`CASES`); options are
    ``render``'s keywords."""
    kind = "PERSP" if name.endswith("persp") or "_persp_" in name else "ORTHO"
    if name.startswith("box"):
        v = box()
        g = grid_to_world(v.spacing, v.origin)
        cam = camera(kind, g, v, (0.03, -0.05, 0.02), 0.045, res=(48, 40))
        return v, cam, const_tf(BOX_ALPHA), {"step_mm": 0.45, "termination": 1.0}
    if name.startswith("blobs"):
        v = blobs()
        g = grid_to_world(v.spacing, v.origin)
        offset = (0.05, -0.086, 0.0) if kind == "ORTHO" else (0.03, -0.05, 0.02)
        tf = phantoms.extinction_tf(BLOB_K, 1.0, rgb=(1.0, 0.5, 0.25))
        return v, camera(kind, g, v, offset, 0.03, res=(48, 48)), tf, {"termination": 1.0}
    if name.startswith("head"):
        v = head(data_dir)
        g = grid_to_world(v.spacing, v.origin)
        cam = camera(kind, g, v, (0.15, -0.25, 0.1), 0.14, res=(64, 64), lens_mm=90.0,
                     clip_end=5.0)
        options = {"termination": 1.0}
        if name.endswith("_noskip"):
            options["skip_empty"] = False
        if name.endswith("_term"):
            options["termination"] = 0.99
        if name.endswith("_depth"):
            options["depth_in"] = depth_plane(cam, v, g)
        if name.endswith("_shaded"):
            options["shading"] = True
        if "_xray" in name:
            return v, cam, None, {**options, "mode": "xray", "xray_scale": 3e-4,
                                  "xray_offset": 0.0}
        if "_mip" in name:
            options["mode"] = "mip"
        return v, cam, TransferFunction.preset("ct_bone"), options
    if name.startswith("labels"):
        v = liver(data_dir) if "_liver" in name else two_labels()
        g = grid_to_world(v.spacing, v.origin)
        scale = float(np.max(np.array(v.shape) * v.spacing)) * 1.2e-3 if "_liver" in name \
            else 0.02
        cam = camera(kind, g, v, (0.3 * scale, -0.4 * scale, 0.25 * scale), scale, res=(40, 32),
                     lens_mm=50.0)
        colours = LIVER_COLOURS if "_liver" in name else RED_GREEN_BLUE
        return v, cam, TransferFunction.categorical(colours), {"termination": 1.0}
    if name.startswith("irregular"):
        v = irregular()
        g = grid_to_world(v.spacing, v.origin)
        cam = camera(kind, g, v, (0.02, -0.03, 0.015), 0.03, res=(40, 36))
        mode = name.split("_")[1]
        options = {"mode": mode, "step_mm": 0.2, "termination": 1.0}
        if "_shaded" in name:
            options["shading"] = True
        if mode == "xray":
            return v, cam, None, {**options, "xray_scale": 2e-3, "xray_offset": 0.0}
        return v, cam, ramp_tf(), options
    raise KeyError(name)


CASES = ("box_ortho", "box_persp", "blobs_ortho", "blobs_persp", "head_ortho", "head_persp",
         "head_persp_noskip", "head_persp_term", "head_persp_depth", "head_persp_xray",
         "head_persp_mip", "head_persp_shaded", "irregular_over_ortho", "irregular_under_ortho",
         "irregular_over_shaded_ortho", "irregular_xray_persp", "irregular_mip_persp",
         "labels_ortho", "labels_persp", "labels_liver_ortho", "labels_liver_persp")
"""Every case the runner renders."""
