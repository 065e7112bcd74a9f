"""Render VolumeEVM in the real bpy: camera match (silhouettes against Cycles), depth against
scene geometry, the operator end to end (images, EXR, PNG, reports), the compositor set-up and
an F12 render that includes the DVR.

Runs under both pinned bpy versions (4.5 on Python 3.11, 5.2 on Python 3.13); Cycles CPU.
"""

import inspect
import math

import bpy
import numpy as np
import OpenEXR
import pytest
from mathutils import Vector

from blender_helpers import REPO, add_camera, cycles, f12_exr, image_rgba, settings_for

SKULL = REPO / "sample_blends" / "data" / "ct_skull_cgal.npy"
SKULL_THRESHOLD = 2.9


@pytest.fixture
def dvr(ext):
    return ext.blender.dvr


@pytest.fixture
def skull(ext):
    """The sample skull as a volume object with its VolumeEVM (the region >= 2.9)."""
    api = ext.blender.api
    vol = api.import_volume(SKULL)
    api.build(vol, SKULL_THRESHOLD)
    return vol


def opaque_tf(ext):
    """Opacity 1 per mm at every density: any ray through a region voxel is opaque."""
    from volumeevm.volumeevm_addon import TransferFunction

    return TransferFunction([(0.0, 1.0, 1.0, 1.0, 1.0), (10.0, 1.0, 1.0, 1.0, 1.0)])


def bone_tf():
    from volumeevm.volumeevm_addon import TransferFunction

    return TransferFunction([(2.0, 0.9, 0.8, 0.7, 0.0), (3.0, 0.95, 0.85, 0.7, 0.15),
                             (5.5, 1.0, 1.0, 1.0, 0.6)])


def plane(scene, location, size, colour, *, rotation=(0.0, 0.0, 0.0)):
    """An emissive opaque plane (colour exactly ``colour`` in the render)."""
    mesh = bpy.data.meshes.new("Plane")
    h = size / 2
    mesh.from_pydata([(-h, -h, 0), (h, -h, 0), (h, h, 0), (-h, h, 0)], [], [(0, 1, 2, 3)])
    obj = bpy.data.objects.new("Plane", mesh)
    obj.location, obj.rotation_euler = location, rotation
    material = bpy.data.materials.new("Emit")
    if bpy.app.version < (5, 0, 0):
        material.use_nodes = True
    nodes = material.node_tree.nodes
    emit = nodes.new("ShaderNodeEmission")
    emit.inputs["Color"].default_value = (*colour, 1.0)
    material.node_tree.links.new(emit.outputs[0], nodes["Material Output"].inputs["Surface"])
    mesh.materials.append(material)
    scene.collection.objects.link(obj)
    return obj


def iou(a, b):
    return float((a & b).sum()) / float((a | b).sum())


# ---------------------------------------------------------------------------- camera
CAMERAS = {
    "ortho_shift_percent": dict(location=(0.55, -0.45, 0.30), ortho=True, shift=(0.08, -0.05),
                                size=(160, 100), percentage=60,
                                placement=((0.03, -0.02, 0.01), (0.2, 0.0, 0.5), 1.1)),
    "persp_shift": dict(location=(-0.25, -0.55, 0.25), ortho=False, shift=(-0.06, 0.04),
                        size=(96, 128), percentage=100),
    "persp_vertical_fit_percent": dict(location=(0.15, 0.60, -0.10), ortho=False,
                                       shift=(0.05, 0.1), size=(150, 90), percentage=80,
                                       sensor_fit="VERTICAL", pixel_aspect=(1.0, 1.25)),
}


#: Smallest IoU per method. Ray casting (exact coverage of region cells), splatting and the
#: reference match exactly here; shear-warp samples each ray once per slice, so rays that only
#: clip a corner of a region voxel between two slices miss it (measured 0.964-0.970 on these
#: views; intermediate_scale does not change it).
SILHOUETTE_IOU = {"raycast": 0.99, "splat": 0.99, "reference": 0.99, "shear_warp": 0.95}


