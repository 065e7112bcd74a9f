"""VolPack (Lacroute's shear-warp library, Debian ``libvolpack1-dev``) driven as a benchmark peer.

The C driver ``volpack_driver.c`` beside this file does the VolPack calls; this module builds it,
turns our scene (densities, grid placement, :class:`Camera`, :class:`TransferFunction`) into the
driver's inputs, runs it in a subprocess and converts its image to ours.

How the scene is matched
------------------------
- **Volume**: the densities as unsigned 16-bit values ``d - d_min`` (integers: both benchmark
  volumes are integer data), x fastest, so VolPack's x, y, z are our index axes.
- **View**: VolPack's view matrix is ``viewport · PROJECT · VIEW · MODEL · prematrix`` where the
  prematrix maps voxel index ``v`` to ``(v - len/2) / maxdim`` (``vp_view.c``). VIEW and PROJECT
  are set to identity and MODEL to ``clip · world_to_camera · grid_to_world · prematrix⁻¹``: the
  exact orthographic projection of our camera, voxel centres at our voxel-centre indices, clip x,
  y over the camera's view plane and clip z from -1 (nearest corner of the volume) to +1
  (farthest). The pixel-centre and voxel-centre conventions and the row order were checked
  against our reference renderer (``VOXEL_OFFSET``, ``PIXEL_OFFSET``, ``FLIP_ROWS`` below).
  VolPack has no perspective projection (``FactorPerspectiveView`` is stubbed out).
- **Transfer function**: VolPack classifies voxels (pre-classification) with an opacity table
  indexed by density and colours them with a lookup "shader" table indexed by the same density
  (no lighting): the TF's straight RGB at every integer density, scaled to VolPack's 0..255. VolPack
  corrects opacity per view with ``α' = 1 - (1 - α)^f``, ``f = sqrt(1 + s_i² + s_j²)``
  (``vp_view.c``, ``ComputeAffineOpacityCorrection``: it counts index units along the ray, ignoring
  physical spacing). The driver is given ``α = 1 - (1 - α_TF)^(L / (f · Δ0))`` with ``L`` the
  physical distance (mm) between consecutive slice samples along a ray, so after VolPack's own
  correction each sample has exactly our ``1 - (1 - α_TF)^(L/Δ0)``, also for anisotropic voxels.
  VolPack stores opacities as 8 bits and writes 8-bit RGBA.
- **Output**: VolPack's RGBA bytes are premultiplied colour and coverage (its man page
  ``vpSetImage``: colour += C·(1 - alpha) composites over a background); divided by 255.
"""

import json
import os
import shutil
import subprocess
import tempfile
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
SOURCE = HERE / "volpack_driver.c"
DEFAULT_BINARY = HERE / "build" / "volpack_driver"

# Conventions verified against the reference renderer (brainsmall, mri preset, oblique view at
# 256x256, principal axis y): VolPack's voxel index v holds our voxel-centre index v (no
# half-voxel offset: voxel values are samples at integer indices, as ours), VolPack samples image
# pixel (x, y) at viewport coordinate (x + PIXEL_OFFSET, y + PIXEL_OFFSET), and its scanline 0 is
# the bottom of the image (viewport y = 0), so rows are flipped to get row 0 at the top.
# MAE of premultiplied RGBA against the reference: 0.00208 with (voxel 0, pixel 0, flipped);
# 0.0024-0.0047 with a quarter or half pixel or voxel offset; 0.016-0.020 without the flip.
VOXEL_OFFSET = 0.0
PIXEL_OFFSET = 0.0
FLIP_ROWS = True


def build(binary=DEFAULT_BINARY, cc="gcc"):
    """Compile the driver against Debian's static ``libvolpack.a`` (or the shared library)."""
    binary = Path(binary)
    binary.parent.mkdir(parents=True, exist_ok=True)
    static = [p for p in ("/usr/lib/x86_64-linux-gnu/libvolpack.a", "/usr/lib/libvolpack.a")
              if os.path.exists(p)]
    lib = static[:1] if static else ["-lvolpack"]
    cmd = [cc, "-O2", "-Wall", "-o", str(binary), str(SOURCE)] + lib + ["-lm"]
    subprocess.run(cmd, check=True)
    return binary


