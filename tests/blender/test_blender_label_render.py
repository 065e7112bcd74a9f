"""Label maps volume-rendered in the real bpy with their label colours: the label table stored
on the volume object on import (names and colours from the file), Render VolumeEVM and F12
against the core's reference with the same categorical function, hiding a label removes its
colour, the table survives save and reload, the sidebar's list, and the Viewport DVR's draw
(GPU) against the reference within the GPU's bounds.

Runs under both pinned bpy versions (4.5 on Python 3.11, 5.2 on Python 3.13).
"""

import importlib
import json

import bpy
import numpy as np
import pytest

from blender_helpers import cycles, f12_exr, image_rgba

#: (mean, 99th percentile, worst) of the largest channel error of the ray caster's DVR to the
#: reference on the Slicer segmentation (the core's liver bounds, test_categorical_render);
#: measured 0.00054, 0.0074, 0.022.
BOUNDS = (0.002, 0.05, 0.2)
#: Skin (1) around two organs (2 in front of 3), in voxels.
SHAPE = (20, 18, 16)


@pytest.fixture
def segmentation(data_dir):
    return data_dir / "slicer" / "Segmentation.seg.nrrd"


def errors(rgba, ref):
    err = np.abs(rgba - ref).max(axis=-1)
    return err.mean(), np.percentile(err, 99), err.max()


def framed(api, vol, size):
    """``vol`` built with every label, a front camera, Cycles at ``size`` (transparent film)."""
    api.build(vol, vol.volumeevm.threshold)
    api.frame_volume(vol, "FRONT")
    cycles(bpy.context.scene, size)
    return api.get_vevm(vol)


@pytest.fixture
def organs(tmp_path):
    """A synthetic label map (``.npy`` read with ``labels=True``): a two-voxel skin (1) around
    organ 2 and organ 3 behind it, 2 mm voxels."""
    a = np.zeros(SHAPE, np.uint8)
    a[1:-1, 1:-1, 1:-1] = 1
    a[3:-3, 3:9, 3:-3] = 2
    a[3:-3, 9:-3, 3:-3] = 3
    path = tmp_path / "organs.npy"
    np.save(path, a)
    path.with_suffix(".json").write_text(json.dumps({"spacing_mm": [2.0, 2.0, 2.0]}))
    return path


def test_the_label_table_is_stored_on_import(api, core, segmentation):
    vol = api.import_volume(segmentation)
    infos = core.read_volume(segmentation).labels
    s = vol.volumeevm
    assert [row.label for row in s.labels] == sorted(infos) == list(range(1, 8))
    for row in s.labels:
        assert row.name == infos[row.label].name and row.show and row.opacity == 0.5
        assert tuple(row.color) == pytest.approx(infos[row.label].color, abs=1e-6)
    assert s.use_label_colors and s.threshold == 1.0  # Build's region holds every label
    tf = api.volume_transfer_function(bpy.context.scene.volumeevm_render, vol)
    want = core.TransferFunction.categorical(infos, opacity=0.5)
    assert tf.is_categorical
    np.testing.assert_allclose(tf.points, want.points, atol=1e-6)  # float32 colours
    assert len(api.import_volume(segmentation, labels=False).volumeevm.labels) == 0


def test_render_and_f12_match_the_reference_with_the_label_colours(ext, api, core, segmentation,
                                                                    tmp_path):
    vol = api.import_volume(segmentation)
    vevm = framed(api, vol, (48, 40))
    scene = bpy.context.scene
    settings = scene.volumeevm_render
    settings.volume, settings.method = vol, "raycast"
    assert bpy.ops.volumeevm.render_dvr() == {"FINISHED"}
    dvr = ext.blender.dvr
    rgba = image_rgba(f"{dvr.DEFAULT_IMAGE} DVR")
    tf = api.label_transfer_function(vol, unit_length_mm=settings.unit_length_mm)
    camera = ext.blender.camera.camera_from_blender(scene)
    ref, _ = core.render(vevm, camera, tf, method="reference",
                         matrix_world=np.array(vol.matrix_world))
    assert ref[..., 3].mean() > 0.05
    mean, p99, worst = errors(rgba, ref)
    assert mean < BOUNDS[0] and p99 < BOUNDS[1] and worst < BOUNDS[2]
    # The ramp's function (the volume's values as densities) gives another image.
    settings.preset = "mri"
    plain, _ = core.render(vevm, camera, api.transfer_function(settings), method="raycast",
                           matrix_world=np.array(vol.matrix_world))
    assert np.abs(plain - rgba).max() > 0.1
    # F12 lays the DVR over the (empty, transparent) scene render.
    assert bpy.ops.volumeevm.setup_compositor() == {"FINISHED"}
    f12 = f12_exr(scene, tmp_path / "f12.exr")
    np.testing.assert_allclose(f12, image_rgba(dvr.DEFAULT_IMAGE), atol=2e-3)
    mean, p99, worst = errors(f12, ref)
    assert mean < BOUNDS[0] and p99 < BOUNDS[1] and worst < BOUNDS[2]
    # Label colours off: the sidebar's colour ramp again.
    vol.volumeevm.use_label_colors = False
    tf_off = api.volume_transfer_function(settings, vol)
    assert not tf_off.is_categorical
    np.testing.assert_array_equal(tf_off.points, api.transfer_function(settings).points)


