"""The Blender side never locks up, and memory is checked before it is spent (real bpy).

An unexpected exception anywhere in a job (``job()``, a step, the commit, ``finished``) ends it:
the operator reports the error (the traceback goes to the console), the running-job marker and
the timer are gone, the scene is exactly as it was before the job, and the next job runs. The
synchronous path runs through ``bpy.ops`` (an ERROR report raises ``RuntimeError`` there); the
modal path runs the operator's timer handler directly (the bpy module has no event loop), with
the minimal window manager of ``test_blender_ui`` that hands out timer events. The tool stack's
operators leave no busy flag behind either; a bug while its surface is rewritten leaves the old
surface, and one while refreshing after removing or moving an entry leaves the entries as they
were. A render failing after its images were filled or its EXR written leaves the images
(names, sizes, pixels) and the files on disk as they were. A small memory budget
(``VOLUMEEVM_MEMORY_LIMIT``) makes Import and Build end with an error that says how much memory
is needed, the scene unchanged.

Runs under both pinned bpy versions (4.5 on Python 3.11, 5.2 on Python 3.13).
"""

import re

import bpy
import numpy as np
import pytest
from test_blender_tools import box_object
from test_blender_ui import _Context, _driver, _ticks

from blender_helpers import add_camera, addon, cycles, mesh_arrays, settings_for

SKULL = "ct_skull_cgal.npy"
SKULL_THRESHOLD = 2.9
UNEXPECTED = r"unexpected error \(ZeroDivisionError: a bug\); nothing was changed"
NEEDS_MEMORY = r"needs about \d+(\.\d)? (bytes|KiB|MiB|GiB) of memory"


def _bug(*_args, **_kwargs):
    raise ZeroDivisionError("a bug")


def _plain(value):
    """An RNA value as plain Python (datablocks by name, arrays as tuples, collections sized)."""
    if isinstance(value, bpy.types.ID):
        return value.name
    if isinstance(value, bpy.types.bpy_prop_collection):
        return len(value)
    if isinstance(value, bpy.types.bpy_prop_array):
        return tuple(value)
    return value


def scene_state(api):
    """Everything a job could change: every datablock (by session id and name), each object's
    data, selection, parent and VolumeEVM settings, each mesh's size, the active object, and the
    session's sidecar files."""
    blocks = set()
    for prop in bpy.data.bl_rna.properties:
        if prop.type == "COLLECTION":
            blocks |= {(prop.identifier, b.session_uid, b.name)
                       for b in getattr(bpy.data, prop.identifier)}
    objects = {}
    for obj in bpy.data.objects:
        s = obj.volumeevm
        settings = {p.identifier: _plain(getattr(s, p.identifier))
                    for p in s.bl_rna.properties if p.identifier != "rna_type"}
        objects[obj.name] = (_plain(obj.data), obj.data.session_uid, obj.select_get(),
                             _plain(obj.parent) if obj.parent else None, settings)
    meshes = {m.name: (len(m.vertices), len(m.polygons)) for m in bpy.data.meshes}
    active = bpy.context.view_layer.objects.active
    sidecars = sorted(p.name for p in addon().blender.sidecar.session_dir().glob("*.vevm"))
    return blocks, objects, meshes, active.name if active else None, sidecars


@pytest.fixture
def jobs(ext):
    return ext.blender.jobs


@pytest.fixture
def skull(data_dir):
    return str(data_dir / SKULL)


def _imported(api, skull):
    obj = api.import_volume(skull)
    bpy.context.view_layer.objects.active = obj
    return obj


def _meshed(api, skull):
    """The skull imported, built and meshed (an existing surface to replace)."""
    obj = _imported(api, skull)
    api.build(obj, SKULL_THRESHOLD)
    api.make_mesh(obj)
    bpy.context.view_layer.objects.active = obj
    return obj


def _assert_ended(jobs, capsys):
    """No job runs any more, and the traceback of the bug went to the console."""
    assert jobs.CURRENT is None
    err = capsys.readouterr().err
    assert "Traceback (most recent call last)" in err and "ZeroDivisionError: a bug" in err


