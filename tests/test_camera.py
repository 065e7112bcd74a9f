"""Camera record: Blender's projection rules, rays through pixel centres, and agreement with
real Blender (``bpy``) for orthographic and perspective cameras."""

import importlib
import sys
import types
from pathlib import Path

import numpy as np
import pytest

from volumeevm_addon import Camera, VolumeEVMError
from volumeevm_addon.rendering import BACKGROUND_DEPTH


# ---------------------------------------------------------------------------- core rules
def test_image_size_rounds_like_blender():
    cam = Camera.orthographic(np.eye(4), 1.0, resolution_x=1001, resolution_y=333,
                              resolution_percentage=50)
    assert (cam.width, cam.height) == (500, 166)
    assert cam.shape == (166, 500)


def test_viewplane_fit_rules():
    # AUTO, landscape: horizontal fit; the width is ortho_scale.
    cam = Camera.orthographic(np.eye(4), 2.0, resolution_x=40, resolution_y=20)
    assert cam.fit == "HORIZONTAL"
    np.testing.assert_allclose(cam.viewplane, (-1.0, 1.0, -0.5, 0.5), rtol=0, atol=1e-15)
    # AUTO, portrait: vertical fit; the height is ortho_scale.
    cam = Camera.orthographic(np.eye(4), 2.0, resolution_x=20, resolution_y=40)
    assert cam.fit == "VERTICAL"
    np.testing.assert_allclose(cam.viewplane, (-0.5, 0.5, -1.0, 1.0), rtol=0, atol=1e-15)
    # Pixel aspect enters the AUTO decision: 40x20 with pixels 1 wide, 3 tall is portrait.
    cam = Camera.orthographic(np.eye(4), 2.0, resolution_x=40, resolution_y=20,
                              pixel_aspect_y=3.0)
    assert cam.fit == "VERTICAL"
    np.testing.assert_allclose(cam.viewplane, (-2 / 3, 2 / 3, -1.0, 1.0), rtol=1e-15)
    # Shift is in units of the fitted dimension.
    cam = Camera.orthographic(np.eye(4), 2.0, resolution_x=40, resolution_y=20, shift_x=0.25,
                              shift_y=-0.1)
    np.testing.assert_allclose(cam.viewplane, (-0.5, 1.5, -0.7, 0.3), rtol=1e-15)
    # Perspective AUTO uses sensor_width even when the fit is vertical.
    cam = Camera.perspective(np.eye(4), 50.0, sensor_width=36.0, sensor_height=10.0,
                             resolution_x=20, resolution_y=40)
    np.testing.assert_allclose(cam.viewplane[3] - cam.viewplane[2], 36.0 / 50.0, rtol=1e-15)
    cam = Camera.perspective(np.eye(4), 50.0, sensor_width=36.0, sensor_height=10.0,
                             sensor_fit="VERTICAL", resolution_x=40, resolution_y=20)
    np.testing.assert_allclose(cam.viewplane[3] - cam.viewplane[2], 10.0 / 50.0, rtol=1e-15)


@pytest.mark.parametrize("kind", ["ORTHO", "PERSP"])
def test_rays_pass_through_pixel_centres(kind):
    m = Camera.look_at((0.3, -2.0, 0.7), (0.1, 0.2, 0.0)).matrix_world
    kw = dict(shift_x=0.1, shift_y=-0.05, resolution_x=24, resolution_y=15,
              pixel_aspect_x=1.5, clip_start=0.01)
    cam = (Camera.orthographic(m, 1.3, **kw) if kind == "ORTHO"
           else Camera.perspective(m, 35.0, **kw))
    o, d = cam.rays()
    assert o.shape == d.shape == (15, 24, 3)
    np.testing.assert_allclose(np.linalg.norm(d, axis=-1), 1.0, rtol=1e-14)
    t = 1.7
    uv, depth = cam.project(o + t * d)
    rows, cols = np.mgrid[0:15, 0:24]
    np.testing.assert_allclose(uv[..., 0], cols + 0.5, rtol=0, atol=1e-10)
    np.testing.assert_allclose(uv[..., 1], rows + 0.5, rtol=0, atol=1e-10)
    # Axial depth of o + t d is t times the cosine to the view axis (plus the origin's depth).
    np.testing.assert_allclose(depth, cam.axial_depth(o) + t * (d @ cam.forward), rtol=1e-12)