def colours(api, vol, **options):
    """``vol``'s DVR (ray casting, the label colours), premultiplied RGBA."""
    return api.render_dvr(vol, method="raycast", options=options).dvr_rgba


def test_hiding_a_label_removes_its_colour(api, core, organs):
    vol = api.import_volume(organs, labels=True)
    assert [row.name for row in vol.volumeevm.labels] == ["label 1", "label 2", "label 3"]
    framed(api, vol, (40, 36))
    for label, colour in ((1, (1.0, 0.0, 0.0)), (2, (0.0, 1.0, 0.0)), (3, (0.0, 0.0, 1.0))):
        row = api.set_label(vol, label, color=colour, opacity=1.0)
        assert row == {"name": f"label {label}", "color": colour, "opacity": 1.0,
                       "visible": True}
    skin = colours(api, vol)
    assert skin[..., 0].max() == pytest.approx(1.0)  # opaque skin hides the organs
    assert skin[..., 1].max() == skin[..., 2].max() == 0.0
    api.set_label(vol, 1, visible=False)
    inside = colours(api, vol)
    assert inside[..., 0].max() == 0.0  # no pixel of the skin's colour is left
    assert inside[..., 1].max() == pytest.approx(1.0)  # organ 2, in front
    assert inside[..., 2].max() == 0.0  # organ 3 behind it, hidden by its opacity
    assert (inside[..., 3] > 0).sum() < (skin[..., 3] > 0).sum()  # the skin's rim is gone
    api.set_label(vol, 2, opacity=0.0)
    behind = colours(api, vol)
    assert behind[..., 0].max() == behind[..., 1].max() == 0.0
    assert behind[..., 2].max() == pytest.approx(1.0)
    api.set_label(vol, 1, visible=True)
    np.testing.assert_array_equal(colours(api, vol), skin)
    assert api.get_label(vol, 1)["visible"]


def test_bad_label_settings_are_refused_and_nothing_changes(api, core, organs):
    vol = api.import_volume(organs, labels=True)
    before = api.get_label(vol, 2)
    for kwargs, word in (({"color": (1.0, 0.0)}, "color"), ({"color": (2.0, 0.0, 0.0)}, "color"),
                         ({"color": "red"}, "color"),
                         ({"opacity": 1.5, "visible": False}, "opacity")):
        with pytest.raises(core.VolumeEVMError, match=word):
            api.set_label(vol, 2, **kwargs)
        assert api.get_label(vol, 2) == before
    with pytest.raises(core.VolumeEVMError, match=r"no label 9 \(its labels: \[1, 2, 3\]\)"):
        api.set_label(vol, 9, visible=False)
    plain = api.import_volume(organs)
    with pytest.raises(core.VolumeEVMError, match="not a label map"):
        api.label_transfer_function(plain)


def test_the_label_table_survives_save_and_reload(api, core, organs, tmp_path):
    vol = api.import_volume(organs, labels=True)
    api.set_label(vol, 1, visible=False)
    api.set_label(vol, 2, color=(0.25, 0.5, 0.75), opacity=0.2)
    vol.volumeevm.use_label_colors = False
    vol.volumeevm.label_index = 2
    tf = api.label_transfer_function(vol)
    blend = tmp_path / "labels.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(blend))
    bpy.ops.wm.read_factory_settings(use_empty=True)
    assert "organs" not in bpy.data.objects
    bpy.ops.wm.open_mainfile(filepath=str(blend))
    vol = bpy.data.objects["organs"]
    s = vol.volumeevm
    assert [row.label for row in s.labels] == [1, 2, 3]
    assert not s.labels[0].show and s.labels[1].show and s.labels[2].show
    assert tuple(s.labels[1].color) == pytest.approx((0.25, 0.5, 0.75))
    assert s.labels[1].opacity == pytest.approx(0.2)
    assert not s.use_label_colors and s.label_index == 2
    np.testing.assert_array_equal(api.label_transfer_function(vol).points, tf.points)


