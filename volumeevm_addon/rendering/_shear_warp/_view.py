"""Shear-warp's view factorization: the principal axis, the passes, the per-slice maps from the
intermediate image to the slices, the warp's map and the per-ray sample spacing.

This is the stage VolPack keeps in ``vp_view.c``: it reads the camera and the region's extent
(never a density) and gives the compositing (:mod:`._composite`) and the warp (:mod:`._warp`)
the numbers they loop over (:class:`View`).

1. **Principal axis** ``c``: the grid axis whose world direction is most parallel to the view
   (orthographic: the camera's forward vector; perspective with the eye outside the region's
   bounding box: the eye-to-region-centre vector, among the axes along which the eye is outside
   the box, so that every ray crosses the slices the same way), ties to x, then y, then z
   (VolPack ``vp_view.c``). A perspective eye inside the box is rendered in up to six passes
   (:func:`passes`), the rays grouped by the axis and sign most parallel to each, each pass
   compositing the slices beyond the eye (Lacroute's split of the view into pyramids). The
   slices ``c = s`` (voxel-centre planes) are read front to back (``"over"``, ``"xray"``,
   ``"mip"``) or back to front (``"under"``).
2. **Intermediate image.** Its pixel ``(p, q)`` is the ray through the point ``(p, q)`` (plus an
   integer origin) of a reference plane ``c = c_ref`` in index space; its two axes are the
   in-slice axes of the table order (:data:`volumeevm_addon.model._densities.TABLE_ORDERS`):
   rows are the slices' scanlines, columns run along them. The ray meets slice ``s`` at
   in-slice index coordinates ``x = α_s p + β_s`` (and likewise ``y``). Orthographic:
   ``α_s = 1`` and ``β_s = (s - c_ref) d_a / d_c`` (the shear): the slice is *translated*, so
   the bilinear weights are the same for the whole slice (VolPack ``vp_renderA.c``).
   Perspective: ``α_s = (s - E_c)/(c_ref - E_c)`` with the eye ``E``, a per-slice uniform scale
   about the eye (Lacroute & Levoy 1994, §4; Schulze et al. 2001); the reference plane is the
   region's far end, so ``α_s <= 1`` (slices are magnified, never minified).
   ``intermediate_scale = k`` divides ``α_s`` by ``k``.
3. **The warp's map**: where every final pixel's ray meets the reference plane, as a sum of a
   per-row and a per-column term (orthographic: an affine map) or per pixel (perspective: a
   homography, :func:`ray_points`, compiled); its extent bounds the intermediate image.
4. **Sample spacing**: the physical distance between consecutive slices along the ray,
   ``Δ = |diag(spacing) · d / d_c|`` mm (``sqrt(1 + s_a² + s_b²)`` slices in VolPack's
   isotropic case); perspective rays have their own, as a ratio to the central ray's.

The image and depth do not depend on where the intermediate image starts (:meth:`View.extent`):
its origin is an integer that moves array indices only; fractions, taps and depths are computed
in absolute intermediate coordinates. (Rounding ``β + origin`` instead gave a fraction of 1e-15
on the region's path and 0 on the dense path, whose images start elsewhere.)
"""

import math

import numpy as np

from ..._errors import VolumeEVMError
from ..._jit import kernel, parallel_map
from ...model._densities import TABLE_ORDERS
from ...model._volume import transform

__all__ = ["View", "passes", "ray_points"]

_MAX_INTERMEDIATE = 1 << 26
"""Largest intermediate image (pixels); only extreme perspective close-ups come near it."""
_RAY_CHUNK = 1 << 14
"""Final pixels per task (in whole rows) of the perspective rays' points."""