def test_row_zero_is_top():
    cam = Camera.orthographic(np.eye(4), 2.0, resolution_x=4, resolution_y=4)
    o, d = cam.rays()
    assert o[0, 0, 1] > o[-1, 0, 1]  # +Y (up) is row 0
    assert o[0, 0, 0] < o[0, -1, 0]  # +X (right) is the last column
    np.testing.assert_allclose(d, np.broadcast_to((0.0, 0.0, -1.0), d.shape))
    uv, depth = cam.project([[0.0, 0.9, -2.0]])
    assert uv[0, 1] < 1.0 and depth[0] == 2.0


def test_scale_of_matrix_world_is_ignored():
    m = Camera.look_at((1.0, -3.0, 2.0), (0.0, 0.0, 0.0)).matrix_world
    s = m.copy()
    s[:3, :3] *= (2.0, 0.5, 3.0)
    a = Camera.perspective(m, 50.0, resolution_x=8, resolution_y=6)
    b = Camera.perspective(s, 50.0, resolution_x=8, resolution_y=6)
    np.testing.assert_allclose(a.rays()[1], b.rays()[1], rtol=1e-14)


def test_look_at_builds_a_right_handed_frame():
    """The camera looks from eye to target with +Y towards ``up``; a view along ``up`` takes
    world +Y as up; the frame is orthonormal and right-handed (X x Y = Z = -forward)."""
    cam = Camera.look_at((1.0, -2.0, 3.0), (1.0, 5.0, 3.0), kind="PERSP", lens_mm=35.0)
    assert cam.projection == "PERSP" and cam.lens_mm == 35.0
    assert cam.forward.tolist() == [0.0, 1.0, 0.0] and cam.up.tolist() == [0.0, 0.0, 1.0]
    assert cam.right.tolist() == [1.0, 0.0, 0.0] and cam.position.tolist() == [1.0, -2.0, 3.0]
    down = Camera.look_at((0.0, 0.0, 5.0), (0.0, 0.0, 0.0), ortho_scale=2.0)
    assert down.is_ortho and down.ortho_scale == 2.0
    assert down.up.tolist() == [0.0, 1.0, 0.0] and down.right.tolist() == [1.0, 0.0, 0.0]
    rng = np.random.default_rng(3)
    for eye, target, up in rng.normal(size=(20, 3, 3)):
        m = Camera.look_at(eye, target, up).matrix_world
        np.testing.assert_allclose(m[:3, :3].T @ m[:3, :3], np.eye(3), atol=1e-12)
        np.testing.assert_allclose(np.cross(m[:3, 0], m[:3, 1]), m[:3, 2], atol=1e-12)
        forward = (target - eye) / np.linalg.norm(target - eye)
        np.testing.assert_allclose(-m[:3, 2], forward, atol=1e-12)
        assert m[:3, 1] @ up > 0  # image up leans towards `up`


@pytest.mark.parametrize("kwargs,match", [
    (dict(eye=(1.0, 2.0, 3.0), target=(1.0, 2.0, 3.0)), "target: must differ from eye"),
    (dict(eye=(0.0, -1.0, 0.0), target=(0.0, 0.0, 0.0), up=(0.0, 1.0, 0.0)),
     "up: no image-up direction"),
    (dict(eye=(1.0, 2.0), target=(0.0, 0.0, 0.0)), "eye: expected 3 finite numbers"),
    (dict(eye=(0.0, 0.0, 1.0), target=(0.0, np.nan, 0.0)), "target: expected 3 finite"),
    (dict(eye=(0.0, 0.0, 1.0), target=(0.0, 0.0, 0.0), kind="FISHEYE"), "kind: 'ORTHO'"),
])
def test_look_at_rejects_bad_input(kwargs, match):
    with pytest.raises(VolumeEVMError, match=match):
        Camera.look_at(**kwargs)