@pytest.mark.parametrize("case", sorted(CAMERAS))
def test_opaque_silhouette_equals_surface_mesh_render(ext, dvr, skull, case):
    """Opaque DVR silhouette = Cycles' silhouette of the EVM surface mesh, same camera."""
    spec = CAMERAS[case]
    scene = bpy.context.scene
    cam = add_camera(scene, spec["location"], ortho=spec["ortho"], shift=spec["shift"])
    cam.data.sensor_fit = spec.get("sensor_fit", "AUTO")
    cycles(scene, spec["size"], spec["percentage"])
    scene.render.pixel_aspect_x, scene.render.pixel_aspect_y = spec.get("pixel_aspect", (1, 1))
    if "placement" in spec:  # the volume object moved, turned and scaled (surface follows)
        skull.location, skull.rotation_euler, scale = spec["placement"]
        skull.scale = (scale, scale, scale)
    surface = ext.blender.api.make_mesh(skull)
    mesh_pass = ext.blender.scene.render_scene(scene)  # the surface mesh by Cycles
    w = spec["size"][0] * spec["percentage"] // 100
    h = spec["size"][1] * spec["percentage"] // 100
    assert mesh_pass.rgba.shape == (h, w, 4)
    mesh_mask = mesh_pass.rgba[..., 3] > 0.5
    assert np.array_equal(mesh_mask, mesh_pass.depth < 1e9)
    assert 0.05 < mesh_mask.mean() < 0.8  # the skull is in view, not everywhere
    for method, bound in SILHOUETTE_IOU.items():
        result = dvr.render_dvr(skull, opaque_tf(ext), method=method, hide_surface=True)
        assert result.rgba.shape == (h, w, 4)
        dvr_mask = result.dvr_rgba[..., 3] > 0.5
        value = iou(mesh_mask, dvr_mask)
        print(f"IoU {case} {method}: {value:.4f} ({int((mesh_mask & ~dvr_mask).sum())} missing, "
              f"{int((dvr_mask & ~mesh_mask).sum())} extra of {int(mesh_mask.sum())})")
        assert value >= bound, method
    # The scene pass hid the surface: nothing but the DVR in the composite.
    assert np.all(result.scene.rgba[..., 3] == 0)
    assert surface.hide_render is False  # put back


# ---------------------------------------------------------------------------- depth
def test_plane_in_front_hides_exactly_the_volume_behind_it(ext, dvr, skull):
    scene = bpy.context.scene
    add_camera(scene, (0.124, -0.6, 0.115), ortho=True)
    cycles(scene, (96, 80))
    free = dvr.render_dvr(skull, bone_tf(), method="raycast")
    # A plane between camera and skull covering the left part of the view.
    plane(scene, (0.02, -0.2, 0.115), 0.2, (0.1, 0.6, 0.2), rotation=(math.pi / 2, 0.0, 0.0))
    result = dvr.render_dvr(skull, bone_tf(), method="raycast")
    covered = result.scene.depth < 1e9
    assert 0.1 < covered.mean() < 0.9
    assert (free.dvr_rgba[..., 3][covered] > 0.1).any()  # the plane does hide some volume
    assert np.all(result.dvr_rgba[covered] == 0)
    np.testing.assert_array_equal(result.dvr_rgba[~covered], free.dvr_rgba[~covered])
    np.testing.assert_allclose(result.rgba[covered], result.scene.rgba[covered], atol=1e-6)
    assert np.allclose(result.scene.rgba[covered][:, :3], (0.1, 0.6, 0.2), atol=1e-3)
    np.testing.assert_array_equal(result.depth[covered], result.scene.depth[covered])


def test_volume_in_front_veils_a_plane_behind_it(ext, dvr, skull):
    scene = bpy.context.scene
    add_camera(scene, (0.124, -0.6, 0.115), ortho=False)
    cycles(scene, (80, 64))
    plane(scene, (0.124, 0.5, 0.115), 2.0, (0.8, 0.2, 0.1), rotation=(math.pi / 2, 0.0, 0.0))
    result = dvr.render_dvr(skull, bone_tf(), method="raycast")
    assert np.all(result.scene.depth < 1e9)  # the plane fills the view
    seen = result.dvr_rgba[..., 3] > 0.01
    assert 0.05 < seen.mean() < 0.9
    # The plane lies behind the whole volume: the DVR is the same as with no scene at all.
    from volumeevm.volumeevm_addon import render

    cam = ext.blender.camera.camera_from_blender(scene)
    alone, alone_depth = render(ext.blender.api.get_vevm(skull), cam, bone_tf(),
                                method="raycast", matrix_world=np.array(skull.matrix_world))
    np.testing.assert_allclose(result.dvr_rgba, alone, atol=1e-6)
    plane_colour = result.scene.rgba
    assert np.allclose(plane_colour[..., :3], (0.8, 0.2, 0.1), atol=1e-3)
    expected = result.dvr_rgba + (1 - result.dvr_rgba[..., 3:4]) * plane_colour
    np.testing.assert_allclose(result.rgba, expected, atol=1e-6)
    assert np.all(result.rgba[..., 3] > 0.999)
    # Output depth: the volume's where it is seen, else the plane's.
    np.testing.assert_array_equal(result.depth[seen], alone_depth[seen])
    np.testing.assert_array_equal(result.depth[~(alone_depth < 1e10)],
                                  result.scene.depth[~(alone_depth < 1e10)])


