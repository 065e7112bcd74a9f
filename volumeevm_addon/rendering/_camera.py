"""A plain camera record that reproduces Blender's camera projection exactly.

Conventions
-----------
- World coordinates are Blender units. The camera looks down its local ``-Z`` axis with ``+Y``
  up and ``+X`` to the right (Blender's camera frame). Like Blender, the camera's
  ``matrix_world`` is used *without scale*: its three axis columns are normalised.
- **Image size** is ``resolution × percentage // 100`` per axis (integer division, as Blender's
  ``BKE_render_resolution`` does).
- **View plane** (Blender's ``BKE_camera_params_compute_viewplane``): with ``ycor =
  pixel_aspect_y / pixel_aspect_x``, the fit is horizontal for ``sensor_fit='HORIZONTAL'``,
  vertical for ``'VERTICAL'``, and for ``'AUTO'`` horizontal iff ``W·aspect_x >= H·aspect_y``.
  ``viewfac = W`` (horizontal) or ``ycor·H`` (vertical). The plane spans
  ``[-W/2, W/2] × [-ycor·H/2, ycor·H/2]`` shifted by ``(shift_x, shift_y)·viewfac``, all scaled
  by ``size / viewfac`` where ``size`` is ``ortho_scale`` (orthographic, in Blender units) or
  ``sensor / lens`` (perspective, at unit distance in front of the camera); the sensor is
  ``sensor_height`` for ``'VERTICAL'`` and ``sensor_width`` otherwise (also for ``'AUTO'``).
- **Pixels.** Pixel coordinates ``(u, v)`` are continuous: ``u`` from 0 at the left edge to ``W``
  at the right edge, ``v`` from 0 at the **top** edge to ``H`` at the bottom. Pixel ``(row,
  col)`` of an image array (row 0 at the top) has its centre at ``(col + 0.5, row + 0.5)``.
  Blender stores images bottom row first: flip rows (``np.flipud``) to go to or from an
  ``Image`` datablock.
- **Depth** is *axial*: the distance along the view axis (``-Z`` of the camera) from the
  camera's position, what Blender's Z pass holds (background ``1e10``). Rays run from the near
  clip plane (axial depth ``clip_start``) to the far clip plane (``clip_end``), as in Cycles,
  for both projections.
"""

from dataclasses import KW_ONLY, dataclass

import numpy as np

from .._errors import VolumeEVMError
from ..model._volume import transform
from ._checks import finite_number, positive_integer, positive_number

__all__ = ["Camera", "BACKGROUND_DEPTH"]

BACKGROUND_DEPTH = 1e10
"""Axial depth Blender's Z pass writes where no geometry is hit."""

_FITS = ("AUTO", "HORIZONTAL", "VERTICAL")


def _cross(a, b):
    """Cross product of two (3,) float64 vectors, element by element (no BLAS)."""
    return np.array([a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2],
                     a[0] * b[1] - a[1] * b[0]])


def _length(v):
    """Euclidean length of a (3,) vector, summed in a fixed order (no BLAS)."""
    return float(np.sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2]))


def _unit(v, problem):
    """``v`` scaled to unit length, or a :class:`VolumeEVMError` saying ``problem`` if it is 0."""
    length = _length(v)
    if length == 0:
        raise VolumeEVMError(problem)
    return v / length


