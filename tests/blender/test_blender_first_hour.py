"""What a new user meets between installing the extension and a first picture (issue 21): a
script that ends without ``unregister()``, framing the volume, the data's units and the presets,
a stale DVR in F12, file paths in an unsaved .blend, the methods an error lists."""

import subprocess
import sys

import bpy
import numpy as np
import pytest
from test_blender_ui import texts

from blender_helpers import REPO

# A user's script: register the extension, import a volume, show the viewport DVR, and end
# without unregister().
REGISTER_ONLY = r'''
import sys
sys.path.insert(0, sys.argv[1])
from sample_blends.make_demo import load_extension
extension = load_extension()
extension.register()
import bpy
from volumeevm.blender import api
vol = api.import_volume(sys.argv[2])
bpy.context.scene.volumeevm_render.viewport = True
print("REGISTERED", vol.name, flush=True)
'''


def test_a_script_that_only_registers_exits_cleanly(tmp_path, data_dir):
    script = tmp_path / "register_only.py"
    script.write_text(REGISTER_ONLY)
    run = subprocess.run([sys.executable, str(script), str(REPO),
                          str(data_dir / "ct_skull_cgal.npy")],
                         capture_output=True, text=True, timeout=300, cwd=tmp_path)
    assert "REGISTERED ct_skull_cgal" in run.stdout, run.stdout[-2000:] + run.stderr[-2000:]
    assert run.returncode == 0, run.stdout[-2000:] + run.stderr[-2000:]


# ---------------------------------------------------------------------------- units, presets
SKULL_NPY = "ct_skull_cgal.npy"  # its sidecar names no units


def test_units_as_the_file_says_set_by_the_user_and_saved(ext, data_dir, ct_crop_npy, tmp_path):
    api, panels = ext.blender.api, ext.ui.panels
    ct = api.import_volume(ct_crop_npy)
    assert (ct.volumeevm.units, ct.volumeevm.file_units) == ("HU", "HU")
    assert panels.units_source(ct.volumeevm) == "Units: the file says HU"
    skull = api.import_volume(data_dir / SKULL_NPY)
    assert (skull.volumeevm.units, skull.volumeevm.file_units) == ("", "")
    assert panels.units_source(skull.volumeevm) == "Units unknown: CT presets mean HU"
    given = api.import_volume(data_dir / SKULL_NPY, name="given", units="HU")
    assert (given.volumeevm.units, given.volumeevm.file_units) == ("HU", "")
    assert panels.units_source(given.volumeevm) == "Units set by you (the file gives none)"
    calls = volume_panel(ext)  # the active volume: given
    assert "Units set by you (the file gives none)" in texts(calls)
    assert ("prop", (given.volumeevm, "units")) in [c[:2] for c in calls]
    ct.volumeevm.units = "a.u."  # the Volume panel's field
    assert panels.units_source(ct.volumeevm) == "Units set by you (the file says HU)"
    # The volume's units are saved with it in the .blend.
    blend = tmp_path / "units.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(blend))
    bpy.ops.wm.open_mainfile(filepath=str(blend))
    saved = {o.name: (o.volumeevm.units, o.volumeevm.file_units) for o in bpy.data.objects
             if o.volumeevm.role == "VOLUME"}
    assert saved == {"ct_crop": ("a.u.", "HU"), "ct_skull_cgal": ("", ""), "given": ("HU", "")}
    # The import operator's Units field does what units= does.
    assert bpy.ops.volumeevm.import_volume(filepath=str(data_dir / SKULL_NPY), name="op",
                                           units="HU") == {"FINISHED"}
    assert bpy.data.objects["op"].volumeevm.units == "HU"


def ramp_matches(tf, want, value_range):
    """The colour ramp's transfer function ``tf`` classifies as ``want`` does (the ramp keeps
    positions in float32, and moves point i by i * 1e-6 of the range)."""
    values = np.linspace(*value_range, 2001)
    np.testing.assert_allclose(tf.evaluate(values), want.evaluate(values), atol=2e-3)
    np.testing.assert_allclose(tf.points[:, 0], want.points[:, 0],
                               atol=1e-5 * np.ptp(want.points[:, 0]))


