"""The Blender side never locks up, and memory is checked before it is spent (real bpy).

An unexpected exception anywhere in a job (``job()``, a step, the commit, ``finished``) ends it:
the operator reports the error (the traceback goes to the console), the running-job marker and
the timer are gone, the scene is exactly as it was before the job, and the next job runs. The
synchronous path runs through ``bpy.ops`` (an ERROR report raises ``RuntimeError`` there); the
modal path runs the operator's timer handler directly (the bpy module has no event loop), with
the minimal window manager of ``test_blender_ui`` that hands out timer events. The tool stack's
operators leave no busy flag behind either. A small memory budget
(``VOLUMEEVM_MEMORY_LIMIT``) makes Import and Build end with an error that says how much memory
is needed, the scene unchanged.

Runs under both pinned bpy versions (4.5 on Python 3.11, 5.2 on Python 3.13).
"""

import re

import bpy
import numpy as np
import pytest
from blender_helpers import api, ext, fresh  # noqa: F401 (fixtures)
from test_blender_tools import box_object
from test_blender_ui import _Context, _driver, _ticks

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
    sidecars = sorted(p.name for p in api.sidecar.session_dir().glob("*.vevm"))
    return blocks, objects, meshes, active.name if active else None, sidecars


@pytest.fixture
def jobs(ext):
    return ext.operators._jobs


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
        api, jobs, skull, monkeypatch, capsys, operator):
    if operator == "import":
        _imported(api, skull)  # something in the scene to keep
        monkeypatch.setattr(api, "read_volume", _bug)
        run = lambda: bpy.ops.volumeevm.import_volume(filepath=skull)  # noqa: E731
        label = "Import ct_skull_cgal"
    elif operator == "build":
        _imported(api, skull)
        monkeypatch.setattr(api.VolumeEVM, "from_volume", _bug)
        run = lambda: bpy.ops.volumeevm.build_vevm(  # noqa: E731
            use_settings=False, threshold=SKULL_THRESHOLD)
        label = "Build VolumeEVM of ct_skull_cgal"
    else:
        _meshed(api, skull)
        monkeypatch.setattr(api.VolumeEVM, "mesh", _bug)
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
def test_commit_failing_half_way_is_undone(api, jobs, skull, monkeypatch, capsys, where):
    """The commit (or ``finished`` after it) raises after writing into Blender: all undone."""
    if where == "import":  # after the new object was linked and selected
        _imported(api, skull)
        monkeypatch.setattr(api._runtime, "forget_except", _bug)
        run = lambda: bpy.ops.volumeevm.import_volume(filepath=skull)  # noqa: E731
    elif where == "build":  # a rebuild, after the settings and sidecar were written
        obj = _meshed(api, skull)
        assert obj.volumeevm.vevm_path
        monkeypatch.setattr(api._runtime, "put_volume", _bug)
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


def test_script_api_raises_and_leaves_the_scene_unchanged(api, jobs, skull, monkeypatch):
    _imported(api, skull)
    before = scene_state(api)
    monkeypatch.setattr(api._runtime, "forget_except", _bug)
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
        make_job = lambda: api.build_job(obj, SKULL_THRESHOLD)  # noqa: E731
        if where == "step":
            monkeypatch.setattr(api.VolumeEVM, "from_volume", _bug)
        else:
            monkeypatch.setattr(api._runtime, "put_volume", _bug)
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
    op = _driver(ext, lambda: api.build_job(obj, SKULL_THRESHOLD))
    context = _Context()
    assert op.start(context) == {"RUNNING_MODAL"}
    assert _ticks(op, context) == {"FINISHED"}
    assert jobs.CURRENT is None and context.window_manager.timers == []
    assert obj.volumeevm.voxel_count == api.get_vevm(obj).voxel_count > 0


# ---------------------------------------------------------------------------- tool stack
@pytest.mark.parametrize("where", ["voxelize", "write"])
def test_tool_error_leaves_no_busy_flag_and_no_entry(api, skull, monkeypatch, capsys, where):
    obj = _meshed(api, skull)
    corners = np.empty(24, np.float32)
    obj.data.vertices.foreach_get("co", corners)
    corners = corners.reshape(8, 3)
    lo, hi = corners.min(axis=0), corners.max(axis=0)
    box = box_object("cutter", lo + 0.25 * (hi - lo), hi - 0.25 * (hi - lo))
    obj.volumeevm.tool_object = box
    bpy.context.view_layer.objects.active = obj
    # "write": the entry is stored, then making the surface's new mesh fails.
    monkeypatch.setattr(api, "voxelize_tool" if where == "voxelize" else "_write_surface", _bug)
    before = scene_state(api)
    with pytest.raises(RuntimeError, match=f"Cut: {UNEXPECTED}"):
        bpy.ops.volumeevm.tool_cut()
    assert not api.is_busy()
    assert "ZeroDivisionError: a bug" in capsys.readouterr().err
    assert scene_state(api) == before and len(obj.volumeevm.tools) == 0
    monkeypatch.undo()
    assert bpy.ops.volumeevm.tool_cut() == {"FINISHED"}
    assert len(obj.volumeevm.tools) == 1 and not api.is_busy()


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