# ---------------------------------------------------------------------------- operator
def test_operator_end_to_end(ext, dvr, skull, tmp_path):
    scene = bpy.context.scene
    add_camera(scene, (-0.3, -0.5, 0.3), ortho=False, shift=(0.05, 0.0))
    cycles(scene, (120, 80), 50, samples=2)
    plane(scene, (0.124, 0.4, 0.115), 2.0, (0.2, 0.3, 0.4), rotation=(math.pi / 2, 0.0, 0.0))
    s = settings_for(scene, skull, tmp_path, use_exr=True, exr_path=str(tmp_path / "a.exr"),
                     use_png=True, png_path=str(tmp_path / "a.png"))
    assert s.ramp is not None and len(s.ramp.color_ramp.elements) == 5
    assert s.value_lo == pytest.approx(0.0, abs=1e-6)
    assert s.value_hi == pytest.approx(skull.volumeevm.value_max, rel=1e-6)
    formats = scene.render.image_settings
    before = {k: getattr(formats, k) for k in ("file_format", "color_depth", "color_mode")}
    assert bpy.ops.volumeevm.render_dvr() == {"FINISHED"}
    assert {k: getattr(formats, k) for k in before} == before  # scene's output format kept
    assert scene.render.use_compositing and not scene.view_layers[0].use_pass_z
    image = bpy.data.images[dvr.DEFAULT_IMAGE]
    assert tuple(image.size) == (60, 40) and image.is_float and image.alpha_mode == "PREMUL"
    pixels = np.empty(60 * 40 * 4, np.float32)
    image.pixels.foreach_get(pixels)
    composite = np.flipud(pixels.reshape(40, 60, 4))
    assert np.isfinite(composite).all()
    # Equal to the core render over the scene render (rays stopped at the scene depth).
    tf = ext.blender.transfer.transfer_function(s)
    options = ext.volumeevm_addon.rendering.method_options("raycast", 1.0, skull.volumeevm.spacing)
    expected = dvr.render_dvr(skull, tf, method="raycast", image_name="check", options=options)
    from volumeevm.volumeevm_addon import render

    cam = ext.blender.camera.camera_from_blender(scene)
    core, core_depth = render(ext.blender.api.get_vevm(skull), cam, tf, method="raycast",
                              depth_in=expected.scene.depth,
                              matrix_world=np.array(skull.matrix_world),
                              step_mm=0.5 * min(skull.volumeevm.spacing), termination=0.99)
    np.testing.assert_allclose(expected.dvr_rgba, core, atol=1e-6)
    np.testing.assert_allclose(composite, core + (1 - core[..., 3:4]) * expected.scene.rgba,
                               atol=2e-3)  # two Cycles renders: sample noise only
    assert (core[..., 3] > 0.2).any()
    dvr_image = bpy.data.images[f"{dvr.DEFAULT_IMAGE} DVR"]
    dvr_pixels = np.empty(60 * 40 * 4, np.float32)
    dvr_image.pixels.foreach_get(dvr_pixels)
    np.testing.assert_allclose(np.flipud(dvr_pixels.reshape(40, 60, 4)), core, atol=1e-6)
    # EXR: R, G, B, A, Z.
    with OpenEXR.File(str(tmp_path / "a.exr"), separate_channels=True) as f:
        channels = {k: v.pixels for k, v in f.parts[0].channels.items()}
    assert set(channels) == {"R", "G", "B", "A", "Z"}
    np.testing.assert_array_equal(np.stack([channels[c] for c in "RGBA"], -1), composite)
    z = channels["Z"]
    seen = core[..., 3] > 0
    np.testing.assert_allclose(z[seen], core_depth[seen], rtol=1e-6)
    assert np.all(z[~seen] == expected.scene.depth[~seen])
    assert np.isfinite(z).all()
    png = bpy.data.images.load(str(tmp_path / "a.png"))
    assert tuple(png.size) == (60, 40)
    # Files are never overwritten unasked; with Overwrite they are replaced.
    with pytest.raises(RuntimeError, match="exists"):
        bpy.ops.volumeevm.render_dvr()
    s.overwrite = True
    assert bpy.ops.volumeevm.render_dvr() == {"FINISHED"}
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.exr", "a.png"]  # no temporaries