# ---------------------------------------------------------------------------- synchronous path
@pytest.mark.parametrize("operator", ["import", "build", "mesh"])
def test_unexpected_error_in_a_step_ends_the_job_scene_unchanged(
        ext, api, jobs, skull, monkeypatch, capsys, operator):
    if operator == "import":
        _imported(api, skull)  # something in the scene to keep
        monkeypatch.setattr(ext.blender.volumes, "read_volume", _bug)
        run = lambda: bpy.ops.volumeevm.import_volume(filepath=skull)  # noqa: E731
        label = "Import ct_skull_cgal"
    elif operator == "build":
        _imported(api, skull)
        monkeypatch.setattr(ext.volumeevm_addon.VolumeEVM, "from_volume", _bug)
        run = lambda: bpy.ops.volumeevm.build_vevm(  # noqa: E731
            use_settings=False, threshold=SKULL_THRESHOLD)
        label = "Build VolumeEVM of ct_skull_cgal"
    else:
        _meshed(api, skull)
        monkeypatch.setattr(ext.blender.volumes, "surface_geometry", _bug)
        run = bpy.ops.volumeevm.make_mesh
        label = "Mesh of ct_skull_cgal"
    before = scene_state(api)
    with pytest.raises(RuntimeError, match=f"{label}: {UNEXPECTED}"):
        run()
    _assert_ended(jobs, capsys)
    assert scene_state(api) == before
    monkeypatch.undo()
    assert run() == {"FINISHED"}  # the next job runs
    assert scene_state(api) != before


@pytest.mark.parametrize("where", ["import", "build", "mesh"])
def test_commit_failing_half_way_is_undone(ext, api, jobs, skull, monkeypatch, capsys, where):
    """The commit (or ``finished`` after it) raises after writing into Blender: all undone."""
    if where == "import":  # after the new object was linked and selected
        _imported(api, skull)
        monkeypatch.setattr(ext.blender.runtime, "forget_except", _bug)
        run = lambda: bpy.ops.volumeevm.import_volume(filepath=skull)  # noqa: E731
    elif where == "build":  # a rebuild, after the settings and sidecar were written
        obj = _meshed(api, skull)
        assert obj.volumeevm.vevm_path
        monkeypatch.setattr(ext.blender.runtime, "put_volume", _bug)
        run = lambda: bpy.ops.volumeevm.build_vevm(use_settings=False, threshold=4.0)  # noqa: E731
    else:  # a new mesh for an existing surface, then the summary fails
        _meshed(api, skull)
        monkeypatch.setattr(bpy.types.VOLUMEEVM_OT_make_mesh, "finished", _bug)
        run = bpy.ops.volumeevm.make_mesh
    before = scene_state(api)
    with pytest.raises(RuntimeError, match=UNEXPECTED):
        run()
    _assert_ended(jobs, capsys)
    assert scene_state(api) == before
    monkeypatch.undo()
    assert run() == {"FINISHED"}


def test_script_api_raises_and_leaves_the_scene_unchanged(ext, api, jobs, skull, monkeypatch):
    _imported(api, skull)
    before = scene_state(api)
    monkeypatch.setattr(ext.blender.runtime, "forget_except", _bug)
    with pytest.raises(ZeroDivisionError, match="a bug"):
        api.import_volume(skull)
    assert scene_state(api) == before and jobs.CURRENT is None


# ---------------------------------------------------------------------------- modal path
@pytest.mark.parametrize("where", ["job", "step", "commit"])
def test_modal_job_error_clears_marker_and_timer(ext, api, jobs, skull, monkeypatch, capsys,
                                                 where):
    obj = _imported(api, skull)
    if where == "job":
        make_job = _bug
    else:
        make_job = lambda: ext.blender.volumes.build_job(  # noqa: E731
            obj, SKULL_THRESHOLD)
        if where == "step":
            monkeypatch.setattr(ext.volumeevm_addon.VolumeEVM, "from_volume", _bug)
        else:
            monkeypatch.setattr(ext.blender.runtime, "put_volume", _bug)
    before = scene_state(api)
    context = _Context()
    op = _driver(ext, make_job)
    started = op.start(context)
    if where == "job":
        assert started == {"CANCELLED"}
    else:
        assert started == {"RUNNING_MODAL"} and jobs.CURRENT is not None
        assert _ticks(op, context) == {"CANCELLED"}
    _assert_ended(jobs, capsys)
    assert context.window_manager.timers == []
    assert op.reports[-1][0] == {"ERROR"}
    label = "" if where == "job" else "Build VolumeEVM of ct_skull_cgal: "
    assert op.reports[-1][1].startswith(f"{label}unexpected error (ZeroDivisionError: a bug)")
    assert scene_state(api) == before
    # The panel is usable again: the next job runs from the timer and commits.
    monkeypatch.undo()
    op = _driver(ext, lambda: ext.blender.volumes.build_job(obj, SKULL_THRESHOLD))
    context = _Context()
    assert op.start(context) == {"RUNNING_MODAL"}
    assert _ticks(op, context) == {"FINISHED"}
    assert jobs.CURRENT is None and context.window_manager.timers == []
    assert obj.volumeevm.voxel_count == api.get_vevm(obj).voxel_count > 0


