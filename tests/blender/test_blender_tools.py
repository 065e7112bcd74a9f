"""CAD tools on a VolumeEVM in the real bpy: tool objects cut, keep and add material on a crop of
the real CT head as a non-destructive stack, live when tools move (depsgraph handler), with
Apply, undo and saved files; against the core called directly on the same triangles.

Runs under both pinned bpy versions (4.5 on Python 3.11, 5.2 on Python 3.13).
"""

import math
from pathlib import Path

import bpy
import numpy as np
import pytest
from mathutils import Matrix

from blender_helpers import CT_BONE_HU, assert_surface_is, mesh_arrays

BACKGROUND = -5000  # below every CT value: marks voxels outside the region in to_dense


@pytest.fixture
def crop_array(ct_crop_npy):
    return np.load(ct_crop_npy)


@pytest.fixture
def volume(api, ct_crop_npy):
    """The crop imported, built at the bone threshold and meshed: (volume object, base)."""
    obj = api.import_volume(ct_crop_npy)
    base = api.build(obj, CT_BONE_HU)
    api.make_mesh(obj)
    bpy.context.view_layer.objects.active = obj
    return obj, base


# ---------------------------------------------------------------------------- helpers
def mesh_object(name, vertices, faces):
    """A mesh object from triangles (vertices in the object's local Blender units)."""
    mesh = bpy.data.meshes.new(name)
    mesh.vertices.add(len(vertices))
    mesh.vertices.foreach_set("co", np.asarray(vertices, np.float32).ravel())
    faces = np.asarray(faces, np.int32)
    mesh.loops.add(faces.size)
    mesh.loops.foreach_set("vertex_index", faces.ravel())
    mesh.polygons.add(len(faces))
    mesh.polygons.foreach_set("loop_start", np.arange(0, faces.size, 3, dtype=np.int32))
    mesh.update(calc_edges=True)
    obj = bpy.data.objects.new(name, mesh)
    bpy.context.scene.collection.objects.link(obj)
    return obj


def tool_object(data_dir, name, size_mm, *, at, degrees=0.0):
    """A real tool mesh from ../shared/data, ``size_mm`` across, centred at world ``at`` (BU)."""
    data = np.load(data_dir / f"{name}.npz")
    vertices = data["vertices"]
    lo, hi = vertices.min(axis=0), vertices.max(axis=0)
    local = (vertices - (lo + hi) / 2) * (size_mm / float((hi - lo).max())) * 0.001
    obj = mesh_object(name, local, data["faces"])
    obj.location = at
    obj.rotation_euler = (0.0, 0.0, math.radians(degrees))
    bpy.context.view_layer.update()
    return obj