def test_camera_that_sees_nothing_warns_and_gives_a_transparent_dvr(ext, dvr, skull, tmp_path):
    scene = bpy.context.scene
    add_camera(scene, (0.124, -0.6, 0.115), target=Vector((0.124, -2.0, 0.115)))  # looks away
    cycles(scene, (40, 30))
    settings_for(scene, skull, tmp_path)
    assert bpy.ops.volumeevm.render_dvr() == {"FINISHED"}
    result = dvr.render_dvr(skull, bone_tf())
    assert not result.visible
    assert np.all(result.dvr_rgba == 0) and np.all(result.dvr_depth == 1e10)
    assert np.isfinite(result.rgba).all()
    assert tuple(result.image.size) == (40, 30)


def test_no_camera_is_an_error(ext, skull, tmp_path):
    scene = bpy.context.scene
    cycles(scene, (40, 30))
    settings_for(scene, skull, tmp_path)
    with pytest.raises(RuntimeError, match="no camera"):
        bpy.ops.volumeevm.render_dvr()
    assert bpy.data.images.get("VolumeEVM Render") is None


def test_transfer_function_from_the_ramp(ext, skull):
    scene = bpy.context.scene
    s = scene.volumeevm_render
    s.volume = skull
    s.preset = "mri"
    tf = ext.blender.transfer.transfer_function(s)
    from volumeevm.volumeevm_addon import TransferFunction

    hi = skull.volumeevm.value_max
    want = TransferFunction.preset("mri", data_range=(skull.volumeevm.value_min, hi))
    values = np.linspace(-1.0, hi + 1.0, 101)
    np.testing.assert_allclose(tf.evaluate(values), want.evaluate(values), atol=1e-5)
    s.unit_length_mm = 2.0
    assert ext.blender.transfer.transfer_function(s).unit_length_mm == 2.0


