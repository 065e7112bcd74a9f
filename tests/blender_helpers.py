"""Helpers for the Blender tests: load the extension from the source tree, reset Blender, compare
meshes, and set up renders (camera, Cycles, Render settings, F12 to EXR, Image pixels).

The repository root is the extension package; tests import it under the name ``volumeevm``
(installed, Blender names it ``bl_ext.<repo>.volumeevm``; the code uses relative imports only),
with the demo script's loader (``sample_blends/make_demo.py``), so both load it the same way.
"""

import json
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
CT_CROP = (slice(64, 192), slice(48, 176), slice(30, 80))  # 128 x 128 x 50 voxels of the CT head
CT_BONE_HU = 300.0
SKULL_CENTRE = (0.124, 0.124, 0.115)  # middle of the sample skull's grid (Blender units)


def addon():
    """The extension package loaded from the source tree (imported once)."""
    from sample_blends.make_demo import load_extension  # the repo root is on sys.path

    return load_extension()


def reset_blender():
    """An empty scene with factory settings (registered classes and properties stay)."""
    import bpy

    bpy.ops.wm.read_factory_settings(use_empty=True)


def mesh_arrays(mesh):
    """Vertices (n, 3) float32, loop vertex indices, loop starts and totals of a Blender mesh."""
    co = np.empty(len(mesh.vertices) * 3, np.float32)
    mesh.vertices.foreach_get("co", co)
    indices = np.empty(len(mesh.loops), np.int32)
    mesh.loops.foreach_get("vertex_index", indices)
    starts = np.empty(len(mesh.polygons), np.int32)
    mesh.polygons.foreach_get("loop_start", starts)
    totals = np.empty(len(mesh.polygons), np.int32)
    mesh.polygons.foreach_get("loop_total", totals)
    return co.reshape(-1, 3), indices, starts, totals


def assert_surface_is(surface, vevm, **options):
    """The Blender surface mesh equals the core's mesh of ``vevm`` (made with ``options``, e.g.
    ``smooth=True``) exactly (x 0.001); returns the core's polygons."""
    return assert_mesh_is(surface, *vevm.mesh(**options))


def assert_identical(got, expected):
    """Every field of two VolumeEVMs equal: vertices, the three tables (values and dtype) and the
    geometry."""
    assert np.array_equal(got.evm.vertices, expected.evm.vertices)
    for axis in range(3):
        assert got.table(axis).dtype == expected.table(axis).dtype
        assert np.array_equal(got.table(axis), expected.table(axis))
    for name in ("shape", "spacing", "origin", "units", "threshold", "upper", "voxel_count"):
        assert getattr(got, name) == getattr(expected, name), name
    assert np.array_equal(got.orientation, expected.orientation)


def assert_mesh_is(surface, verts_mm, polys):
    """The Blender surface mesh equals a core mesh (vertices in mm, polygons) exactly (x 0.001);
    returns the polygons."""
    co, indices, starts, totals = mesh_arrays(surface.data)
    np.testing.assert_array_equal(co, (verts_mm * 0.001).astype(np.float32))
    np.testing.assert_array_equal(indices, polys.indices)
    np.testing.assert_array_equal(starts, polys.starts)
    np.testing.assert_array_equal(totals, polys.sizes)
    return polys


def write_ct_crop(path, data_dir):
    """Write the CT crop as ``.npy`` with its JSON sidecar (spacing, HU); returns the array."""
    meta = json.loads((data_dir / "ct_head_invesalius.json").read_text())
    array = np.ascontiguousarray(np.load(data_dir / "ct_head_invesalius.npy")[CT_CROP])
    np.save(path, array)
    side = {k: meta[k] for k in ("spacing_mm", "spacing_known", "units", "axis_order", "dtype")}
    side["shape"] = list(array.shape)
    Path(path).with_suffix(".json").write_text(json.dumps(side))
    return array


def add_camera(scene, location, *, ortho=False, shift=(0.0, 0.0), target=SKULL_CENTRE):
    """A camera at ``location`` looking at ``target`` (Blender units), the scene's camera:
    perspective (50 mm lens) or orthographic (scale 0.36), with a lens ``shift``."""
    import bpy
    from mathutils import Vector

    cam = bpy.data.objects.new("Camera", bpy.data.cameras.new("Camera"))
    scene.collection.objects.link(cam)
    cam.location = location
    cam.rotation_euler = (Vector(target) - Vector(location)).to_track_quat("-Z", "Y").to_euler()
    cam.data.shift_x, cam.data.shift_y = shift
    cam.data.clip_start, cam.data.clip_end = 0.01, 10.0
    if ortho:
        cam.data.type = "ORTHO"
        cam.data.ortho_scale = 0.36
    else:
        cam.data.lens = 50.0
    scene.camera = cam
    return cam


def cycles(scene, size, percentage=100, *, samples=1):
    """Cycles CPU, ``samples`` per pixel at the pixel centre (filter width 0.01), linear view."""
    r = scene.render
    r.engine = "CYCLES"
    scene.cycles.device = "CPU"
    scene.cycles.samples = samples
    scene.cycles.use_denoising = False
    scene.cycles.filter_width = 0.01
    r.resolution_x, r.resolution_y = size
    r.resolution_percentage = percentage
    r.film_transparent = True
    scene.view_settings.view_transform = "Standard"
    r.dither_intensity = 0.0


def settings_for(scene, vol, tmp_path, **extra):
    """The Render settings of ``scene`` for the sample skull ``vol``: ray casting, the CT bone
    preset stretched onto the skull's densities, then ``extra`` (setting names and values)."""
    s = scene.volumeevm_render
    s.volume = vol
    s.method = "raycast"
    s.preset_stretch = True  # the CT preset stretched onto the skull's 0 .. 5.4 (not HU)
    s.preset = "ct_bone"
    for key, value in extra.items():
        setattr(s, key, value)
    return s


def f12_exr(scene, path):
    """F12 to a float EXR at ``path``: its RGBA (H, W, 4), row 0 at the top."""
    import bpy
    import OpenEXR

    settings = scene.render.image_settings
    settings.file_format = "OPEN_EXR"
    settings.color_depth = "32"
    scene.render.filepath = str(path)
    bpy.ops.render.render(write_still=True)
    with OpenEXR.File(str(path), separate_channels=True) as f:
        ch = {k.split(".")[-1]: v.pixels for p in f.parts for k, v in p.channels.items()}
    return np.stack([ch[c] for c in "RGBA"], -1)


def image_rgba(name):
    """An Image datablock's pixels (H, W, 4), row 0 at the top."""
    import bpy

    image = bpy.data.images[name]
    w, h = image.size
    return np.flipud(np.array(image.pixels[:], np.float32).reshape(h, w, 4))