@dataclass(frozen=True, eq=False)
class Camera:
    """Blender's camera projection as a frozen record.

    Every renderer takes one, so an image can be composited over Blender's own render pixel for
    pixel. Build it with :meth:`orthographic`, :meth:`perspective` or :meth:`look_at`; the
    fields are Blender's camera and render settings of the same names, checked and stored as
    plain floats and ints (every option after ``matrix_world`` is keyword-only).

    Parameters
    ----------
    projection : {"ORTHO", "PERSP"}
        Orthographic or perspective.
    matrix_world : (4, 4) array_like
        Camera-to-world matrix; stored with its axis columns normalised (read-only float64
        ndarray), as Blender uses it without scale.
    ortho_scale : float, optional
        Orthographic: width of the fitted image dimension in Blender units (default 6).
    lens_mm, sensor_width, sensor_height : float, optional
        Perspective: focal length and sensor size in mm (defaults 50, 36, 24).
    sensor_fit : {"AUTO", "HORIZONTAL", "VERTICAL"}, optional
        Which image dimension the sensor (or ``ortho_scale``) spans (module docstring).
    shift_x, shift_y : float, optional
        Lens shift in units of the fitted dimension (Blender's ``shift_x/y``).
    clip_start, clip_end : float, optional
        Near and far clip, axial depth in Blender units: ``clip_start > 0`` for a perspective
        camera (``>= 0`` orthographic), ``clip_end > clip_start``.
    resolution_x, resolution_y, resolution_percentage : int, optional
        Render resolution and percentage; the image is ``resolution × percentage // 100``
        pixels per axis (at least 1).
    pixel_aspect_x, pixel_aspect_y : float, optional
        Pixel aspect ratio, > 0.

    Raises
    ------
    VolumeEVMError
        Naming the field that is not as described: an unknown projection or fit, a matrix
        that is not a finite affine 4x4 matrix with independent axes, a size, clip distance
        or aspect that is not a finite positive number, a resolution that is not a positive
        integer or leaves an empty image.

    Examples
    --------
    >>> cam = Camera("ORTHO", np.eye(4), ortho_scale=2.0, resolution_x=4, resolution_y=2)
    >>> cam.shape, cam.fit
    ((2, 4), 'HORIZONTAL')
    """

    projection: str
    matrix_world: np.ndarray
    _: KW_ONLY
    ortho_scale: float = 6.0
    lens_mm: float = 50.0
    sensor_width: float = 36.0
    sensor_height: float = 24.0
    sensor_fit: str = "AUTO"
    shift_x: float = 0.0
    shift_y: float = 0.0
    clip_start: float = 0.1
    clip_end: float = 100.0
    resolution_x: int = 1920
    resolution_y: int = 1080
    resolution_percentage: int = 100
    pixel_aspect_x: float = 1.0
    pixel_aspect_y: float = 1.0

    def __post_init__(self):
        if self.projection not in ("ORTHO", "PERSP"):
            raise VolumeEVMError(f"projection: 'ORTHO' or 'PERSP', got {self.projection!r}")
        try:
            m = np.array(self.matrix_world, dtype=np.float64)
        except (TypeError, ValueError) as error:
            raise VolumeEVMError(f"matrix_world: expected a 4x4 matrix of numbers, got "
                                 f"{type(self.matrix_world).__name__}") from error
        if m.shape != (4, 4) or not np.all(np.isfinite(m)):
            raise VolumeEVMError(f"matrix_world: expected a finite 4x4 matrix, got shape {m.shape}")
        if not np.allclose(m[3], (0.0, 0.0, 0.0, 1.0)):
            raise VolumeEVMError(f"matrix_world: last row must be (0, 0, 0, 1), got {m[3]}")
        norms = np.linalg.norm(m[:3, :3], axis=0)
        if np.any(norms == 0):
            raise VolumeEVMError("matrix_world: an axis column is zero (scale 0)")
        m[:3, :3] /= norms
        if abs(np.linalg.det(m[:3, :3])) < 1e-12:
            raise VolumeEVMError("matrix_world: axes are degenerate (determinant 0)")
        m.setflags(write=False)
        object.__setattr__(self, "matrix_world", m)
        if self.sensor_fit not in _FITS:
            raise VolumeEVMError(f"sensor_fit: one of {_FITS}, got {self.sensor_fit!r}")
        for name in ("ortho_scale", "lens_mm", "sensor_width", "sensor_height", "clip_end",
                     "pixel_aspect_x", "pixel_aspect_y"):
            object.__setattr__(self, name, positive_number(name, getattr(self, name)))
        for name in ("shift_x", "shift_y"):
            object.__setattr__(self, name, finite_number(name, getattr(self, name)))
        cs = finite_number("clip_start", self.clip_start)
        if cs < 0 or (self.projection == "PERSP" and cs == 0):
            raise VolumeEVMError(f"clip_start: must be > 0 (>= 0 orthographic), got {cs!r}")
        object.__setattr__(self, "clip_start", cs)
        if self.clip_end <= cs:
            raise VolumeEVMError(
                f"clip_end: must be greater than clip_start ({cs!r}), got {self.clip_end!r}")
        for name in ("resolution_x", "resolution_y", "resolution_percentage"):
            object.__setattr__(self, name, positive_integer(name, getattr(self, name)))
        if self.width < 1 or self.height < 1:
            raise VolumeEVMError(
                f"resolution_percentage: {self.resolution_percentage}% of "
                f"{self.resolution_x}x{self.resolution_y} leaves an empty image")

    # ------------------------------------------------------------------ constructors
    @classmethod
    def orthographic(cls, matrix_world, ortho_scale, *, sensor_fit="AUTO", shift_x=0.0,
                     shift_y=0.0, clip_start=0.1, clip_end=100.0, resolution_x=1920,
                     resolution_y=1080, resolution_percentage=100, pixel_aspect_x=1.0,
                     pixel_aspect_y=1.0):
        """An orthographic camera; ``ortho_scale`` spans the fitted image dimension (BU).

        Parameters
        ----------
        matrix_world : (4, 4) array_like
            Camera-to-world matrix (Blender's ``camera.matrix_world``; scale is ignored).
        ortho_scale : float
            Width of the fitted image dimension in Blender units, > 0.
        sensor_fit, shift_x, shift_y, clip_start, clip_end : optional
            Fit, lens shift and clip range, as in :class:`Camera` (``clip_start`` may be 0).
        resolution_x, resolution_y, resolution_percentage, pixel_aspect_x, pixel_aspect_y
            Image size and pixel aspect, as in :class:`Camera`.

        Returns
        -------
        Camera
            With ``projection="ORTHO"``.

        Raises
        ------
        VolumeEVMError
            For a bad ``ortho_scale`` or option (:class:`Camera` checks them).

        Examples
        --------
        >>> cam = Camera.orthographic(np.eye(4), 2.0, resolution_x=4, resolution_y=2)
        >>> cam.shape
        (2, 4)
        >>> uv, depth = cam.project([[0.75, 0.0, -3.0]])
        >>> uv.tolist(), depth.tolist()
        ([[3.5, 1.0]], [3.0])
        """
        return cls("ORTHO", matrix_world, ortho_scale=ortho_scale, sensor_fit=sensor_fit,
                   shift_x=shift_x, shift_y=shift_y, clip_start=clip_start, clip_end=clip_end,
                   resolution_x=resolution_x, resolution_y=resolution_y,
                   resolution_percentage=resolution_percentage,
                   pixel_aspect_x=pixel_aspect_x, pixel_aspect_y=pixel_aspect_y)

    @classmethod
    def perspective(cls, matrix_world, lens_mm, *, sensor_width=36.0, sensor_height=24.0,
                    sensor_fit="AUTO", shift_x=0.0, shift_y=0.0, clip_start=0.1,
                    clip_end=100.0, resolution_x=1920, resolution_y=1080,
                    resolution_percentage=100, pixel_aspect_x=1.0, pixel_aspect_y=1.0):
        """A perspective camera with Blender's lens, sensor and fit rules.

        Parameters
        ----------
        matrix_world : (4, 4) array_like
            Where the camera is: Blender's ``camera.matrix_world`` (its scale is ignored).
        lens_mm : float
            Focal length in mm, > 0.
        sensor_width, sensor_height : float, optional
            Sensor size in mm (defaults 36 and 24, Blender's).
        sensor_fit, shift_x, shift_y, clip_start, clip_end, resolution_x, resolution_y
            As for :meth:`orthographic`, except that ``clip_start`` must be > 0.
        resolution_percentage, pixel_aspect_x, pixel_aspect_y : optional
            As for :meth:`orthographic`.

        Returns
        -------
        Camera
            With ``projection="PERSP"``.

        Raises
        ------
        VolumeEVMError
            Naming ``lens_mm``, a sensor size or an option that :class:`Camera` refuses.

        Examples
        --------
        >>> cam = Camera.perspective(np.eye(4), 50.0, resolution_x=4, resolution_y=2)
        >>> uv, depth = cam.project([[0.0, 0.0, -2.0]])
        >>> uv.tolist(), depth.tolist()
        ([[2.0, 1.0]], [2.0])
        """
        return cls("PERSP", matrix_world, lens_mm=lens_mm, sensor_width=sensor_width,
                   sensor_height=sensor_height, sensor_fit=sensor_fit, shift_x=shift_x,
                   shift_y=shift_y, clip_start=clip_start, clip_end=clip_end,
                   resolution_x=resolution_x, resolution_y=resolution_y,
                   resolution_percentage=resolution_percentage,
                   pixel_aspect_x=pixel_aspect_x, pixel_aspect_y=pixel_aspect_y)

    @classmethod
    def look_at(cls, eye, target, up=(0.0, 0.0, 1.0), *, kind="ORTHO", ortho_scale=6.0,
                lens_mm=50.0, **options):
        """A camera at ``eye`` looking at ``target``, its image ``+Y`` as close to ``up`` as
        possible.

        The camera-to-world matrix is computed element by element in float64 (no BLAS), so the
        same arguments give the same bits on every CPU.

        Parameters
        ----------
        eye, target : (3,) array_like
            Camera position and the point it looks at (world, Blender units); must differ.
        up : (3,) array_like, optional
            World direction that appears up in the image. When the view runs along ``up``,
            world ``+Y`` is used instead.
        kind : {"ORTHO", "PERSP"}, optional
            Orthographic or perspective projection.
        ortho_scale : float, optional
            Orthographic: width of the fitted image dimension (Blender units).
        lens_mm : float, optional
            Perspective: focal length (mm).
        **options
            Any other keyword of :meth:`orthographic` or :meth:`perspective`
            (``resolution_x``, ``clip_start``, ``sensor_fit``, ...).

        Returns
        -------
        Camera

        Raises
        ------
        VolumeEVMError
            If ``kind`` is unknown, ``eye``, ``target`` or ``up`` is not 3 finite numbers,
            ``eye`` equals ``target``, or an option is bad (as :class:`Camera`).

        Examples
        --------
        >>> cam = Camera.look_at((0.0, -2.0, 0.0), (0.0, 0.0, 0.0), resolution_x=4,
        ...                      resolution_y=4)
        >>> cam.forward.tolist(), cam.up.tolist(), cam.position.tolist()
        ([0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [0.0, -2.0, 0.0])
        """
        if kind not in ("ORTHO", "PERSP"):
            raise VolumeEVMError(f"kind: 'ORTHO' or 'PERSP', got {kind!r}")
        vectors = []
        for name, value in (("eye", eye), ("target", target), ("up", up)):
            try:
                v = np.array(value, dtype=np.float64)
            except (TypeError, ValueError) as error:
                raise VolumeEVMError(f"{name}: expected 3 numbers, got {value!r}") from error
            if v.shape != (3,) or not np.all(np.isfinite(v)):
                raise VolumeEVMError(f"{name}: expected 3 finite numbers, got {value!r}")
            vectors.append(v)
        eye, target, up = vectors
        f = _unit(target - eye, f"target: must differ from eye, both are {target.tolist()}")
        r = _cross(f, up)
        if _length(r) < 1e-9:  # looking along `up`
            r = _cross(f, np.array([0.0, 1.0, 0.0]))
        r = _unit(r, f"up: no image-up direction for a view along {f.tolist()}")
        u = _cross(r, f)
        m = np.eye(4)
        m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = r, u, -f, eye
        if kind == "ORTHO":
            return cls("ORTHO", m, ortho_scale=ortho_scale, **options)
        return cls("PERSP", m, lens_mm=lens_mm, **options)

    # ------------------------------------------------------------------ geometry
    @property
    def is_ortho(self):
        """True for an orthographic camera, False for a perspective one."""
        return self.projection == "ORTHO"

    @property
    def width(self):
        """Image width in pixels: ``resolution_x * resolution_percentage // 100``."""
        return self.resolution_x * self.resolution_percentage // 100

    @property
    def height(self):
        """Image height in pixels: ``resolution_y * resolution_percentage // 100``."""
        return self.resolution_y * self.resolution_percentage // 100

    @property
    def shape(self):
        """``(H, W)``, the shape of an image array."""
        return self.height, self.width

    @property
    def position(self):
        """Camera position in world space, (3,) float64."""
        return self.matrix_world[:3, 3].copy()

    @property
    def forward(self):
        """Unit view direction (camera ``-Z``) in world space."""
        return -self.matrix_world[:3, 2]

    @property
    def right(self):
        """Unit image-right direction (camera ``+X``) in world space."""
        return self.matrix_world[:3, 0].copy()

    @property
    def up(self):
        """Unit image-up direction (camera ``+Y``) in world space."""
        return self.matrix_world[:3, 1].copy()

    @property
    def fit(self):
        """The fit actually used: ``"HORIZONTAL"`` or ``"VERTICAL"``."""
        if self.sensor_fit != "AUTO":
            return self.sensor_fit
        sx = self.width * self.pixel_aspect_x
        sy = self.height * self.pixel_aspect_y
        return "HORIZONTAL" if sx >= sy else "VERTICAL"

    @property
    def viewplane(self):
        """``(xmin, xmax, ymin, ymax)`` of the image in camera space: in Blender units for an
        orthographic camera, on the plane at unit distance (``z = -1``) for a perspective one."""
        w, h = float(self.width), float(self.height)
        ycor = self.pixel_aspect_y / self.pixel_aspect_x
        if self.is_ortho:
            size = self.ortho_scale
        else:
            sensor = self.sensor_height if self.sensor_fit == "VERTICAL" else self.sensor_width
            size = sensor / self.lens_mm
        viewfac = w if self.fit == "HORIZONTAL" else ycor * h
        pix = size / viewfac
        dx = self.shift_x * viewfac
        dy = self.shift_y * viewfac
        return ((-0.5 * w + dx) * pix, (0.5 * w + dx) * pix,
                (-0.5 * ycor * h + dy) * pix, (0.5 * ycor * h + dy) * pix)

    def matrix_projection(self):
        """4x4 OpenGL-style projection matrix, as Blender's ``Object.calc_matrix_camera``
        returns it for the rendered size and pixel aspect.

        Useful to check the camera against Blender, or to project with a GPU.

        Returns
        -------
        (4, 4) ndarray of np.float64
            Clip space from camera space, near and far planes at ``clip_start``/``clip_end``.
        """
        xmin, xmax, ymin, ymax = self.viewplane
        n, f = self.clip_start, self.clip_end
        p = np.zeros((4, 4))
        if self.is_ortho:
            p[0, 0] = 2.0 / (xmax - xmin)
            p[1, 1] = 2.0 / (ymax - ymin)
            p[2, 2] = -2.0 / (f - n)
            p[0, 3] = -(xmax + xmin) / (xmax - xmin)
            p[1, 3] = -(ymax + ymin) / (ymax - ymin)
            p[2, 3] = -(f + n) / (f - n)
            p[3, 3] = 1.0
        else:
            # Blender builds it from the view plane at the near clip: the same frustum.
            xmin, xmax, ymin, ymax = (c * n for c in (xmin, xmax, ymin, ymax))
            p[0, 0] = 2.0 * n / (xmax - xmin)
            p[1, 1] = 2.0 * n / (ymax - ymin)
            p[0, 2] = (xmax + xmin) / (xmax - xmin)
            p[1, 2] = (ymax + ymin) / (ymax - ymin)
            p[2, 2] = -(f + n) / (f - n)
            p[2, 3] = -2.0 * f * n / (f - n)
            p[3, 2] = -1.0
        return p

    def world_to_camera(self, points):
        """Points in world space to camera space (the inverse of the normalised camera matrix).

        Parameters
        ----------
        points : (..., 3) array_like
            Positions in the scene (world space, Blender units).

        Returns
        -------
        (..., 3) ndarray of np.float64
            The camera looks down ``-Z``, ``+Y`` up, ``+X`` right.

        Raises
        ------
        VolumeEVMError
            If ``points`` does not end in an axis of 3.
        """
        pts = np.asarray(points, dtype=np.float64)
        if pts.shape[-1:] != (3,):
            raise VolumeEVMError(f"points: expected shape (..., 3), got {pts.shape}")
        m = self.matrix_world
        # The inverse of the (normalised) camera matrix, as Blender's view matrix is.
        return transform(pts - m[:3, 3], np.linalg.inv(m[:3, :3]).T)

    def project(self, points):
        """Pixel coordinates and axial depth of world points.

        Parameters
        ----------
        points : (..., 3) array_like
            World positions (Blender units).

        Returns
        -------
        uv : (..., 2) ndarray of np.float64
            ``(u, v)`` pixel coordinates: ``u`` from the left edge, ``v`` from the **top**
            edge; pixel ``(row, col)`` covers ``[col, col+1] × [row, row+1]``. NaN for points
            at or behind the plane of a perspective camera (axial depth ``<= 0``).
        depth : (...) ndarray of np.float64
            Axial depth (distance along the view axis) in Blender units.

        Raises
        ------
        VolumeEVMError
            If ``points`` does not end in an axis of 3.
        """
        c = self.world_to_camera(points)
        depth = -c[..., 2]
        xmin, xmax, ymin, ymax = self.viewplane
        if self.is_ortho:
            x, y = c[..., 0], c[..., 1]
        else:
            with np.errstate(divide="ignore", invalid="ignore"):
                x = np.where(depth > 0, c[..., 0] / depth, np.nan)
                y = np.where(depth > 0, c[..., 1] / depth, np.nan)
        uv = np.empty(c.shape[:-1] + (2,))
        uv[..., 0] = (x - xmin) / (xmax - xmin) * self.width
        uv[..., 1] = (ymax - y) / (ymax - ymin) * self.height
        return uv, depth

    def pixel_centres(self):
        """View-plane coordinates of the pixel centres, through which :meth:`rays` pass.

        Returns
        -------
        x : (W,) ndarray of np.float64
            Per pixel column, left to right.
        y : (H,) ndarray of np.float64
            Per pixel row, top to bottom.
        """
        h, w = self.shape
        xmin, xmax, ymin, ymax = self.viewplane
        return (xmin + (np.arange(w) + 0.5) * ((xmax - xmin) / w),
                ymax - (np.arange(h) + 0.5) * ((ymax - ymin) / h))

    def rays(self):
        """World-space rays through the pixel centres.

        Returns
        -------
        origins : (H, W, 3) ndarray of np.float64
            Perspective: the camera position for every pixel. Orthographic: the pixel centre on
            the camera plane (axial depth 0).
        directions : (H, W, 3) ndarray of np.float64
            Unit directions. Row 0 is the top of the image. A point at ray parameter ``t`` has
            axial depth ``t · (directions · forward)`` (orthographic: ``t``).
        """
        h, w = self.shape
        x, y = self.pixel_centres()
        m = self.matrix_world
        rx, uy, fz = m[:3, 0], m[:3, 1], m[:3, 2]
        if self.is_ortho:
            origins = (m[:3, 3] + x[None, :, None] * rx + y[:, None, None] * uy)
            directions = np.broadcast_to(-fz, (h, w, 3)).copy()
        else:
            origins = np.broadcast_to(m[:3, 3], (h, w, 3)).copy()
            d = x[None, :, None] * rx + y[:, None, None] * uy - fz
            directions = d / np.linalg.norm(d, axis=-1, keepdims=True)
        return origins, directions

    def axial_depth(self, points):
        """Axial depth of world points: their distance along the view axis, as Blender's Z pass.

        Parameters
        ----------
        points : (..., 3) array_like
            World positions (Blender units).

        Returns
        -------
        (...) ndarray of np.float64
            Axial depth in Blender units (negative behind the camera).
        """
        return -self.world_to_camera(points)[..., 2]