def available(binary=DEFAULT_BINARY):
    """Why VolPack cannot run here (a string), or None when it can."""
    if not Path(binary).exists():
        if shutil.which("gcc") is None:
            return "gcc not found"
        if not os.path.exists("/usr/include/volpack.h"):
            return "libvolpack1-dev not installed (apt-get install libvolpack1-dev)"
        try:
            build(binary)
        except (subprocess.CalledProcessError, OSError) as exc:
            return f"building the VolPack driver failed: {exc}"
    return None


def factorization(grid_to_world, spacing, camera):
    """VolPack's principal axis and shears for this view, computed as ``vp_view.c`` does, and
    the physical distance (mm) between consecutive samples along a ray.

    Returns ``(axis, shear_i, shear_j, voxel_size, step_mm)``; ``voxel_size`` is VolPack's
    ``sqrt(1 + s_i² + s_j²)`` (index units per slice along a ray)."""
    g = np.asarray(grid_to_world, dtype=np.float64)[:3, :3]
    fwd = camera.forward
    # unit object vectors in image space: normalised |z| = |cos| of the angle to the view axis
    cosines = [abs(g[:, a] @ fwd) / np.linalg.norm(g[:, a]) for a in range(3)]
    x, y, z = cosines
    axis = (0 if x >= z else 2) if x >= y else (1 if y >= z else 2)
    d = np.linalg.solve(g, fwd)  # view direction in index units
    i_ax, j_ax = {0: (1, 2), 1: (2, 0), 2: (0, 1)}[axis]
    si, sj = -d[i_ax] / d[axis], -d[j_ax] / d[axis]  # sign is irrelevant below
    voxel_size = float(np.sqrt(1.0 + si * si + sj * sj))
    step_mm = float(np.linalg.norm(np.asarray(spacing) * d / d[axis]))
    return "xyz"[axis], float(si), float(sj), voxel_size, step_mm


def model_matrix(shape, grid_to_world, camera, voxel_offset=VOXEL_OFFSET,
                 pixel_offset=PIXEL_OFFSET):
    """VolPack's VP_MODEL matrix (VIEW and PROJECT identity) for our orthographic camera."""
    if not camera.is_ortho:
        raise ValueError("VolPack renders parallel projections only")
    g = np.asarray(grid_to_world, dtype=np.float64)
    m = camera.matrix_world
    view = np.eye(4)
    rinv = np.linalg.inv(m[:3, :3])
    view[:3, :3] = rinv
    view[:3, 3] = -rinv @ m[:3, 3]
    # axial depth range of the volume's box (for clip z: -1 nearest, +1 farthest)
    n = np.asarray(shape, dtype=np.float64)
    corners = np.array([[a, b, c, 1.0] for a in (-0.5, n[0] - 0.5) for b in (-0.5, n[1] - 0.5)
                        for c in (-0.5, n[2] - 0.5)])
    cam = corners @ (view @ g).T
    depth = -cam[:, 2]
    dmin, dmax = depth.min(), depth.max()
    xmin, xmax, ymin, ymax = camera.viewplane
    w, h = camera.width, camera.height
    clip = np.zeros((4, 4))
    clip[0, 0] = 2.0 / (xmax - xmin)
    clip[0, 3] = -2.0 * xmin / (xmax - xmin) - 1.0
    clip[1, 1] = 2.0 / (ymax - ymin)
    clip[1, 3] = -2.0 * ymin / (ymax - ymin) - 1.0
    span = max(dmax - dmin, 1e-12) * 1.02
    mid = 0.5 * (dmax + dmin)
    clip[2, 2] = -2.0 / span  # camera z = -depth
    clip[2, 3] = -2.0 * mid / span
    clip[3, 3] = 1.0
    # VolPack samples pixel x at viewport coordinate x + pixel_offset; ours sit at x + 0.5
    shift = np.eye(4)
    # (VolPack's scanline r lies at viewport y = r + pixel_offset, y up: our row h - 1 - r)
    shift[0, 3] = -2.0 * (0.5 - pixel_offset) / w
    shift[1, 3] = -2.0 * (0.5 - pixel_offset) / h
    # VolPack's voxel index v holds our voxel-centre index v - voxel_offset
    to_index = np.eye(4)
    to_index[:3, 3] = -voxel_offset
    maxdim = float(n.max())
    pre_inv = np.eye(4)
    pre_inv[:3, :3] *= maxdim
    pre_inv[:3, 3] = 0.5 * n
    return shift @ clip @ view @ g @ to_index @ pre_inv