def test_projection_matrix_matches_project():
    rng = np.random.default_rng(1)
    m = Camera.look_at((2.0, -3.0, 1.0), (0.0, 0.2, 0.1)).matrix_world
    for cam in (Camera.perspective(m, 40.0, shift_x=0.2, resolution_x=30, resolution_y=20,
                                   pixel_aspect_y=1.3),
                Camera.orthographic(m, 2.5, shift_y=0.2, resolution_x=30, resolution_y=20)):
        pts = rng.uniform(-1, 1, (50, 3))
        uv, depth = cam.project(pts)
        h = np.c_[pts, np.ones(50)] @ (cam.matrix_projection() @ np.linalg.inv(cam.matrix_world)).T
        ndc = h[:, :3] / h[:, 3:]
        np.testing.assert_allclose((ndc[:, 0] + 1) / 2 * cam.width, uv[:, 0], atol=1e-9)
        np.testing.assert_allclose((1 - ndc[:, 1]) / 2 * cam.height, uv[:, 1], atol=1e-9)


def test_points_behind_perspective_camera_are_nan():
    cam = Camera.perspective(np.eye(4), 50.0, resolution_x=8, resolution_y=8)
    uv, depth = cam.project([[0.0, 0.0, 1.0], [0.0, 0.0, 0.0]])
    assert np.isnan(uv).all() and depth.tolist() == [-1.0, 0.0]
    assert BACKGROUND_DEPTH == 1e10


@pytest.mark.parametrize("kwargs, match", [
    (dict(projection="FISHEYE"), "projection"),
    (dict(matrix_world=np.ones((3, 3))), "matrix_world"),
    (dict(matrix_world=np.full((4, 4), np.nan)), "matrix_world"),
    (dict(sensor_fit="DIAGONAL"), "sensor_fit"),
    (dict(lens_mm=0.0), "lens_mm"),
    (dict(ortho_scale=-1.0), "ortho_scale"),
    (dict(clip_start=0.0), "clip_start"),
    (dict(clip_end=0.05), "clip_end"),
    (dict(resolution_x=0), "resolution_x"),
    (dict(resolution_x=2.5), "resolution_x"),
    (dict(resolution_x=1, resolution_percentage=50), "empty image"),
    (dict(pixel_aspect_y=np.nan), "pixel_aspect_y"),
    (dict(shift_x=np.inf), "shift_x"),
])
def test_invalid_camera(kwargs, match):
    base = dict(projection="PERSP", matrix_world=np.eye(4))
    base.update(kwargs)
    with pytest.raises(VolumeEVMError, match=match):
        Camera(**base)


# ---------------------------------------------------------------------------- against Blender
import bpy  # noqa: E402  (the real wheel; both pinned environments have it)

REPO = Path(__file__).resolve().parents[1]


def _operators_camera():
    """``blender/camera.py`` imported as part of the extension package rooted at the repo, as
    Blender does (it imports the core with ``from ..volumeevm_addon``): through the shared
    test helper when it is there, else as a bare package (no registration code run)."""
    try:
        from blender_helpers import addon
    except ImportError:
        name = "_volumeevm_repo_pkg"
        if name not in sys.modules:
            pkg = types.ModuleType(name)
            pkg.__path__ = [str(REPO)]
            sys.modules[name] = pkg
    else:
        name = addon().__name__
    module = importlib.import_module(f"{name}.blender.camera")
    return module.camera_from_blender, module.VolumeEVMError