# ---------------------------------------------------------------------------- compositor
def test_compositor_setup_and_f12_include_the_dvr(ext, dvr, skull, tmp_path):
    scene = bpy.context.scene
    add_camera(scene, (0.4, -0.5, 0.2), ortho=True)
    cycles(scene, (64, 48), samples=2)
    scene.render.film_transparent = False
    scene.render.compositor_device = "CPU"
    plane(scene, (0.124, 0.4, 0.115), 2.0, (0.3, 0.5, 0.2), rotation=(math.pi / 2, 0.0, 0.0))
    settings_for(scene, skull, tmp_path)
    assert bpy.ops.volumeevm.render_dvr() == {"FINISHED"}
    assert bpy.ops.volumeevm.setup_compositor() == {"FINISHED"}
    assert bpy.ops.volumeevm.setup_compositor() == {"FINISHED"}  # again: nothing duplicated
    render_ops = ext.blender.compositor
    if hasattr(scene, "compositing_node_group"):
        tree = scene.compositing_node_group
        output = [n for n in tree.nodes if n.bl_idname == "NodeGroupOutput"]
    else:
        assert scene.use_nodes
        tree = scene.node_tree
        output = [n for n in tree.nodes if n.bl_idname == "CompositorNodeComposite"]
    assert len(output) == 1
    kinds = [n.bl_idname for n in tree.nodes]
    assert kinds.count("CompositorNodeAlphaOver") == 1 and kinds.count("CompositorNodeImage") == 1
    over = tree.nodes[render_ops.NODE_OVER]
    assert tree.nodes[render_ops.NODE_IMAGE].image.name == f"{dvr.DEFAULT_IMAGE} DVR"
    assert output[0].inputs[0].links[0].from_node == over
    background, foreground = render_ops.over_sockets(over)
    source = background.links[0].from_node
    while source.bl_idname == "NodeReroute":  # 4.5's default tree routes through one
        source = source.inputs[0].links[0].from_node
    assert source.bl_idname == "CompositorNodeRLayers"
    assert foreground.links[0].from_node.name == render_ops.NODE_IMAGE
    # F12 to a float EXR (linear) and to a PNG (Standard view transform, no dither).
    expected = np.empty(64 * 48 * 4, np.float32)
    bpy.data.images[dvr.DEFAULT_IMAGE].pixels.foreach_get(expected)
    expected = np.flipud(expected.reshape(48, 64, 4))
    settings = scene.render.image_settings
    settings.file_format = "OPEN_EXR"
    settings.color_depth = "32"
    scene.render.filepath = str(tmp_path / "f12.exr")
    bpy.ops.render.render(write_still=True)
    with OpenEXR.File(str(tmp_path / "f12.exr"), separate_channels=True) as f:
        ch = {k.split(".")[-1]: v.pixels for p in f.parts for k, v in p.channels.items()}
    f12 = np.stack([ch[c] for c in "RGBA"], -1)
    dvr_alpha = np.flipud(np.array(bpy.data.images[f"{dvr.DEFAULT_IMAGE} DVR"].pixels[:],
                                   np.float32).reshape(48, 64, 4))[..., 3]
    assert (dvr_alpha > 0.2).any()
    np.testing.assert_allclose(f12, expected, atol=2e-3)
    settings.file_format = "PNG"
    settings.color_depth = "8"
    scene.render.filepath = str(tmp_path / "f12.png")
    bpy.ops.render.render(write_still=True)
    png = bpy.data.images.load(str(tmp_path / "f12.png"))
    got = np.flipud(np.array(png.pixels[:], np.float32).reshape(48, 64, 4))[..., :3]
    srgb = np.where(expected[..., :3] <= 0.0031308, 12.92 * expected[..., :3],
                    1.055 * np.clip(expected[..., :3], 0.0031308, None) ** (1 / 2.4) - 0.055)
    np.testing.assert_allclose(got, np.clip(srgb, 0, 1), atol=2.5 / 255)


def test_f12_leaves_a_stale_dvr_out_and_says_so(ext, dvr, skull, tmp_path, capfd):
    compositor = ext.blender.compositor
    scene = bpy.context.scene
    cam = add_camera(scene, (0.124, -0.6, 0.115), ortho=True)
    cycles(scene, (40, 32))
    scene.render.film_transparent = False
    scene.render.compositor_device = "CPU"
    plane(scene, (0.124, 0.4, 0.115), 2.0, (0.3, 0.5, 0.2), rotation=(math.pi / 2, 0.0, 0.0))
    cam.keyframe_insert("location", frame=1)
    cam.location.x += 0.06
    cam.keyframe_insert("location", frame=2)
    scene.frame_set(1)
    settings_for(scene, skull, tmp_path)
    assert bpy.ops.volumeevm.render_dvr() == {"FINISHED"}
    assert bpy.ops.volumeevm.setup_compositor() == {"FINISHED"}
    assert compositor.stale_dvr(scene) == ""
    np.testing.assert_allclose(f12_exr(scene, tmp_path / "f1.exr"),
                               image_rgba(dvr.DEFAULT_IMAGE), atol=2e-3)
    # Frame 2: the DVR of frame 1 is stale. The panel says so before F12...
    scene.frame_set(2)
    stale = compositor.stale_dvr(scene)
    assert stale == (f"'{dvr.DEFAULT_IMAGE} DVR' was rendered for another frame, camera or "
                     f"resolution (frame 1; this render: frame 2)")
    from test_blender_ui import Recorder, texts

    calls = []
    panel = type("P", (), {})()
    panel.layout = Recorder(calls)
    ext.ui.render_panel.VOLUMEEVM_PT_render.draw(panel, bpy.context)
    assert "F12 leaves the DVR out:" in texts(calls)
    # ... and F12 saves the scene without it (as with compositing off), with an error.
    capfd.readouterr()
    f12 = f12_exr(scene, tmp_path / "f2_stale.exr")
    err = capfd.readouterr().err
    assert f"[volumeevm] error: {stale}: this render leaves it out" in err
    over = scene.compositing_node_group.nodes[compositor.NODE_OVER] if hasattr(
        scene, "compositing_node_group") else scene.node_tree.nodes[compositor.NODE_OVER]
    assert over.mute
    scene.render.use_compositing = False
    plain = f12_exr(scene, tmp_path / "f2_plain.exr")
    scene.render.use_compositing = True
    np.testing.assert_array_equal(f12, plain)
    assert not np.allclose(f12, image_rgba(dvr.DEFAULT_IMAGE), atol=0.05)  # frame 1's composite
    # Rendered again for frame 2: F12 lays it over again.
    assert bpy.ops.volumeevm.render_dvr() == {"FINISHED"}
    assert compositor.stale_dvr(scene) == ""
    f12 = f12_exr(scene, tmp_path / "f2.exr")
    assert not over.mute
    np.testing.assert_allclose(f12, image_rgba(dvr.DEFAULT_IMAGE), atol=2e-3)
    assert not np.allclose(f12, plain, atol=0.05)
    # Allowed: the stale DVR is laid over, with a warning.
    scene.volumeevm_render.allow_stale_dvr = True
    scene.frame_set(1)
    capfd.readouterr()
    f12_exr(scene, tmp_path / "f1_allowed.exr")
    out = capfd.readouterr().out
    assert "[volumeevm] warning: " in out and "(Allow Stale DVR)" in out
    assert not over.mute