def test_the_sidebar_lists_the_labels_and_edits_them(ext, api, organs):
    from test_blender_ui import Recorder, texts

    vol = api.import_volume(organs, labels=True)
    bpy.context.scene.volumeevm_render.volume = vol
    render_panel = ext.ui.render_panel

    def draw():
        calls = []
        panel = type("P", (), {})()
        panel.layout = Recorder(calls)
        render_panel.VOLUMEEVM_PT_render.draw(panel, bpy.context)
        return calls

    calls = draw()
    assert any(name == "template_list" and args[0] == "VOLUMEEVM_UL_label_colors"
               for name, args, _ in calls)
    assert not any(name == "template_color_ramp" for name, _, _ in calls)
    assert "Each sample takes its nearest voxel's label" in texts(calls)
    rows = []
    row = vol.volumeevm.labels[0]
    render_panel.VOLUMEEVM_UL_label_colors.draw_item(None, bpy.context, Recorder(rows), None,
                                                     row, 0, None, "")
    props = [(args[1], kw.get("icon")) for name, args, kw in rows if name == "prop"]
    assert props == [("show", "HIDE_OFF"), ("color", None), ("opacity", None)]
    assert "label 1" in texts(rows)
    row.show = False  # as the eye button does: the next render leaves label 1 out
    assert api.label_transfer_function(vol).evaluate([1.0])[0, 3] == 0.0
    vol.volumeevm.use_label_colors = False
    calls = draw()
    assert not any(name == "template_list" for name, _, _ in calls)
    assert any(name == "prop" and args[1] == "use_label_colors" for name, args, _ in calls)


def test_viewport_draws_the_label_colours_within_the_gpu_bounds(ext, api, core, segmentation):
    """The Viewport DVR's drawing (``draw_view``, as the draw handler calls it) takes the label
    map's categorical function; drawn on the GPU it is within the GPU's label-map bound of
    test_gpu_render (no more than 1.5 times the CPU ray caster's RMSE to the reference)."""
    import gpu
    from mathutils import Matrix

    gpu_context, viewport = ext.blender.gpu_context, ext.blender.gpu_viewport
    try:
        gpu_context.ensure_context()
    except gpu_context.GPUUnavailable as error:
        pytest.skip(str(error))
    vol = api.import_volume(segmentation)
    vevm = framed(api, vol, (48, 40))
    scene = bpy.context.scene
    settings = scene.volumeevm_render
    settings.viewport = True
    camera = ext.blender.camera.camera_from_blender(scene)
    h, w = camera.shape
    projection = Matrix(camera.matrix_projection().tolist())
    view = Matrix(np.linalg.inv(camera.matrix_world).tolist())
    drawn = []
    draw_volume = viewport.draw_volume

    def traced(vevm, tf, *args, **options):
        drawn.append((tf, options))
        return draw_volume(vevm, tf, *args, **options)

    viewport.draw_volume = traced
    offscreen = gpu.types.GPUOffScreen(w, h, format="RGBA32F")
    try:
        with offscreen.bind():
            framebuffer = gpu.state.active_framebuffer_get()
            framebuffer.clear(color=(0.0, 0.0, 0.0, 0.0), depth=1.0)
            viewport.draw_view(scene, [vol], "labels", (w, h), projection, view)
            assert viewport.problem(vol) == ""
            (tf, options), = drawn
            options = {k: v for k, v in options.items() if k != "display"}  # scene-linear
            framebuffer.clear(color=(0.0, 0.0, 0.0, 0.0), depth=1.0)
            viewport.draw_volume(vevm, tf, projection, view, (w, h), **options)
            rgba = np.empty((h, w, 4), np.float32)
            framebuffer.read_color(0, 0, w, h, 4, 0, "FLOAT",
                                   data=gpu.types.Buffer("FLOAT", rgba.size, rgba))
    finally:
        viewport.draw_volume = draw_volume
        offscreen.free()
        settings.viewport = False
    want = api.label_transfer_function(vol, unit_length_mm=settings.unit_length_mm)
    assert tf.is_categorical
    np.testing.assert_array_equal(tf.points, want.points)
    rgba = np.flipud(rgba)
    matrix_world = np.array(vol.matrix_world)
    ref, _ = core.render(vevm, camera, tf, method="reference", matrix_world=matrix_world)
    cpu_options = {k: v for k, v in options.items() if k in ("step_mm", "termination")}
    cpu, _ = core.render(vevm, camera, tf, method="raycast", matrix_world=matrix_world,
                         **cpu_options)
    rmse = importlib.import_module(f"{core.__name__}.metrics").rmse
    assert ref[..., 3].mean() > 0.05 and rgba[..., 3].max() > 0.3
    assert rmse(rgba, ref) <= 1.5 * rmse(cpu, ref) + 1e-5