@pytest.mark.parametrize("units", ["HU", ""])
@pytest.mark.parametrize("preset", ["ct_bone", "ct_skin", "ct_vessels"])
def test_a_ct_preset_means_hu_in_the_sidebar_as_in_a_script(ext, data_dir, units, preset):
    from volumeevm.volumeevm_addon import TransferFunction

    transfer = ext.blender.transfer
    vol = ext.blender.api.import_volume(data_dir / SKULL_NPY, units=units)  # 0 .. 5.4
    s = bpy.context.scene.volumeevm_render
    s.volume = vol
    s.preset = preset  # the sidebar's Preset menu
    assert not s.preset_stretch
    script = TransferFunction.preset(preset)
    ramp_matches(transfer.transfer_function(s), script, (-1100.0, 3100.0))
    assert transfer.preset_note(s, vol) == ""
    # Stretched only when asked, and the sidebar says so.
    s.preset_stretch = True
    lo, hi = vol.volumeevm.value_min, vol.volumeevm.value_max
    stretched = transfer.transfer_function(s)
    scale = (hi - lo) / (3071.0 + 1024.0)
    np.testing.assert_allclose(stretched.points[:, 0], lo + (script.points[:, 0] + 1024.0) * scale,
                               atol=1e-5 * (hi - lo))
    assert transfer.preset_note(s, vol) == (
        f"CT preset stretched from -1024 .. 3071 HU onto {lo:g} .. {hi:g}")
    # The operator's Load Preset keeps the choice; the script API can ask either way.
    assert bpy.ops.volumeevm.load_tf_preset() == {"FINISHED"}
    np.testing.assert_array_equal(transfer.transfer_function(s).points, stretched.points)
    transfer.load_preset(s, preset, vol, stretch=False)
    assert not s.preset_stretch
    ramp_matches(transfer.transfer_function(s), script, (-1100.0, 3100.0))


def test_a_ct_preset_on_data_in_other_units_says_so(ext, data_dir):
    transfer = ext.blender.transfer
    vol = ext.blender.api.import_volume(data_dir / SKULL_NPY, units="a.u.")
    s = bpy.context.scene.volumeevm_render
    s.volume = vol
    s.preset = "ct_vessels"
    assert transfer.preset_note(s, vol) == ("CT preset in HU on data in a.u.: stretch it, or "
                                            "set the volume's units")


# ---------------------------------------------------------------------------- framing
def volume_panel(ext):
    """The calls the Volume panel makes to draw the active volume."""
    from test_blender_ui import Recorder

    calls = []
    panel = type("P", (), {})()
    panel.layout = Recorder(calls)
    ext.ui.panels.VOLUMEEVM_PT_volume.draw(panel, bpy.context)
    return calls


@pytest.mark.parametrize("kind", ["PERSP", "ORTHO"])
@pytest.mark.parametrize("resolution", [(640, 360), (300, 500)])
def test_frame_volume_shows_the_whole_volume_from_every_side(ext, data_dir, kind, resolution):
    framing = ext.blender.framing
    scene = bpy.context.scene
    scene.render.resolution_x, scene.render.resolution_y = resolution
    vol = ext.blender.api.import_volume(data_dir / SKULL_NPY)
    vol.location = (0.3, -0.1, 0.05)  # a volume moved away from where the file put it
    bpy.context.view_layer.update()
    corners = framing.volume_corners(vol)
    camera = None
    for side in framing.SIDES:
        if side == "TOP":  # the operator, as the Volume panel's menu runs it
            assert bpy.ops.volumeevm.frame_volume(side=side) == {"FINISHED"}
            camera = scene.camera
        else:
            camera = ext.blender.api.frame_volume(vol, side)
        if camera.data.type != kind:
            camera.data.type = kind
            camera = ext.blender.api.frame_volume(vol, side)
        bpy.context.view_layer.update()
        view = ext.blender.camera.camera_from_blender(scene)
        uv, depth = view.project(corners)
        w, h = view.width, view.height
        assert np.all((uv >= 0) & (uv <= (w, h))), (side, uv)
        assert np.all((depth > camera.data.clip_start) & (depth < camera.data.clip_end)), side
        # Not a speck: the box spans at least a third of the image's shorter side.
        span = uv.max(axis=0) - uv.min(axis=0)
        assert span.max() > min(w, h) / 3, (side, span)
        # Seen from that side: the camera looks along the side's direction.
        np.testing.assert_allclose(view.forward, framing.SIDES[side][0], atol=1e-6)
    assert [o.name for o in bpy.data.objects if o.type == "CAMERA"] == [camera.name]