# ---------------------------------------------------------------------------- UI
def test_render_panel_draws_and_the_job_runs_from_the_modal_driver(ext, dvr, skull, tmp_path):
    from test_blender_ui import Recorder, _Context, _driver, _ticks, texts

    scene = bpy.context.scene
    panel_cls = ext.ui.render_panel.VOLUMEEVM_PT_render

    def draw():
        calls = []
        panel = type("P", (), {})()
        panel.layout = Recorder(calls)
        panel_cls.draw(panel, bpy.context)
        return calls

    calls = draw()  # no ramp, no camera yet
    assert "Load a preset to edit the ramp" in texts(calls)
    assert "The scene has no camera" in texts(calls)
    add_camera(scene, (0.124, -0.6, 0.115), ortho=True)
    cycles(scene, (48, 40))
    settings_for(scene, skull, tmp_path)
    calls = draw()
    assert any(name == "template_color_ramp" for name, _, _ in calls)
    assert any(name == "operator" and args[0] == "volumeevm.render_dvr" for name, args, _ in calls)
    assert len([name for name, _, _ in calls if name == "progress"]) == 8  # the histogram
    # The UI path: scene pass on the main thread, the volume render in the worker thread.
    tf = ext.blender.transfer.transfer_function(scene.volumeevm_render)
    op = _driver(ext, lambda: dvr.render_dvr_job(scene, skull, tf, method="shear_warp"))
    context = _Context()
    assert op.start(context) == {"RUNNING_MODAL"}
    assert _ticks(op, context, limit=1000) == {"FINISHED"}
    image = bpy.data.images[dvr.DEFAULT_IMAGE]
    assert tuple(image.size) == (48, 40)
    assert np.array(image.pixels[:])[3::4].max() > 0.5


# ---------------------------------------------------------------------------- frames
def test_animation_renders_every_frame_and_f12_says_the_dvr_is_stale(ext, dvr, skull, tmp_path,
                                                                     capfd):
    scene = bpy.context.scene
    cam = add_camera(scene, (0.124, -0.6, 0.115), ortho=True)
    cycles(scene, (40, 32))
    cam.keyframe_insert("location", frame=1)
    cam.location.x += 0.08
    cam.keyframe_insert("location", frame=2)
    scene.frame_start, scene.frame_end = 1, 2
    scene.frame_set(1)
    settings_for(scene, skull, tmp_path, use_png=True, png_path=str(tmp_path / "f_##.png"),
                 use_exr=True, exr_path=str(tmp_path / "f_##.exr"))
    assert bpy.ops.volumeevm.render_dvr_animation() == {"FINISHED"}
    assert sorted(p.name for p in tmp_path.iterdir()) == ["f_01.exr", "f_01.png", "f_02.exr",
                                                          "f_02.png"]
    assert scene.frame_current == 1
    frames = []
    for frame in (1, 2):
        with OpenEXR.File(str(tmp_path / f"f_{frame:02d}.exr"), separate_channels=True) as f:
            frames.append(f.parts[0].channels["A"].pixels)
    assert (frames[0] > 0.5).any() and not np.array_equal(frames[0], frames[1])
    # Each frame's image equals a single render at that frame.
    scene.frame_set(2)
    single = dvr.render_dvr(skull, ext.blender.transfer.transfer_function(scene.volumeevm_render),
                            method="raycast", image_name="single")
    np.testing.assert_allclose(frames[1], single.rgba[..., 3], atol=1e-6)
    # F12 with the compositor: quiet when the DVR matches the view, an error when it does not
    # (test_f12_leaves_a_stale_dvr_out_and_says_so).
    assert bpy.ops.volumeevm.setup_compositor() == {"FINISHED"}
    scene.volumeevm_render.image_name = "single"
    assert bpy.ops.volumeevm.setup_compositor() == {"FINISHED"}
    capfd.readouterr()
    bpy.ops.render.render()
    assert "[volumeevm]" not in "".join(capfd.readouterr())
    scene.frame_set(1)
    bpy.ops.render.render()
    assert "rendered for another frame, camera or resolution" in capfd.readouterr().err
    assert dvr.frame_path("/x/a.png", 7) == "/x/a_0007.png"
    assert dvr.frame_path("/x/a_###_b.exr", 12) == "/x/a_012_b.exr"