@pytest.fixture
def scene():
    bpy.ops.wm.read_homefile(use_empty=True)
    sc = bpy.context.scene
    data = bpy.data.cameras.new("cam")
    obj = bpy.data.objects.new("cam", data)
    sc.collection.objects.link(obj)
    sc.camera = obj
    yield sc
    bpy.ops.wm.read_homefile(use_empty=True)


CASES = [
    # type, fit, shift, res x, res y, percentage, aspect x, aspect y
    ("PERSP", "AUTO", (0.0, 0.0), 64, 48, 100, 1.0, 1.0),
    ("PERSP", "AUTO", (0.15, -0.1), 48, 64, 50, 1.0, 1.0),
    ("PERSP", "HORIZONTAL", (-0.2, 0.1), 50, 70, 100, 2.0, 1.0),
    ("PERSP", "VERTICAL", (0.1, 0.3), 80, 40, 75, 1.0, 1.7),
    ("PERSP", "AUTO", (0.05, 0.05), 60, 50, 100, 1.0, 1.5),  # aspect flips AUTO to vertical
    ("ORTHO", "AUTO", (0.0, 0.0), 64, 48, 100, 1.0, 1.0),
    ("ORTHO", "AUTO", (0.1, 0.2), 30, 70, 100, 1.3, 1.0),
    ("ORTHO", "HORIZONTAL", (-0.3, 0.0), 40, 90, 50, 1.0, 2.0),
    ("ORTHO", "VERTICAL", (0.0, -0.25), 90, 40, 200, 1.0, 1.0),
]