# ---------------------------------------------------------------------------- tool stack
def _middle_box(obj):
    """A box object over the middle half of a volume object's wire box."""
    corners = np.empty(24, np.float32)
    obj.data.vertices.foreach_get("co", corners)
    corners = corners.reshape(8, 3)
    lo, hi = corners.min(axis=0), corners.max(axis=0)
    return box_object("cutter", lo + 0.25 * (hi - lo), hi - 0.25 * (hi - lo))


@pytest.mark.parametrize("where", ["voxelize", "write"])
def test_tool_error_leaves_no_busy_flag_and_no_entry(ext, api, skull, monkeypatch, capsys,
                                                     where):
    obj = _meshed(api, skull)
    box = _middle_box(obj)
    obj.volumeevm.tool_object = box
    bpy.context.view_layer.objects.active = obj
    # "write": the entry is stored, then making the surface's new mesh fails.
    monkeypatch.setattr(ext.blender.tool_stack,
                        "voxelize_tool" if where == "voxelize" else "_write_surface", _bug)
    before = scene_state(api)
    with pytest.raises(RuntimeError, match=f"Cut: {UNEXPECTED}"):
        bpy.ops.volumeevm.tool_cut()
    assert not ext.blender.tool_stack.is_busy()
    assert "ZeroDivisionError: a bug" in capsys.readouterr().err
    assert scene_state(api) == before and len(obj.volumeevm.tools) == 0
    monkeypatch.undo()
    assert bpy.ops.volumeevm.tool_cut() == {"FINISHED"}
    assert len(obj.volumeevm.tools) == 1 and not ext.blender.tool_stack.is_busy()


def _cutter(api, skull):
    """The meshed skull with a Cut entry of a box through its middle; returns (volume, box)."""
    obj = _meshed(api, skull)
    box = _middle_box(obj)
    api.add_tool(obj, box, "cut")
    bpy.context.view_layer.objects.active = obj
    return obj, box


def _geometry(surface):
    """Vertex positions, loop vertices, loop starts and totals of a surface's mesh."""
    return tuple(array.copy() for array in mesh_arrays(surface.data))


def _assert_same_geometry(surface, geometry):
    for now, before in zip(_geometry(surface), geometry, strict=True):
        np.testing.assert_array_equal(now, before)