class View:
    """The factorization of one view: principal axis, slice order, per-slice maps from the
    intermediate image to slice coordinates, the warp and the per-ray sample spacing."""

    def __init__(self, vevm, camera, g, layout, scale, axis, step, rays):
        self.scale = scale  # intermediate pixels per voxel along each in-slice axis
        self.inv = np.linalg.inv(g)
        rot = self.inv[:3, :3].T
        self.axis = axis
        self.light = self.view_direction(vevm, camera, g)
        a, b = ("xyz".index(ch) for ch in TABLE_ORDERS[axis][1:])
        self.abc = (a, b, axis)
        self.ortho = camera.is_ortho
        self.constant = self.ortho and scale == 1.0  # slices are only translated
        nc = vevm.shape[axis]
        if self.ortho:
            forward = -camera.matrix_world[:3, 2] @ rot  # the rays' index-space direction
            self.step = 1 if forward[axis] > 0 else -1
            self.c_ref = 0.0
            self.slope = forward / forward[axis]  # index-space ray per unit step along c
            self.rows, self.cols, seen = self.ortho_plane(camera, rot)
            ok = True
        else:
            self.eye = self.inv[:3, :3] @ camera.position + self.inv[:3, 3]
            self.step = step
            self.c_ref = nc - 0.5 if self.step > 0 else -0.5
            self.pq, ok, seen = self.persp_plane(camera, rot, rays)
        self.rays_ok = ok
        lo_box = layout.runs.box
        used = np.flatnonzero(lo_box[:, 1] > lo_box[:, 0])
        if not self.ortho:
            lam = (used - self.eye[axis]) / (self.c_ref - self.eye[axis])
            used = used[lam > 0]
        # Slices front to back.
        self.slices = used if self.step > 0 else used[::-1]
        self.empty = self.slices.size == 0 or not np.any(ok)
        if self.empty:
            return
        # Extent: the region's footprint over all slices, within the image's footprint.
        alpha, beta_a, beta_b = self.slice_maps(self.slices.astype(np.float64))
        bx = lo_box[self.slices]
        foot = [((bx[:, 0] - 1 - beta_a) / alpha).min(), ((bx[:, 1] - beta_a) / alpha).max(),
                ((bx[:, 2] - 1 - beta_b) / alpha).min(), ((bx[:, 3] - beta_b) / alpha).max()]
        img = [seen[0] - 1, seen[1] + 2, seen[2] - 1, seen[3] + 2]
        self.origin, self.size = self.extent(foot, img)
        if self.size[0] * self.size[1] == 0:
            self.empty = True
            return
        if self.size[0] * self.size[1] > _MAX_INTERMEDIATE:
            raise VolumeEVMError(
                f"camera: the intermediate image would have {self.size[0]}x{self.size[1]} "
                "pixels (a perspective camera too close to the volume for shear-warp)")
        # Axial depth as an affine function of index-space points.
        basis = np.vstack([np.zeros(3), np.eye(3)])
        dep = camera.axial_depth(basis @ g[:3, :3].T + g[:3, 3])
        self.depth0, self.depth_grad = dep[0], dep[1:] - dep[0]
        # Physical length (mm) per step of one slice along each intermediate pixel's ray.
        sp = np.asarray(vevm.spacing, dtype=np.float64)
        if self.ortho:
            self.delta = float(np.linalg.norm(sp * self.slope))
            self.ratio = None
        else:
            p = self.origin[0] + np.arange(self.size[0])
            q = self.origin[1] + np.arange(self.size[1])
            delta = self.ray_step(p[:, None], q[None, :], sp)
            # The table's step: the central ray's nearest intermediate pixel (the centre of the
            # rays' footprint if the central ray is not in this pass).
            centre = np.array(camera.shape) // 2
            k = centre[0] * camera.shape[1] + centre[1]
            pc = self.pq[:, k] if ok[k] else np.array([seen[0] + seen[1], seen[2] + seen[3]]) / 2
            pc = np.floor(pc + 0.5)
            self.delta = float(self.ray_step(pc[0], pc[1], sp))
            self.ratio = (delta / self.delta).astype(np.float32)

    def ray_step(self, p, q, spacing):
        """Perspective: mm between consecutive slices along the ray through the absolute
        intermediate point ``(p, q)`` (arrays broadcast), for voxel ``spacing``."""
        a, b, c = self.abc
        span = self.c_ref - self.eye[c]
        va = ((p / self.scale - self.eye[a]) / span * spacing[a]) ** 2
        vb = ((q / self.scale - self.eye[b]) / span * spacing[b]) ** 2
        return np.sqrt(va + vb + spacing[c] ** 2)

    @staticmethod
    def extent(foot, img):
        """The intermediate image over the region's footprint ``foot`` within the image's
        footprint ``img`` (both ``(p min, p max, q min, q max)``, absolute intermediate
        coordinates): its origin, the absolute point of array index ``(0, 0)``, and its size.

        The origin is an integer applied to indices only: the samples' fractions, the warp's
        taps and the depths are computed in absolute coordinates, so that they do not depend
        on where the image starts (the region's path and the dense path start it differently).
        """
        p_lo, p_hi = math.floor(max(foot[0], img[0])), math.ceil(min(foot[1], img[1]))
        q_lo, q_hi = math.floor(max(foot[2], img[2])), math.ceil(min(foot[3], img[3]))
        return (np.array([p_lo, q_lo], np.int64),
                (max(p_hi - p_lo + 1, 0), max(q_hi - q_lo + 1, 0)))

    def ortho_plane(self, camera, rot):
        """Orthographic: the intermediate coordinates of every pixel's ray as the sum of a
        per-row term ``(H, 2)`` and a per-column term ``(W, 2)``, and their ``(p min, p max,
        q min, q max)``.

        The rays of :meth:`Camera.rays` start at ``m + x_j r + y_i u`` (pixel column ``j``,
        row ``i``) and share one direction, so each coordinate is a sum of a per-row and a
        per-column term (same values as transforming every ray, up to rounding).
        """
        a, b, c = self.abc
        h, w = camera.shape
        x, y = camera.pixel_centres()
        m = camera.matrix_world
        origin = m[:3, 3] @ rot + self.inv[:3, 3]
        right, up = m[:3, 0] @ rot, m[:3, 1] @ rot
        rows_pq, cols_pq = np.empty((h, 2)), np.empty((w, 2))
        extent = []
        for k, e in enumerate((a, b)):
            # Along the ray to c = c_ref: coordinate e moves by slope[e] per unit of c.
            along = np.eye(3)[e] - self.slope[e] * np.eye(3)[c]
            base = (origin @ along + self.slope[e] * self.c_ref) * self.scale
            rows = rows_pq[:, k] = base + y * ((up @ along) * self.scale)
            cols = cols_pq[:, k] = x * ((right @ along) * self.scale)
            extent += [rows.min() + cols.min(), rows.max() + cols.max()]
        return rows_pq, cols_pq, extent

    def persp_plane(self, camera, rot, rays):
        """Perspective: the intermediate coordinates of every pixel's ray, ``(2, H*W)`` before
        the origin shift (0 for rays that do not cross the slices towards the reference plane),
        which rays do (those of ``rays``, a flat mask or None for all) and their ``(p min,
        p max, q min, q max)`` (:func:`ray_points`)."""
        h, w = camera.shape
        x, y = camera.pixel_centres()
        m = camera.matrix_world
        right, up, back = m[:3, 0], m[:3, 1], m[:3, 2]
        axes = list(self.abc)
        terms = np.stack([right @ rot, up @ rot, -(back @ rot)], axis=1)[axes]
        gram = np.array([right @ right, up @ up, back @ back, right @ up, right @ back,
                         up @ back])
        eye = (m[:3, 3] @ rot + self.inv[:3, 3])[axes]
        pq, ok = np.empty((2, h * w)), np.empty(h * w, bool)
        rows = max(1, _RAY_CHUNK // w)
        only = np.zeros(0, bool) if rays is None else rays
        parts = parallel_map(
            lambda first: ray_points(first, min(first + rows, h), x, y, terms, gram, eye,
                                     self.c_ref, float(self.step), self.scale, only, pq, ok),
            [(first,) for first in range(0, h, rows)])
        parts = np.array(parts)
        seen = np.array([parts[:, 0].min(), parts[:, 1].max(), parts[:, 2].min(),
                         parts[:, 3].max()])
        return pq, ok, seen

    @staticmethod
    def principal_axis(vevm, camera, g):
        """The grid axis most parallel (in world space) to the viewing direction.

        Orthographic: to the camera's forward vector. Perspective, eye outside the region's
        bounding box: to the eye-to-centre vector, among the axes along which the eye is
        outside the box (so that every ray crosses the slices in one direction); eye inside
        the box: to the forward vector (:func:`passes` then splits the rays instead).
        """
        cols = g[:3, :3]
        forward = np.asarray(camera.forward, dtype=np.float64)
        allowed = np.ones(3, bool)
        view = forward
        if not camera.is_ortho:
            lo, hi = (np.array(b, dtype=np.float64) - 0.5 for b in vevm.evm.bounds())
            eye = np.linalg.solve(cols, camera.position - g[:3, 3])
            outside = (eye < lo) | (eye > hi)
            if outside.any():
                allowed = outside
                view = cols @ ((lo + hi) / 2.0) + g[:3, 3] - camera.position
        cos = np.abs(view @ cols) / np.linalg.norm(cols, axis=0)
        return int(np.argmax(np.where(allowed, cos, -1.0)))

    @staticmethod
    def view_direction(vevm, camera, g):
        """Unit world direction of the headlight: the forward vector (orthographic) or from the
        eye to the region's centre (perspective)."""
        view = np.asarray(camera.forward, dtype=np.float64)
        if not camera.is_ortho:
            lo, hi = (np.array(b, dtype=np.float64) - 0.5 for b in vevm.evm.bounds())
            toward = g[:3, :3] @ ((lo + hi) / 2.0) + g[:3, 3] - camera.position
            if np.any(toward):
                view = toward
        return view / np.linalg.norm(view)

    def slice_maps(self, s):
        """``(α, β_a, β_b)``: slice coordinates ``x = α p + β_a``, ``y = α q + β_b`` of the ray
        through intermediate point ``(p, q)`` (before the origin shift) at ``c = s``; the
        intermediate point is ``scale`` times the reference plane's index coordinates."""
        a, b, c = self.abc
        s = np.asarray(s, dtype=np.float64)
        if self.ortho:
            run = s - self.c_ref
            return np.full_like(s, 1.0 / self.scale), run * self.slope[a], run * self.slope[b]
        lam = (s - self.eye[c]) / (self.c_ref - self.eye[c])
        return lam / self.scale, self.eye[a] * (1 - lam), self.eye[b] * (1 - lam)

    def depth_coefficients(self, s):
        """Axial depth ``k0 + kp·p + kq·q`` of the sample of slice ``s`` at the absolute
        intermediate point ``(p, q)`` (array index plus origin), as ``(k0, kp, kq)``."""
        a, b, c = self.abc
        alpha, beta_a, beta_b = self.slice_maps(s)
        ga, gb, gc = self.depth_grad[a], self.depth_grad[b], self.depth_grad[c]
        k0 = self.depth0 + ga * beta_a + gb * beta_b + gc * np.asarray(s, dtype=np.float64)
        return k0, ga * alpha, gb * alpha

    def depth_limit(self, camera, g, depth_in):
        """``min(clip_end, depth_in)`` at every intermediate pixel (nearest final pixel)."""
        a, b, c = self.abc
        h, w = camera.shape
        p = (self.origin[0] + np.arange(self.size[0])) / self.scale
        q = (self.origin[1] + np.arange(self.size[1])) / self.scale
        pts = np.empty(self.size + (3,))
        pts[..., a] = p[:, None]
        pts[..., b] = q[None, :]
        pts[..., c] = self.c_ref
        uv, _ = camera.project(transform(pts, g[:3, :3].T, g[:3, 3]))
        with np.errstate(invalid="ignore"):
            col = np.floor(uv[..., 0])
            row = np.floor(uv[..., 1])
            inside = (col >= 0) & (col < w) & (row >= 0) & (row < h)
        limit = np.full(self.size, camera.clip_end)
        hit = depth_in[row[inside].astype(np.int64), col[inside].astype(np.int64)]
        limit[inside] = np.minimum(hit, camera.clip_end)
        return limit.astype(np.float32)


def passes(vevm, camera, g):
    """``(principal axis, step, rays)`` of each shear-warp pass; ``step`` (perspective) is the
    front-to-back direction along the axis, ``rays`` (flat bool mask or None: all) the pixels
    the pass renders.

    One pass, except for a perspective eye inside the region's bounding box: there no axis has
    the whole region on one side of the eye, so the rays are split by the grid axis and sign
    most parallel to each (up to six pyramids around the eye, as Lacroute suggests); each pass
    composites the slices beyond the eye for its rays. The rays are disjoint, so the passes
    fill disjoint pixels.
    """
    axis = View.principal_axis(vevm, camera, g)
    if camera.is_ortho:
        return [(axis, None, None)]
    cols = g[:3, :3]
    lo, hi = (np.array(b, dtype=np.float64) - 0.5 for b in vevm.evm.bounds())
    eye = np.linalg.solve(cols, camera.position - g[:3, 3])
    if eye[axis] < lo[axis] or eye[axis] > hi[axis]:
        return [(axis, 1 if eye[axis] < lo[axis] else -1, None)]
    _, dirs = camera.rays()
    dirs = dirs.reshape(-1, 3)
    cos = np.abs(transform(dirs, cols)) / np.linalg.norm(cols, axis=0)
    dominant = np.argmax(cos, axis=1)
    index_dirs = transform(dirs, np.linalg.inv(cols).T)
    ahead = index_dirs[np.arange(len(dirs)), dominant] > 0
    key = 2 * dominant + ahead
    return [(int(k // 2), 1 if k % 2 else -1, key == k) for k in np.unique(key)]


# ------------------------------------------------------------------------------------- kernels
@kernel
def ray_points(first_row, stop_row, x, y, terms, gram, eye, c_ref, step, scale, rays, pq, ok):
    """Perspective: where the ray of each pixel of rows ``first_row .. stop_row - 1`` meets
    the reference plane ``c = c_ref`` of index space, as intermediate coordinates
    ``pq[:, pixel]`` (times ``scale``), and whether it does, going the slices' way (``ok``;
    also only pixels of ``rays``, empty: all). Returns ``(p min, p max, q min, q max)`` over
    those rays.

    The ray of pixel ``(i, j)`` leaves the ``eye`` (index space) along ``x_j r + y_i u - f``
    (:meth:`Camera.rays`): index-space component ``k`` (of ``a, b, c``) is ``terms[k, 0] x_j +
    terms[k, 1] y_i + terms[k, 2]``; ``gram``: the world dot products ``r·r, u·u, f·f, r·u,
    r·f, u·f``, for the length of the direction (the test is on the unit direction, as the
    rays have it). Where the ray meets the plane does not depend on that length.
    """
    extent = np.array([np.inf, -np.inf, np.inf, -np.inf])
    width = x.size
    for i in range(first_row, stop_row):
        for j in range(width):
            k = i * width + j
            xj, yi = x[j], y[i]
            dc = terms[2, 0] * xj + terms[2, 1] * yi + terms[2, 2]
            length = math.sqrt(xj * xj * gram[0] + yi * yi * gram[1] + gram[2]
                               + 2 * xj * yi * gram[3] - 2 * xj * gram[4] - 2 * yi * gram[5])
            ok[k] = dc / length * step > 1e-12 and (rays.size == 0 or rays[k])
            if not ok[k]:
                pq[0, k] = pq[1, k] = 0.0
                continue
            t = (c_ref - eye[2]) / dc
            pq[0, k] = (eye[0] + t * (terms[0, 0] * xj + terms[0, 1] * yi + terms[0, 2])) * scale
            pq[1, k] = (eye[1] + t * (terms[1, 0] * xj + terms[1, 1] * yi + terms[1, 2])) * scale
            extent[0] = min(extent[0], pq[0, k])
            extent[1] = max(extent[1], pq[0, k])
            extent[2] = min(extent[2], pq[1, k])
            extent[3] = max(extent[3], pq[1, k])
    return extent