def test_the_method_enum_is_the_registry(ext):
    """The sidebar lists every registered method with its record's name and description, in
    the registry's order (Blender stores the setting by position: the old methods keep
    theirs), and the GPU method's options are the core record's."""
    records = ext.volumeevm_addon.rendering.methods()
    settings = bpy.context.scene.volumeevm_render
    items = settings.bl_rna.properties["method"].enum_items
    assert [(i.identifier, i.name, i.description) for i in items] == [
        (r.name, r.label, r.description) for r in records.values()]
    assert [i.identifier for i in items][:6] == ["raycast", "shear_warp", "splat",
                                                 "raycast_navigate", "reference", "gpu"]
    assert [i.value for i in items] == list(range(len(records)))
    gpu_draw = ext.blender.gpu_draw
    signature = inspect.signature(gpu_draw.render_gpu).parameters.values()
    assert {p.name: p.default for p in signature if p.kind == p.KEYWORD_ONLY and p.name not in
            ("mode", "depth_in", "matrix_world", "level")} == dict(records[gpu_draw.METHOD].options)


def test_every_method_and_mode_through_the_operator(ext, dvr, skull, tmp_path):
    scene = bpy.context.scene
    add_camera(scene, (0.124, -0.6, 0.115), ortho=True)
    cycles(scene, (48, 36))
    s = settings_for(scene, skull, tmp_path)
    s.xray_scale = 0.01
    ui = ext.ui.props
    for method, *_ in ui.METHOD_ITEMS:
        for mode, *_ in ui.MODE_ITEMS:
            s.method, s.mode = method, mode
            assert bpy.ops.volumeevm.render_dvr() == {"FINISHED"}
            pixels = np.array(bpy.data.images[f"{dvr.DEFAULT_IMAGE} DVR"].pixels[:], np.float32)
            alpha = pixels.reshape(36, 48, 4)[..., 3]
            assert np.isfinite(pixels).all(), (method, mode)
            assert 0.1 < alpha.mean() < 0.5 and alpha.max() > 0.9, (method, mode)


def test_the_tool_stack_result_is_rendered(ext, dvr, skull):
    """A volume with CAD tools renders the stack's result, not the bare VolumeEVM."""
    api = ext.blender.api
    scene = bpy.context.scene
    add_camera(scene, (0.124, -0.6, 0.115), ortho=True)
    cycles(scene, (48, 40))
    bare = dvr.render_dvr(skull, bone_tf())
    mesh = bpy.data.meshes.new("Box")
    h = 0.08
    corners = [(x, y, z) for x in (-h, h) for y in (-h, h) for z in (-h, h)]
    mesh.from_pydata(corners, [], [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6),
                                   (0, 2, 6, 4), (1, 5, 7, 3)])
    box = bpy.data.objects.new("Box", mesh)
    box.location = (0.05, 0.0, 0.2)
    scene.collection.objects.link(box)
    result = api.add_tool(skull, box, "cut")
    assert result.voxel_count < api.get_vevm(skull).voxel_count
    box.hide_render = True  # the tool itself stays out of the picture here
    cut = dvr.render_dvr(skull, bone_tf())
    from volumeevm.volumeevm_addon import render

    cam = ext.blender.camera.camera_from_blender(scene)
    want, _ = render(result, cam, bone_tf(), method="raycast",
                     matrix_world=np.array(skull.matrix_world))
    np.testing.assert_allclose(cut.dvr_rgba, want, atol=1e-6)
    assert not np.allclose(cut.dvr_rgba, bare.dvr_rgba, atol=1e-3)