def test_fill_mesh_failing_half_way_keeps_the_old_surface(ext, api, skull, monkeypatch, capsys):
    """A bug inside ``fill_mesh`` after it added vertices: the surface keeps its old geometry,
    from the live refresh (depsgraph handler) and from the Refresh operator alike."""
    obj, box = _cutter(api, skull)
    surface = ext.blender.objects.own_surface(obj)
    geometry = _geometry(surface)
    signature = surface.volumeevm.stack_signature
    real_fill = ext.blender.meshes.fill_mesh
    calls = []

    def fill_half_then_bug(mesh, co, polys):
        calls.append(len(co))
        if len(calls) == 1:  # the new geometry: half written, then the bug
            mesh.vertices.add(len(co))
            raise ZeroDivisionError("a bug")
        real_fill(mesh, co, polys)  # putting the old geometry back

    monkeypatch.setattr(ext.blender.meshes, "fill_mesh", fill_half_then_bug)
    box.location.x += 0.01  # the live refresh: a new result to write
    before = scene_state(api)
    bpy.context.view_layer.update()
    # The new geometry was tried, then the old one put back.
    assert len(calls) == 2 and calls[0] != calls[1] == len(geometry[0])
    _assert_same_geometry(surface, geometry)
    assert (surface.volumeevm.stack_signature == signature
            and not ext.blender.tool_stack.is_busy())
    assert "unexpected error while refreshing" in api.stack_state(obj).problem
    assert "ZeroDivisionError: a bug" in capsys.readouterr().err
    assert scene_state(api) == before

    calls.clear()
    with pytest.raises(RuntimeError, match=f"Refresh: {UNEXPECTED}"):
        bpy.ops.volumeevm.tool_refresh()
    assert len(calls) == 2 and not ext.blender.tool_stack.is_busy()
    _assert_same_geometry(surface, geometry)
    assert scene_state(api) == before
    monkeypatch.undo()
    assert bpy.ops.volumeevm.tool_refresh() == {"FINISHED"}
    assert len(surface.data.polygons) != len(geometry[2])  # the moved cut is shown now


def _entries(obj):
    return [(e.operation, e.tool.name if e.tool else None, e.enabled, e.use_density, e.density)
            for e in obj.volumeevm.tools]


@pytest.mark.parametrize("change", ["remove", "move"])
def test_failing_refresh_after_remove_or_move_keeps_the_entries(ext, api, skull, monkeypatch,
                                                                capsys, change):
    obj, _box = _cutter(api, skull)
    api.add_tool(obj, None, "largest")
    obj.volumeevm.tool_index = 0
    entries = _entries(obj)
    assert len(entries) == 2
    geometry = _geometry(ext.blender.objects.own_surface(obj))
    before = scene_state(api)
    monkeypatch.setattr(ext.blender.tool_stack, "_write_surface", _bug)  # after the evaluation
    if change == "remove":
        run = lambda: bpy.ops.volumeevm.tool_remove(index=0)  # noqa: E731
        label = "Remove Tool Entry"
    else:
        run = bpy.ops.volumeevm.tool_move_down
        label = "Move Tool Entry Down"
    with pytest.raises(RuntimeError, match=f"{label}: {UNEXPECTED}"):
        run()
    assert "ZeroDivisionError: a bug" in capsys.readouterr().err
    assert _entries(obj) == entries and obj.volumeevm.tool_index == 0
    assert scene_state(api) == before and not ext.blender.tool_stack.is_busy()
    _assert_same_geometry(ext.blender.objects.own_surface(obj), geometry)
    monkeypatch.undo()
    assert run() == {"FINISHED"}
    expected = entries[1:] if change == "remove" else entries[::-1]
    assert _entries(obj) == expected


# ---------------------------------------------------------------------------- render
def _images():
    """Every image: name -> (session id, size, pixels)."""
    found = {}
    for image in bpy.data.images:
        pixels = np.empty(len(image.pixels), np.float32)
        image.pixels.foreach_get(pixels)
        found[image.name] = (image.session_uid, tuple(image.size), pixels)
    return found


def _assert_same_images(images):
    now = _images()
    assert sorted(now) == sorted(images)
    for name, (uid, size, pixels) in images.items():
        assert now[name][:2] == (uid, size)
        np.testing.assert_array_equal(now[name][2], pixels)


def _files(folder):
    return {p.name: p.read_bytes() for p in sorted(folder.iterdir())}