@pytest.mark.parametrize("case", CASES, ids=[f"{c[0]}-{c[1]}-{i}" for i, c in enumerate(CASES)])
def test_project_matches_blender(scene, case):
    from bpy_extras.object_utils import world_to_camera_view
    from mathutils import Matrix, Vector

    kind, fit, shift, rx, ry, pct, ax, ay = case
    obj = scene.camera
    cam = obj.data
    cam.type = kind
    cam.sensor_fit = fit
    cam.lens = 42.0
    cam.sensor_width = 32.0
    cam.sensor_height = 20.0
    cam.ortho_scale = 3.2
    cam.shift_x, cam.shift_y = shift
    cam.clip_start, cam.clip_end = 0.05, 50.0
    r = scene.render
    r.resolution_x, r.resolution_y, r.resolution_percentage = rx, ry, pct
    r.pixel_aspect_x, r.pixel_aspect_y = ax, ay
    obj.matrix_world = Matrix(
        Camera.look_at((1.5, -4.0, 2.0), (0.2, 0.1, 0.3)).matrix_world.tolist())
    obj.scale = (1.0, 2.0, 0.5)  # Blender ignores camera scale; so must we
    bpy.context.view_layer.update()

    ours = _operators_camera()[0](scene)
    assert (ours.width, ours.height) == (rx * pct // 100, ry * pct // 100)
    rng = np.random.default_rng(7)
    pts = rng.uniform(-1.5, 1.5, (200, 3))
    uv, depth = ours.project(pts)
    theirs = np.array([world_to_camera_view(scene, obj, Vector(p)) for p in pts])
    # Blender computes in float32 (mathutils too): agreement to float32 precision is the best
    # possible (measured: 1e-7 of the image size, 1e-7 relative depth).
    w, h = ours.width, ours.height
    np.testing.assert_allclose(uv[:, 0] / w, theirs[:, 0], rtol=0, atol=5e-7)
    np.testing.assert_allclose(1.0 - uv[:, 1] / h, theirs[:, 1], rtol=0, atol=5e-7)
    np.testing.assert_allclose(depth, theirs[:, 2], rtol=5e-7, atol=0)

    # The projection matrix equals calc_matrix_camera for the rendered size and pixel aspect.
    dg = bpy.context.evaluated_depsgraph_get()
    pm = np.array(obj.calc_matrix_camera(dg, x=w, y=h, scale_x=ax, scale_y=ay))
    np.testing.assert_allclose(ours.matrix_projection(), pm, rtol=0, atol=5e-7 * np.abs(pm).max())
    view = np.array(obj.matrix_world.normalized().inverted())
    np.testing.assert_allclose(np.linalg.inv(ours.matrix_world), view, rtol=0, atol=2e-6)


def test_camera_from_blender_errors(scene):
    camera_from_blender, VolumeEVMError = _operators_camera()  # the package's own error class
    mesh = bpy.data.objects.new("empty", None)
    with pytest.raises(VolumeEVMError, match="not a CAMERA"):
        camera_from_blender(scene, mesh)
    scene.camera.data.type = "PANO"
    with pytest.raises(VolumeEVMError, match="PANO"):
        camera_from_blender(scene)
    scene.camera = None
    with pytest.raises(VolumeEVMError, match="no camera"):
        camera_from_blender(scene)


def test_percentage_rounding_follows_the_render(scene):
    """101x67 at 50 % renders 50x33 pixels, a slightly different aspect than 101x67. The render
    (and ``calc_matrix_camera`` for the rendered size) uses 50x33; ``world_to_camera_view`` uses
    the full resolution's aspect, so only the former is compared."""
    r = scene.render
    r.resolution_x, r.resolution_y, r.resolution_percentage = 101, 67, 50
    scene.camera.data.shift_x = 0.1
    bpy.context.view_layer.update()
    ours = _operators_camera()[0](scene)
    assert ours.shape == (33, 50)
    dg = bpy.context.evaluated_depsgraph_get()
    pm = np.array(scene.camera.calc_matrix_camera(dg, x=50, y=33))
    np.testing.assert_allclose(ours.matrix_projection(), pm, rtol=0, atol=5e-7 * np.abs(pm).max())


SILHOUETTE_CASES = [
    # type, fit, shift, res x, res y, percentage, aspect x, aspect y
    ("PERSP", "AUTO", (0.1, -0.05), 48, 36, 100, 1.0, 1.0),
    ("PERSP", "VERTICAL", (-0.1, 0.1), 60, 40, 75, 1.0, 1.4),
    ("ORTHO", "AUTO", (0.0, 0.15), 32, 44, 100, 1.3, 1.0),
    ("ORTHO", "HORIZONTAL", (0.2, 0.0), 40, 40, 100, 1.0, 1.0),
]


def _render_cycles(scene, path):
    """Render with Cycles into a multilayer EXR; return (alpha, Z pass), rows top first."""
    import OpenEXR

    r = scene.render
    r.engine = "CYCLES"
    r.film_transparent = True
    try:  # Blender 4.5
        r.image_settings.file_format = "OPEN_EXR_MULTILAYER"
    except TypeError:  # Blender 5.x: the media type selects multilayer EXR
        r.image_settings.media_type = "MULTI_LAYER_IMAGE"
    r.image_settings.color_depth = "32"
    r.filepath = str(path)
    scene.view_layers[0].use_pass_z = True
    scene.cycles.samples = 128
    scene.cycles.device = "CPU"
    scene.cycles.pixel_filter_type = "BOX"
    scene.cycles.filter_width = 1.0
    bpy.ops.render.render(write_still=True)
    with OpenEXR.File(str(path)) as exr:  # EXR stores the top row first
        channels = {k: v.pixels for part in exr.parts for k, v in part.channels.items()}
        layer = scene.view_layers[0].name
        return channels[f"{layer}.Combined"][..., 3].copy(), channels[f"{layer}.Depth.Z"].copy()


@pytest.mark.parametrize("case", SILHOUETTE_CASES,
                         ids=[f"{c[0]}-{c[1]}" for c in SILHOUETTE_CASES])
def test_silhouette_and_depth_match_a_cycles_render(scene, case, tmp_path):
    """An opaque box rendered by our reference through the camera record covers exactly the
    pixels that Cycles (box filter, 1 px) covers by more than half, and its depth equals
    Cycles' Z pass: row 0 at the top, pixel centres, sensor fit, shift, percentage, pixel
    aspect and axial depth as Blender renders them."""
    from mathutils import Matrix

    from volumeevm_addon import TransferFunction
    from volumeevm_addon.rendering._reference import render_reference

    kind, fit, shift, rx, ry, pct, ax, ay = case
    cam = scene.camera.data
    cam.type, cam.sensor_fit, cam.lens, cam.ortho_scale = kind, fit, 50.0, 2.4
    cam.shift_x, cam.shift_y = shift
    r = scene.render
    r.resolution_x, r.resolution_y, r.resolution_percentage = rx, ry, pct
    r.pixel_aspect_x, r.pixel_aspect_y = ax, ay
    scene.camera.matrix_world = Matrix(
        Camera.look_at((2.0, -3.0, 1.5), (0.1, 0.0, 0.05)).matrix_world.tolist())

    # A box of 3 x 5 x 4 voxels of 0.2 BU, rotated and moved: the mesh and the grid agree.
    shape = np.array([3, 5, 4])
    place = np.eye(4)
    place[:3, :3] = np.array(Matrix.Rotation(0.5, 3, (0.3, 0.2, 1.0)))
    place[:3, 3] = (0.1, -0.1, 0.2)
    index_to_local = np.diag([0.2, 0.2, 0.2, 1.0])
    index_to_local[:3, 3] = 0.1 - 0.1 * shape  # box centred on the object's origin
    grid_to_world = place @ index_to_local
    mesh = bpy.data.meshes.new("box")
    h = 0.1 * shape
    verts = [(sx * h[0], sy * h[1], sz * h[2])
             for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)]
    faces = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    mesh.from_pydata(verts, [], faces)
    box = bpy.data.objects.new("box", mesh)
    scene.collection.objects.link(box)
    box.matrix_world = Matrix(place.tolist())
    bpy.context.view_layer.update()
    coverage, zpass = _render_cycles(scene, tmp_path / "box.exr")

    ours_cam = _operators_camera()[0](scene)
    # the record from the package copy, rebuilt as this module's class for the reference
    ours_cam = Camera(**{f: getattr(ours_cam, f) for f in ours_cam.__dataclass_fields__})
    assert coverage.shape == ours_cam.shape
    tf = TransferFunction([(0.0, 1, 1, 1, 1.0), (1.0, 1, 1, 1, 1.0)])
    rgba, depth = render_reference(np.zeros(tuple(shape)), None, grid_to_world, (1.0, 1.0, 1.0),
                                   ours_cam, tf, step_mm=1.0)
    ours = rgba[..., 3] > 0.5
    sure_in, sure_out = coverage > 0.75, coverage < 0.25
    assert sure_in.sum() > 30 and sure_out.sum() > 30
    assert np.all(ours[sure_in]) and not np.any(ours[sure_out])
    # the undecided band is the one-pixel outline only
    assert (~sure_in & ~sure_out).sum() < 0.5 * ours.sum()
    # Axial depth: Cycles' Z pass (float32 ray tracing) at fully covered pixels. Inside faces
    # they agree to 3e-5 relative (measured); at the outline, on faces seen almost edge-on,
    # the tiniest sub-pixel difference is magnified (measured 5e-4). A tenth of a pixel off
    # would show as ~1e-2 on the typical slope here (0.1 BU per pixel).
    full = coverage > 0.999
    pad = np.pad(full, 1)
    interior = np.ones_like(full)
    for dr in (0, 1, 2):
        for dc in (0, 1, 2):
            interior &= pad[dr:dr + full.shape[0], dc:dc + full.shape[1]]
    assert interior.sum() > 30
    np.testing.assert_allclose(depth[interior], zpass[interior], rtol=5e-5)
    np.testing.assert_allclose(depth[full], zpass[full], rtol=0, atol=2e-3)
    empty = coverage == 0
    assert np.all(zpass[empty] == BACKGROUND_DEPTH) and np.all(depth[empty] == BACKGROUND_DEPTH)