def box_object(name, lo_bu, hi_bu):
    """An axis-aligned box mesh object (a clip box): its mesh is its own bounding box."""
    lo, hi = np.asarray(lo_bu, float), np.asarray(hi_bu, float)
    corners = np.array([[i, j, k] for i in (0, 1) for j in (0, 1) for k in (0, 1)], float)
    faces = [[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
             [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]]
    obj = mesh_object(name, corners * (hi - lo), faces)
    obj.location = lo
    bpy.context.view_layer.update()
    return obj


def world_of_voxel(core, vevm, index, vol_obj):
    """World position (BU) of voxel centre ``index`` of the volume."""
    from_grid = core.model._volume.grid_to_world(vevm.spacing, vevm.origin, vevm.orientation,
                                           np.array(vol_obj.matrix_world))
    return tuple((from_grid @ np.append(np.asarray(index, float), 1.0))[:3])


def expected_tool(core, vevm, vol_obj, tool_obj):
    """The tool's EVM from the core alone: the object's own triangles (as Blender stores them),
    the documented placement, the whole grid."""
    mesh = tool_obj.data
    co = np.empty(len(mesh.vertices) * 3, np.float32)
    mesh.vertices.foreach_get("co", co)
    faces = np.empty(len(mesh.polygons) * 3, np.int32)
    mesh.polygons.foreach_get("vertices", faces)  # the test tools are triangle meshes
    world = core.model._volume.grid_to_world(vevm.spacing, vevm.origin, vevm.orientation,
                                       np.array(vol_obj.matrix_world))
    to_grid = np.linalg.inv(world) @ np.array(tool_obj.matrix_world)
    to_grid[3] = (0, 0, 0, 1)
    mask = core.voxelize_mesh(co.reshape(-1, 3).astype(np.float64), faces.reshape(-1, 3),
                              vevm.shape, to_grid)
    return core.EVM.from_mask(mask), mask


def assert_same_vevm(a, b):
    assert a.evm == b.evm
    np.testing.assert_array_equal(a.table(0), b.table(0))


def bone_voxel_near(base, target):
    """A bone voxel of the region near ``target`` (voxel index)."""
    voxels = base.evm.voxels().astype(np.int64)
    return voxels[np.argmin(((voxels - np.asarray(target)) ** 2).sum(axis=1))]


def surface_of(vol_obj):
    return vol_obj.volumeevm.surface


# ---------------------------------------------------------------------------- cut, move
def test_tool_cut_equals_core_and_follows_moves(ext, api, core, data_dir, volume, crop_array):
    vol, base = volume
    centre = bone_voxel_near(base, (10, 14, 25))
    nut = tool_object(data_dir, "mesh_tool_nut", 30.0, at=world_of_voxel(core, base, centre, vol),
                      degrees=20.0)
    vol.volumeevm.tool_object = nut
    surface = surface_of(vol)
    mesh_before = surface.data
    assert bpy.ops.volumeevm.tool_cut() == {"FINISHED"}

    entries = vol.volumeevm.tools
    assert len(entries) == 1 and entries[0].tool == nut and entries[0].operation == "CUT"
    tool, mask = expected_tool(core, base, vol, nut)
    expected = base.cut(tool)
    assert 0 < expected.voxel_count < base.voxel_count  # the nut really cuts bone
    assert surface.data == mesh_before  # refreshed in place
    assert_surface_is(surface, expected)
    result = api.stack_state(vol).result
    assert_same_vevm(result, expected)
    # Densities voxel by voxel: the region's HU where bone and not tool, nothing elsewhere.
    region = (crop_array >= CT_BONE_HU) & ~mask
    np.testing.assert_array_equal(result.to_dense(BACKGROUND),
                                  np.where(region, crop_array, BACKGROUND))

    # Moving the tool: the depsgraph handler refreshes the surface for the new placement.
    nut.location.x += 0.006
    bpy.context.view_layer.update()
    moved = base.cut(expected_tool(core, base, vol, nut)[0])
    assert moved.evm != expected.evm
    assert_surface_is(surface, moved)
    timing = api.stack_state(vol).timing
    assert timing["voxelized"] == 1 and timing["recomputed"] == 1 and timing["total_s"] > 0
    # Our own mesh write does not trigger another refresh; nothing changed, nothing written.
    bpy.context.view_layer.update()
    bpy.context.view_layer.update()
    assert api.stack_state(vol).timing is timing

    # Rotating and scaling the tool, then re-evaluating through the API.
    nut.matrix_world = nut.matrix_world @ Matrix.Diagonal((1.2, 0.8, 1.0, 1.0)) @ Matrix.Rotation(
        math.radians(30.0), 4, "X")
    again = api.evaluate(vol)
    turned = base.cut(expected_tool(core, base, vol, nut)[0])
    assert_same_vevm(again, turned)
    assert_surface_is(surface, turned)

    # Moving the volume object moves its surface; the tools stay, so they cut elsewhere.
    vol.location = (0.002, -0.003, 0.001)
    bpy.context.view_layer.update()
    shifted = base.cut(expected_tool(core, base, vol, nut)[0])
    assert shifted.evm != turned.evm
    assert_surface_is(surface, shifted)

    # Editing the tool's mesh (geometry update) refreshes too.
    co = np.empty(len(nut.data.vertices) * 3, np.float32)
    nut.data.vertices.foreach_get("co", co)
    nut.data.vertices.foreach_set("co", co * 0.7)
    nut.data.update()
    bpy.context.view_layer.update()
    assert_surface_is(surface, base.cut(expected_tool(core, base, vol, nut)[0]))


def test_a_move_that_changes_no_voxel_writes_no_mesh(ext, api, core, data_dir, volume,
                                                     monkeypatch):
    vol, base = volume
    centre = bone_voxel_near(base, (10, 14, 25))
    nut = tool_object(data_dir, "mesh_tool_nut", 30.0, at=world_of_voxel(core, base, centre, vol))
    vol.volumeevm.tool_object = nut
    assert bpy.ops.volumeevm.tool_cut() == {"FINISHED"}
    surface = surface_of(vol)
    expected = base.cut(expected_tool(core, base, vol, nut)[0])
    writes = []
    write = ext.blender.tool_stack.refill_mesh
    monkeypatch.setattr(ext.blender.tool_stack, "refill_mesh",
                        lambda *args: (writes.append(args[0]), write(*args)))

    nut.location.x += 1e-6  # a micrometre (voxels are about a millimetre): the same voxels
    bpy.context.view_layer.update()
    assert base.cut(expected_tool(core, base, vol, nut)[0]).evm == expected.evm
    state = api.stack_state(vol)
    assert state.timing["voxelized"] == 1  # the moved tool was read and voxelized again
    assert writes == []
    assert surface.volumeevm.stack_signature == state.shown[0]  # it shows this stack
    assert_surface_is(surface, expected)

    nut.location.x += 0.006  # now voxels change, and the mesh is written
    bpy.context.view_layer.update()
    assert writes == [surface.data]
    assert_surface_is(surface, base.cut(expected_tool(core, base, vol, nut)[0]))


# ---------------------------------------------------------------------------- stack
def test_stack_equals_one_by_one_disable_restores(api, core, data_dir, volume):
    vol, base = volume
    s = vol.volumeevm
    lo = world_of_voxel(core, base, (3.3, 2.6, 2.2), vol)
    hi = world_of_voxel(core, base, (124.5, 125.25, 47.7), vol)
    clip = box_object("ClipBox", lo, hi)
    fan = tool_object(data_dir, "mesh_tool_fandisk", 40.0, degrees=35.0,
                      at=world_of_voxel(core, base, bone_voxel_near(base, (110, 104, 25)), vol))
    nut = tool_object(data_dir, "mesh_tool_nut", 25.0,
                      at=world_of_voxel(core, base, (64, 64, 20), vol))
    for tool, operator in ((clip, bpy.ops.volumeevm.tool_clip),
                           (fan, bpy.ops.volumeevm.tool_cut),
                           (nut, bpy.ops.volumeevm.tool_add)):
        s.tool_object = tool
        kwargs = dict(use_density=True, density=1500.0) if tool == nut else {}
        assert operator(**kwargs) == {"FINISHED"}
    assert [e.operation for e in s.tools] == ["CLIP", "CUT", "ADD"]
    assert s.tools[2].use_density and s.tools[2].density == 1500.0

    box = expected_tool(core, base, vol, clip)[0]  # the clip box's own mesh is its bound box
    drill = expected_tool(core, base, vol, fan)[0]
    implant = expected_tool(core, base, vol, nut)[0]
    full = base.keep(box).cut(drill).add(implant, 1500.0)
    assert_same_vevm(api.stack_state(vol).result, full)
    assert_surface_is(surface_of(vol), full)

    # Disabling the middle entry: exactly the stack without it; enabling it again restores.
    s.tools[1].enabled = False  # the entry's update callback refreshes at once
    without = base.keep(box).add(implant, 1500.0)
    assert_same_vevm(api.stack_state(vol).result, without)
    assert_surface_is(surface_of(vol), without)
    assert api.stack_state(vol).timing["recomputed"] == 2
    s.tools[1].enabled = True
    assert_same_vevm(api.evaluate(vol), full)
    assert_surface_is(surface_of(vol), full)

    # Order matters: the add moved first, then the cut removes part of the implant.
    s.tool_index = 2
    assert bpy.ops.volumeevm.tool_move_up() == {"FINISHED"}
    assert [e.operation for e in s.tools] == ["CLIP", "ADD", "CUT"] and s.tool_index == 1
    assert_same_vevm(api.stack_state(vol).result,
                     base.keep(box).add(implant, 1500.0).cut(drill))

    # Keep the largest part on top; the default add density is the region's largest.
    assert bpy.ops.volumeevm.tool_largest() == {"FINISHED"}
    assert bpy.ops.volumeevm.tool_remove(index=1) == {"FINISHED"}
    s.tool_object = nut
    assert bpy.ops.volumeevm.tool_add() == {"FINISHED"}
    assert [e.operation for e in s.tools] == ["CLIP", "CUT", "LARGEST", "ADD"]
    expected = base.keep(box).cut(drill).largest_component()
    expected = expected.add(implant)
    assert_same_vevm(api.stack_state(vol).result, expected)
    assert_surface_is(surface_of(vol), expected)
    # The sidebar's density settings reach the Add button; editing an entry re-evaluates.
    s.tool_use_density, s.tool_density = True, 2000.0
    assert bpy.ops.volumeevm.tool_add() == {"FINISHED"}
    assert s.tools[4].use_density and s.tools[4].density == 2000.0
    s.tools[4].density = 900.0
    assert_same_vevm(api.stack_state(vol).result, expected.add(implant, 900.0))
    assert bpy.ops.volumeevm.tool_remove() == {"FINISHED"}  # the active (last) entry
    assert len(s.tools) == 4
    assert_surface_is(surface_of(vol), expected)

    # The box fast path (axis-aligned clip) equals voxelizing the box mesh; a rotated box too.
    clip.rotation_euler = (0.0, 0.0, math.radians(10.0))
    bpy.context.view_layer.update()
    turned = expected_tool(core, base, vol, clip)[0]  # its mesh is its local bound box
    expected = base.keep(turned).cut(drill).largest_component().add(implant)
    assert_same_vevm(api.stack_state(vol).result, expected)


def test_api_add_tool_same_as_operator(api, core, data_dir, volume):
    vol, base = volume
    at = world_of_voxel(core, base, bone_voxel_near(base, (110, 112, 25)), vol)
    fan = tool_object(data_dir, "mesh_tool_fandisk", 35.0, at=at, degrees=-15.0)
    result = api.add_tool(vol, fan, "keep")
    expected = base.keep(expected_tool(core, base, vol, fan)[0])
    assert_same_vevm(result, expected)
    assert_surface_is(surface_of(vol), expected)
    with pytest.raises(core.VolumeEVMError, match="operation must be one of"):
        api.add_tool(vol, fan, "drill")
    with pytest.raises(core.VolumeEVMError, match="density is for 'add' only"):
        api.add_tool(vol, fan, "cut", density=10.0)
    with pytest.raises(core.VolumeEVMError, match="does not fit the data type int16"):
        api.add_tool(vol, fan, "add", density=1e6)
    assert len(vol.volumeevm.tools) == 1


# ---------------------------------------------------------------------------- errors
def test_poll_messages(api, core, data_dir, ct_crop_npy):
    with pytest.raises(RuntimeError, match="Select a volume object"):
        bpy.ops.volumeevm.tool_cut()
    vol = api.import_volume(ct_crop_npy)
    with pytest.raises(RuntimeError, match="No VolumeEVM built yet"):
        bpy.ops.volumeevm.tool_keep()
    api.build(vol, CT_BONE_HU)
    surface = api.make_mesh(vol)
    bpy.context.view_layer.objects.active = vol
    with pytest.raises(RuntimeError, match="Choose a tool object"):
        bpy.ops.volumeevm.tool_cut()
    with pytest.raises(RuntimeError, match="The tool stack is empty"):
        bpy.ops.volumeevm.tool_apply()
    camera = bpy.data.objects.new("Camera", bpy.data.cameras.new("Camera"))
    vol.volumeevm.tool_object = camera
    with pytest.raises(RuntimeError, match="Camera is not a mesh"):
        bpy.ops.volumeevm.tool_add()
    vol.volumeevm.tool_object = surface
    with pytest.raises(RuntimeError, match="is the volume's own surface"):
        bpy.ops.volumeevm.tool_clip()
    assert bpy.ops.volumeevm.tool_largest() == {"FINISHED"}  # needs no tool


def test_open_or_outside_tool_clear_error_nothing_changed(api, core, data_dir, volume):
    vol, base = volume
    surface = surface_of(vol)
    before = mesh_arrays(surface.data)
    shark = tool_object(data_dir, "mesh_open_mech_holes_shark", 40.0,
                        at=world_of_voxel(core, base, (64, 64, 25), vol))
    vol.volumeevm.tool_object = shark
    with pytest.raises(RuntimeError, match=r"Cut with mesh_open_mech_holes_shark: tool mesh is "
                                           r"not closed: 304 open \(boundary\) edges"):
        bpy.ops.volumeevm.tool_cut()
    far = tool_object(data_dir, "mesh_tool_nut", 20.0, at=(1.0, 1.0, 1.0))
    vol.volumeevm.tool_object = far
    with pytest.raises(RuntimeError, match="tool mesh lies wholly outside the volume"):
        bpy.ops.volumeevm.tool_keep()
    assert len(vol.volumeevm.tools) == 0
    for a, b in zip(before, mesh_arrays(surface.data)):
        np.testing.assert_array_equal(a, b)


def test_live_error_keeps_last_mesh_and_shows_in_sidebar(ext, api, core, data_dir, volume):
    from test_blender_ui import draw_all, texts

    vol, base = volume
    nut = tool_object(data_dir, "mesh_tool_nut", 30.0,
                      at=world_of_voxel(core, base, bone_voxel_near(base, (10, 14, 25)), vol))
    result = api.add_tool(vol, nut, "cut")
    good = mesh_arrays(surface_of(vol).data)
    shown = texts(draw_all(ext, bpy.context))
    assert any(t.startswith("Last refresh: ") for t in shown)
    assert f"Result: {result.voxel_count:,} voxels" in shown

    nut.location = (2.0, 0.0, 0.0)  # wholly outside: the handler must not raise
    bpy.context.view_layer.update()
    problem = api.stack_state(vol).problem
    assert problem.startswith("Cut with mesh_tool_nut: tool mesh lies wholly outside the volume")
    for a, b in zip(good, mesh_arrays(surface_of(vol).data)):
        np.testing.assert_array_equal(a, b)
    shown = texts(draw_all(ext, bpy.context))
    assert "Tool stack problem:" in shown
    with pytest.raises(RuntimeError, match="wholly outside"):
        bpy.ops.volumeevm.tool_apply()

    nut.location = world_of_voxel(core, base, (64, 64, 25), vol)  # back inside: fixed
    bpy.context.view_layer.update()
    assert api.stack_state(vol).problem == ""
    assert_surface_is(surface_of(vol), base.cut(expected_tool(core, base, vol, nut)[0]))
    bpy.data.objects.remove(nut)  # a deleted tool: the entry says so
    with pytest.raises(core.VolumeEVMError, match="entry 1 \\(Cut\\): it has no tool object"):
        api.evaluate(vol)


def test_handler_never_raises(ext, api, core, data_dir, volume, monkeypatch):
    vol, base = volume
    nut = tool_object(data_dir, "mesh_tool_nut", 30.0,
                      at=world_of_voxel(core, base, bone_voxel_near(base, (10, 14, 25)), vol))
    api.add_tool(vol, nut, "cut")
    good = mesh_arrays(surface_of(vol).data)

    def broken(*_args):
        raise ZeroDivisionError("a bug")

    monkeypatch.setattr(ext.blender.tool_stack, "refresh_quietly", broken)
    nut.location.x += 0.004
    bpy.context.view_layer.update()  # the handler catches it
    assert api.stack_state(vol).problem == ("unexpected error while refreshing: "
                                            "ZeroDivisionError('a bug')")
    for a, b in zip(good, mesh_arrays(surface_of(vol).data)):
        np.testing.assert_array_equal(a, b)


# ---------------------------------------------------------------------------- undo
def _push(name):
    assert bpy.ops.ed.undo_push(message=name) == {"FINISHED"}


def test_undo_restores_mesh_and_stack(api, core, data_dir, volume):
    vol, base = volume
    name = vol.name
    nut = tool_object(data_dir, "mesh_tool_nut", 30.0,
                      at=world_of_voxel(core, base, bone_voxel_near(base, (10, 14, 25)), vol))
    _push("tool made")
    api.add_tool(vol, nut, "cut")
    _push("cut")
    first = base.cut(expected_tool(core, base, vol, nut)[0])
    nut.location.z += 0.005
    bpy.context.view_layer.update()
    _push("moved")
    second = base.cut(expected_tool(core, base, vol, nut)[0])
    assert second.evm != first.evm
    assert_surface_is(surface_of(vol), second)

    assert bpy.ops.ed.undo() == {"FINISHED"}  # back to before the move (real undo)
    vol, nut = bpy.data.objects[name], bpy.data.objects["mesh_tool_nut"]
    assert_surface_is(surface_of(vol), first)  # Blender restored the mesh
    assert_same_vevm(api.evaluate(vol), first)  # the runtime stack follows the properties

    assert bpy.ops.ed.undo() == {"FINISHED"}  # back to before the cut
    vol = bpy.data.objects[name]
    assert len(vol.volumeevm.tools) == 0
    assert_surface_is(surface_of(vol), base)
    assert bpy.ops.ed.redo() == {"FINISHED"}
    assert bpy.ops.ed.redo() == {"FINISHED"}
    vol = bpy.data.objects[name]
    assert len(vol.volumeevm.tools) == 1
    assert_surface_is(surface_of(vol), second)
    assert_same_vevm(api.evaluate(vol), second)


def test_apply_new_sidecar_undo_and_reopen(tmp_path, ext, api, core, data_dir, volume):
    vol, base = volume
    name = vol.name
    old_path = vol.volumeevm.vevm_path
    nut = tool_object(data_dir, "mesh_tool_nut", 30.0,
                      at=world_of_voxel(core, base, bone_voxel_near(base, (10, 14, 25)), vol))
    api.add_tool(vol, nut, "cut")
    api.add_tool(vol, None, "largest")
    _push("stacked")
    expected = base.cut(expected_tool(core, base, vol, nut)[0]).largest_component()
    assert bpy.ops.volumeevm.tool_apply() == {"FINISHED"}
    _push("applied")
    s = vol.volumeevm
    assert len(s.tools) == 0 and s.vevm_path != old_path
    assert Path(s.vevm_path).is_file() and Path(old_path).is_file()  # a new file, old kept
    assert_same_vevm(core.VolumeEVM.load(s.vevm_path), expected)
    assert s.voxel_count == expected.voxel_count and s.ev_count == len(expected.evm)
    assert_same_vevm(api.get_vevm(vol), expected)
    assert_surface_is(surface_of(vol), expected)
    nut.location.x += 0.01  # no longer a tool of the stack: nothing happens
    bpy.context.view_layer.update()
    assert_surface_is(surface_of(vol), expected)
    _push("moved")  # as the transform operator does

    assert bpy.ops.ed.undo() == {"FINISHED"}
    assert bpy.ops.ed.undo() == {"FINISHED"}  # before Apply: old base, stack back
    vol = bpy.data.objects[name]
    assert vol.volumeevm.vevm_path == old_path and len(vol.volumeevm.tools) == 2
    # The undo_post handler re-synced the runtime stack to the restored base path, and the
    # mesh Blender restored matches the restored stack (nothing to rewrite).
    state = ext.blender.runtime.stack_state(vol.volumeevm.uid, name)
    assert state.base_path == str(Path(old_path)) and state.problem == ""
    assert surface_of(vol).volumeevm.stack_signature != ""
    assert_surface_is(surface_of(vol), expected)
    assert_same_vevm(api.get_vevm(vol), base)
    nut = bpy.data.objects["mesh_tool_nut"]
    assert_same_vevm(api.evaluate(vol), expected)
    assert bpy.ops.ed.redo() == {"FINISHED"}
    vol = bpy.data.objects[name]
    assert len(vol.volumeevm.tools) == 0

    blend = tmp_path / "tools.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(blend))
    bpy.ops.wm.open_mainfile(filepath=str(blend))
    vol = bpy.data.objects[name]
    assert vol.volumeevm.vevm_path == f"//tools_volumeevm/{name}.vevm"
    assert_same_vevm(api.get_vevm(vol), expected)
    assert_surface_is(surface_of(vol), expected)


def test_saved_stack_reopens_live(tmp_path, api, core, data_dir, volume):
    vol, base = volume
    name = vol.name
    nut = tool_object(data_dir, "mesh_tool_nut", 30.0,
                      at=world_of_voxel(core, base, bone_voxel_near(base, (10, 14, 25)), vol))
    api.add_tool(vol, nut, "cut")
    blend = tmp_path / "stack.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(blend))
    bpy.ops.wm.open_mainfile(filepath=str(blend))
    vol, nut = bpy.data.objects[name], bpy.data.objects["mesh_tool_nut"]
    assert vol.volumeevm.tools[0].tool == nut
    assert_surface_is(surface_of(vol), base.cut(expected_tool(core, base, vol, nut)[0]))
    nut.location.y += 0.004
    bpy.context.view_layer.update()
    assert_surface_is(surface_of(vol), base.cut(expected_tool(core, base, vol, nut)[0]))