@pytest.mark.parametrize("where", ["exr", "png", "finished"])
def test_render_failing_after_images_or_files_leaves_them_as_they_were(
        ext, api, jobs, skull, tmp_path, monkeypatch, capsys, where):
    """The render's commit (or its report) fails after the images were filled, or after the
    EXR was written: the existing images keep their names, sizes and pixels, a replaced file
    is the old one again and no new file is left."""
    dvr = ext.blender.dvr
    obj = _imported(api, skull)
    api.build(obj, SKULL_THRESHOLD)
    scene = bpy.context.scene
    add_camera(scene, (-0.3, -0.5, 0.3))
    cycles(scene, (40, 30))
    bpy.ops.render.render()  # Blender's "Render Result" image exists (the scene pass renders)
    rng = np.random.default_rng(9)
    # The composite's name: a float image of another size (reused in place, resized).
    reused = bpy.data.images.new(dvr.DEFAULT_IMAGE, 7, 5, alpha=True, float_buffer=True)
    reused.pixels.foreach_set(rng.random(7 * 5 * 4, np.float32))
    reused.alpha_mode = "STRAIGHT"
    # The DVR image's name: an 8-bit image, unused (it makes way, and goes once a render works).
    other = bpy.data.images.new(f"{dvr.DEFAULT_IMAGE} DVR", 3, 2, alpha=True)
    other.pixels.foreach_set(rng.integers(0, 256, 3 * 2 * 4).astype(np.float32) / 255)
    exr_file, png_file = tmp_path / "a.exr", tmp_path / "a.png"
    if where == "finished":  # the EXR is new, the PNG replaces an old one
        png_file.write_bytes(b"the old PNG")
    else:  # the EXR replaces an old one, the PNG is new
        exr_file.write_bytes(b"the old EXR")
    settings_for(scene, obj, tmp_path, use_exr=True, exr_path=str(exr_file), use_png=True,
                 png_path=str(png_file), overwrite=True)
    target = {"exr": (dvr.exr, "write_exr"), "png": (ext.blender.images, "write_png"),
              "finished": (bpy.types.VOLUMEEVM_OT_render_dvr, "finished")}[where]
    monkeypatch.setattr(*target, _bug)
    images, files, before = _images(), _files(tmp_path), scene_state(api)
    with pytest.raises(RuntimeError, match=f"Render ct_skull_cgal: {UNEXPECTED}"):
        bpy.ops.volumeevm.render_dvr()
    _assert_ended(jobs, capsys)
    _assert_same_images(images)
    assert reused.alpha_mode == "STRAIGHT"
    assert dvr.VIEW_KEY not in reused and dvr.VIEW_KEY not in other
    assert _files(tmp_path) == files  # nor a temporary, nor a kept old file
    assert scene_state(api) == before
    monkeypatch.undo()
    assert bpy.ops.volumeevm.render_dvr() == {"FINISHED"}
    assert bpy.data.images[dvr.DEFAULT_IMAGE] == reused and tuple(reused.size) == (40, 30)
    assert bpy.data.images[f"{dvr.DEFAULT_IMAGE} DVR"].is_float
    assert f"{dvr.DEFAULT_IMAGE} DVR (old)" not in bpy.data.images  # unused: removed
    written = _files(tmp_path)
    assert sorted(written) == ["a.exr", "a.png"]
    assert written["a.exr"] != b"the old EXR" and written["a.png"] != b"the old PNG"


# ---------------------------------------------------------------------------- memory
def test_memory_budget_refuses_import_scene_unchanged(api, jobs, skull, monkeypatch):
    before = scene_state(api)
    monkeypatch.setenv("VOLUMEEVM_MEMORY_LIMIT", "4K")
    with pytest.raises(RuntimeError, match=f"{re.escape(skull)}: .*{NEEDS_MEMORY}"):
        bpy.ops.volumeevm.import_volume(filepath=skull)
    assert scene_state(api) == before and jobs.CURRENT is None
    monkeypatch.delenv("VOLUMEEVM_MEMORY_LIMIT")
    assert bpy.ops.volumeevm.import_volume(filepath=skull) == {"FINISHED"}


def test_memory_budget_refuses_build_scene_unchanged(api, jobs, skull, monkeypatch):
    obj = _imported(api, skull)  # the dense volume is cached: Build only builds
    before = scene_state(api)
    monkeypatch.setenv("VOLUMEEVM_MEMORY_LIMIT", "4K")
    with pytest.raises(RuntimeError, match=f"{re.escape(skull)}: .*{NEEDS_MEMORY}"):
        bpy.ops.volumeevm.build_vevm(use_settings=False, threshold=SKULL_THRESHOLD)
    assert scene_state(api) == before and jobs.CURRENT is None
    assert obj.volumeevm.vevm_path == ""
    monkeypatch.delenv("VOLUMEEVM_MEMORY_LIMIT")
    assert bpy.ops.volumeevm.build_vevm(use_settings=False,
                                        threshold=SKULL_THRESHOLD) == {"FINISHED"}