def tables(densities, tf, dmin, field_max, voxel_size, step_mm):
    """Opacity (pre-compensated for VolPack's own correction) and straight RGB tables."""
    values = dmin + np.arange(field_max + 1, dtype=np.float64)
    straight = tf.evaluate(values)
    a_tf = np.clip(straight[:, 3], 0.0, 1.0)
    exponent = step_mm / (voxel_size * tf.unit_length_mm)
    opacity = 1.0 - np.power(1.0 - a_tf, exponent)
    # VolPack's shading tables hold colours in 0..255 (man vpShadeTable)
    return opacity.astype(np.float32), (255.0 * straight[:, :3]).astype(np.float32)


def render(densities, grid_to_world, spacing, camera, tf, *, frames=5, min_voxel_opacity=0.0,
           max_ray_opacity=1.0, binary=DEFAULT_BINARY, workdir=None,
           voxel_offset=VOXEL_OFFSET, pixel_offset=PIXEL_OFFSET, flip_rows=FLIP_ROWS):
    """Render with VolPack; returns a dict with ``rgba`` (H, W, 4) premultiplied float32 (row 0
    at the top), ``classify_s``, ``frames_s``, ``best_s``, ``view_axis``, ``max_rss_kb`` and the
    factorization we computed for the opacity correction."""
    d = np.asarray(densities)
    if not np.issubdtype(d.dtype, np.integer):
        raise ValueError("VolPack peer: integer densities expected")
    dmin = int(d.min())
    shifted = (d.astype(np.int64) - dmin)
    field_max = max(int(shifted.max()), 1)
    if field_max > 65535:
        raise ValueError("VolPack peer: density range exceeds 16 bits")
    axis, si, sj, voxel_size, step_mm = factorization(grid_to_world, spacing, camera)
    opacity, rgb = tables(d, tf, dmin, field_max, voxel_size, step_mm)
    model = model_matrix(d.shape, grid_to_world, camera, voxel_offset, pixel_offset)
    nx, ny, nz = d.shape
    with tempfile.TemporaryDirectory(dir=workdir) as tmp:
        tmp = Path(tmp)
        np.ascontiguousarray(shifted.astype("<u2").T).tofile(tmp / "volume.u16")  # x fastest
        np.concatenate([opacity, rgb.ravel()]).astype("<f4").tofile(tmp / "table.f32")
        model.astype("<f8").tofile(tmp / "model.f64")
        cmd = [str(binary), str(tmp / "volume.u16"), str(nx), str(ny), str(nz), str(field_max),
               str(tmp / "table.f32"), str(tmp / "model.f64"), str(camera.width),
               str(camera.height), str(int(frames)), repr(float(min_voxel_opacity)),
               repr(float(max_ray_opacity)), str(tmp / "image.rgba")]
        proc = subprocess.run(cmd, capture_output=True, text=True, check=False)
        if proc.returncode != 0:
            raise RuntimeError(f"volpack_driver failed ({proc.returncode}): {proc.stderr.strip()}")
        info = json.loads(proc.stdout)
        raw = np.fromfile(tmp / "image.rgba", dtype=np.uint8)
    img = raw.reshape(camera.height, camera.width, 4).astype(np.float32) / 255.0
    if flip_rows:
        img = img[::-1].copy()
    info.update(rgba=img, our_view_axis=axis, shear=(si, sj), voxel_size=voxel_size,
                step_mm=step_mm, field_max=field_max)
    if info.get("view_axis") != axis:
        info["warning"] = f"VolPack chose axis {info.get('view_axis')}, we computed {axis}"
    return info