def test_import_finds_and_hides_the_cube_that_encloses_the_volume(ext, data_dir):
    bpy.ops.mesh.primitive_cube_add(size=2.0)  # the default scene's cube
    cube = bpy.context.active_object
    bpy.ops.mesh.primitive_cube_add(size=0.05, location=(0.1, 0.1, 0.1))  # inside the volume
    small = bpy.context.active_object
    framing = ext.blender.framing
    assert bpy.ops.volumeevm.import_volume(filepath=str(data_dir / SKULL_NPY)) == {"FINISHED"}
    vol = bpy.context.active_object
    assert framing.enclosing_objects(vol) == [cube]
    calls = volume_panel(ext)  # the Volume panel offers to hide it
    assert "Hidden inside Cube" in texts(calls)
    assert ("operator", ("volumeevm.hide_enclosing",)) in [c[:2] for c in calls]
    vol.location = (2.0, 0.0, 0.0)  # moved out of the cube
    bpy.context.view_layer.update()
    assert framing.enclosing_objects(vol) == []
    vol.location = (0.0, 0.0, 0.0)
    bpy.context.view_layer.update()
    assert bpy.ops.volumeevm.hide_enclosing() == {"FINISHED"}
    assert cube.hide_get() and cube.hide_render
    assert not small.hide_get() and not small.hide_render
    assert framing.enclosing_objects(vol) == []


# ---------------------------------------------------------------------------- smaller things
def test_a_blend_relative_file_in_an_unsaved_blend_is_refused(ext, data_dir, tmp_path,
                                                              monkeypatch):
    from volumeevm.volumeevm_addon import TransferFunction, VolumeEVMError

    monkeypatch.chdir(tmp_path)
    api = ext.blender.api
    vol = api.import_volume(data_dir / SKULL_NPY)
    api.build(vol, 2.9)
    api.frame_volume(vol)
    r = bpy.context.scene.render
    r.engine, r.resolution_x, r.resolution_y, r.resolution_percentage = "CYCLES", 48, 36, 100
    bpy.context.scene.cycles.samples = 1
    tf = TransferFunction.preset("mri", data_range=(0.0, 5.5))
    for key in ("png_path", "exr_path"):
        with pytest.raises(VolumeEVMError, match=f"{key}: '//out' is relative to the .blend "
                                                 f"file, which is not saved yet"):
            api.render_dvr(vol, tf, **{key: "//out"})
    s = bpy.context.scene.volumeevm_render
    s.volume, s.use_png = vol, True  # the default PNG file: //volumeevm.png
    with pytest.raises(RuntimeError, match="png_path: '//volumeevm.png' is relative to the "):
        bpy.ops.volumeevm.render_dvr()  # the operator reports the error
    assert list(tmp_path.iterdir()) == []  # nothing written into the current directory
    bpy.ops.wm.save_as_mainfile(filepath=str(tmp_path / "saved" / "scene.blend"))
    result = api.render_dvr(vol, tf, png_path="//out.png")
    assert result.png_path == str(tmp_path / "saved" / "out.png")
    assert (tmp_path / "saved" / "out.png").is_file()


def test_an_unknown_method_error_lists_every_method(ext, data_dir):
    from volumeevm.volumeevm_addon import TransferFunction, VolumeEVMError

    api, dvr = ext.blender.api, ext.blender.dvr
    vol = api.import_volume(data_dir / SKULL_NPY)
    api.frame_volume(vol)
    with pytest.raises(VolumeEVMError) as error:
        api.render_dvr(vol, TransferFunction.preset("ct_bone"), method="raytrace")
    assert str(error.value) == f"method: one of {dvr.METHODS}, got 'raytrace'"
    assert "gpu" in dvr.METHODS and "raycast" in dvr.METHODS


def test_the_api_says_how_to_enable_the_extension(ext, data_dir):
    from volumeevm.volumeevm_addon import VolumeEVMError

    api = ext.blender.api
    ext.unregister()
    try:
        message = ("the VolumeEVM extension is not enabled: call "
                   "bpy.ops.preferences.addon_enable(module='volumeevm')")
        with pytest.raises(VolumeEVMError) as error:
            api.import_volume(data_dir / SKULL_NPY)
        assert str(error.value) == message
        with pytest.raises(VolumeEVMError) as error:
            api.build(bpy.data.objects.new("x", None))
        assert str(error.value) == message
    finally:
        ext.register()