def test_resolution_setting_renders_a_minified_view_from_a_coarser_level(ext, dvr, skull,
                                                                         tmp_path):
    """Resolution (Auto by default) reaches the core through method_options, from the Render
    operator too: a view with pixels about 2.4 voxels wide renders from level 2 (an eighth of
    the work), near the full render. The skull's bone is one or two voxels thick, and level 2
    thickens it to one coarse voxel: measured RMSE 0.113 to the full render on both bpy
    versions."""
    scene = bpy.context.scene
    s = scene.volumeevm_render
    assert s.resolution == "auto"
    assert [item[0] for item in ext.ui.props.RESOLUTION_ITEMS] == ["auto", "full"]
    add_camera(scene, (0.124, -0.6, 0.115), ortho=True)  # ortho scale 0.36 BU
    cycles(scene, (38, 30))  # 9.5 mm pixels, 3.9 mm voxels
    vevm = ext.blender.api.get_vevm(skull)
    spacing = skull.volumeevm.spacing
    settings_for(scene, skull, tmp_path, resolution="full")
    assert bpy.ops.volumeevm.render_dvr() == {"FINISHED"}

    def levels():
        """The factors of the coarser levels kept in the VolumeEVM's cache."""
        return [key[1] for key in vevm.cache.keys() if key[0] == "level"]

    assert not levels()  # Full: no coarser level built
    s.resolution = "auto"
    assert bpy.ops.volumeevm.render_dvr() == {"FINISHED"}
    assert levels() == [2]
    images = {}
    for level in ("full", "auto"):
        options = ext.volumeevm_addon.rendering.method_options("raycast", 1.0, spacing, level=level)
        images[level] = dvr.render_dvr(skull, bone_tf(), options=options).dvr_rgba
    assert levels() == [2]
    assert vevm.level(2).voxel_count < vevm.voxel_count / 4
    from volumeevm.volumeevm_addon.metrics import rmse

    error = rmse(images["auto"], images["full"])
    assert 1e-4 < error < 0.14, error
    with pytest.raises(ext.volumeevm_addon.VolumeEVMError, match="level"):
        ext.volumeevm_addon.rendering.method_options("raycast", 1.0, spacing, level="half")


def test_method_settings_reach_the_core(ext, dvr, skull, tmp_path):
    """Shear-warp's slices and classification and the ray casters' jitter and pre-integration
    go from the Render settings to the method that has them, and change the operator's image."""
    scene = bpy.context.scene
    add_camera(scene, (0.124, -0.6, 0.115), ortho=True)
    cycles(scene, (24, 20))
    s = settings_for(scene, skull, tmp_path, method="shear_warp", slices_per_voxel=2,
                     classification="post", jitter=True, preintegrate=True)
    options = ext.blender.dvr.job_arguments(bpy.context, s)[2]["options"]
    assert options["slices_per_voxel"] == 2 and options["classification"] == "post"
    assert "jitter" not in options and "preintegrate" not in options
    s.method = "raycast"
    options = ext.blender.dvr.job_arguments(bpy.context, s)[2]["options"]
    assert options["jitter"] is True and options["preintegrate"] is True
    assert "slices_per_voxel" not in options
    spacing = skull.volumeevm.spacing
    # quality = sub-slabs
    assert ext.volumeevm_addon.rendering.method_options("splat", 3.0, spacing)["substeps"] == 3
    assert ext.volumeevm_addon.rendering.method_options("splat", 0.5, spacing)["substeps"] == 1
    images = []
    for on in (True, False):
        s.jitter = s.preintegrate = on
        assert bpy.ops.volumeevm.render_dvr() == {"FINISHED"}
        pixels = np.empty(24 * 20 * 4, np.float32)
        bpy.data.images[dvr.DEFAULT_IMAGE].pixels.foreach_get(pixels)
        images.append(pixels.reshape(20, 24, 4))
    assert images[0][..., 3].max() > 0.5
    assert np.abs(images[0] - images[1]).max() > 1e-3  # the settings change the image
