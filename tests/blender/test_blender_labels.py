"""Label maps in the real bpy: a Slicer segmentation becomes named, coloured mesh objects (one
per segment, each exactly the core's label mesh, LabelSet.meshes: touching segments share their
polygons), or one mesh with a material per label; a volume that is not a label map is refused
with the scene left as it was.

Runs under both pinned bpy versions (4.5 on Python 3.11, 5.2 on Python 3.13).
"""

import bpy
import numpy as np
import pytest

from blender_helpers import assert_mesh_is, mesh_arrays


@pytest.fixture
def segmentation(data_dir):
    return data_dir / "slicer" / "Segmentation.seg.nrrd"


def test_a_segmentation_becomes_one_named_coloured_object_per_segment(api, core, segmentation):
    vol = api.import_volume(segmentation)
    made = api.make_label_meshes(vol)
    volume = core.read_volume(segmentation)
    regions = core.VolumeEVM.from_labels(volume)
    assert [o.name for o in made] == [volume.labels[label].name for label in regions]
    collection = bpy.data.collections["Segmentation.seg labels"]
    parent = bpy.data.objects["Segmentation.seg labels"]
    assert parent.parent == vol and parent.name in collection.objects
    meshes = regions.meshes()
    for obj, label in zip(made, regions):
        assert obj.parent == parent and obj.name in collection.objects
        assert obj["volumeevm_label"] == label
        assert_mesh_is(obj, *meshes[label])  # exactly the core's label mesh
        color = volume.labels[label].color
        assert tuple(obj.color)[:3] == pytest.approx(color, abs=1e-6)
        material = obj.data.materials[0]
        assert tuple(material.diffuse_color)[:3] == pytest.approx(color, abs=1e-6)
        base = material.node_tree.nodes["Principled BSDF"].inputs["Base Color"].default_value
        assert tuple(base)[:3] == pytest.approx(color, abs=1e-6)
    # Made again: the new objects replace the old ones, nothing is left behind.
    again = api.make_label_meshes(vol)
    assert len(again) == len(regions)
    assert len(bpy.data.collections) == 1
    assert sum(1 for o in bpy.data.objects if "volumeevm_label" in o) == len(regions)
    assert len(bpy.data.materials) == len(bpy.data.meshes) - 1 == len(regions)  # and the box


def test_one_mesh_with_a_material_and_a_label_per_face(api, core, segmentation):
    vol = api.import_volume(segmentation)
    (obj,) = api.make_label_meshes(vol, single_mesh=True)
    regions = core.VolumeEVM.from_labels(core.read_volume(segmentation))
    meshes = list(regions.meshes().values())
    counts = [len(polygons) for _, polygons in meshes]
    mesh = obj.data
    labels = np.empty(len(mesh.polygons), np.int32)
    mesh.attributes["label"].data.foreach_get("value", labels)
    assert labels.tolist() == np.repeat(list(regions), counts).tolist()
    slots = np.empty(len(mesh.polygons), np.int32)
    mesh.polygons.foreach_get("material_index", slots)
    names = [mesh.materials[s].name for s in slots[np.cumsum(counts) - 1]]
    assert names == [f"Segmentation.seg {regions.infos[label].name}" for label in regions]
    co, indices, _, _ = mesh_arrays(mesh)
    first_vertices = len(meshes[0][0])
    np.testing.assert_array_equal(co[:first_vertices], (meshes[0][0] * 0.001).astype(np.float32))


def test_a_volume_that_is_not_a_label_map_is_refused_and_nothing_changes(api, core, data_dir):
    vol = api.import_volume(data_dir / "slicer" / "CTChest4.nrrd")
    before = {o.name for o in bpy.data.objects}, len(bpy.data.collections), len(bpy.data.materials)
    with pytest.raises(core.VolumeEVMError, match="CTChest4.nrrd: a label map holds labels >= 0"):
        api.make_label_meshes(vol)
    assert ({o.name for o in bpy.data.objects}, len(bpy.data.collections),
            len(bpy.data.materials)) == before


def test_the_operator_makes_them_from_the_sidebar(api, segmentation):
    vol = api.import_volume(segmentation)
    assert vol.volumeevm.label_count == 7  # the panel offers the label buttons
    assert api.import_volume(segmentation, labels=False).volumeevm.label_count == 0
    bpy.context.view_layer.objects.active = vol
    assert bpy.ops.volumeevm.make_label_meshes.poll()
    assert bpy.ops.volumeevm.make_label_meshes(single_mesh=True) == {"FINISHED"}
    made = bpy.data.objects["Segmentation.seg labels mesh"]
    assert "label" in made.data.attributes and len(made.data.materials) == 7


def _non_manifold_edges(obj):
    import bmesh

    bm = bmesh.new()
    bm.from_mesh(obj.data)
    count = sum(not edge.is_manifold for edge in bm.edges)
    bm.free()
    return count


def test_manifold_label_meshes_for_3d_printing(api, core, segmentation):
    vol = api.import_volume(segmentation)
    assert sum(_non_manifold_edges(obj) for obj in api.make_label_meshes(vol)) > 0  # plain
    made = api.make_label_meshes(vol, manifold=True)
    regions = core.VolumeEVM.from_labels(core.read_volume(segmentation))
    for obj, (vertices, polygons) in zip(made, regions.meshes(manifold=True).values()):
        assert_mesh_is(obj, vertices, polygons)
        assert _non_manifold_edges(obj) == 0, obj.name


def test_a_segmentation_in_layers_becomes_one_object_per_segment(api, core, data_dir):
    path = data_dir / "slicer" / "SegmentationOverlapping.seg.nrrd"
    vol = api.import_volume(path)
    assert vol.volumeevm.label_count == 8
    made = api.make_label_meshes(vol)
    regions = core.VolumeEVM.from_labels(core.read_volume(path))
    assert [o.name for o in made][-2:] == ["tissue", "overlapping sphere"]
    for obj, (vertices, polygons) in zip(made, regions.meshes().values()):
        assert_mesh_is(obj, vertices, polygons)  # every segment its exact solid, overlaps and all
    assert made[-1]["volumeevm_label"] == 8


def test_measurements_listed_sorted_picked_and_exported(ext, api, core, segmentation, tmp_path):
    from test_blender_ui import draw_all, texts

    vol = api.import_volume(segmentation)
    made = {o["volumeevm_label"]: o for o in api.make_label_meshes(vol)}
    bpy.context.view_layer.objects.active = vol
    assert "Not measured yet" in texts(draw_all(ext, bpy.context))
    assert bpy.ops.volumeevm.measure_labels() == {"FINISHED"}
    regions = core.VolumeEVM.from_labels(core.read_volume(segmentation))
    rows = vol.volumeevm.label_measurements
    assert [row.label for row in rows] == list(regions)
    for row, (label, region) in zip(rows, regions.items()):
        exact = region.measure()
        assert row.name == regions.infos[label].name
        assert row.voxels == exact["voxels"] and row.components == exact["components"]
        assert row.volume_ml == pytest.approx(exact["volume_ml"], rel=1e-6)  # float32 property
        assert row.area_mm2 == pytest.approx(exact["area_mm2"], rel=1e-6)
    calls = draw_all(ext, bpy.context)
    assert any(name == "template_list" and args[0] == "VOLUMEEVM_UL_labels"
               for name, args, _ in calls)
    shown = " ".join(texts(calls))
    assert "Exact for the voxel model" in shown and "1.5 on average (a sphere)" in shown
    # Sorting: by volume, largest first; by name; the list's own order is the label order.
    ul = ext.ui.panels.VOLUMEEVM_UL_labels
    listed = type("Listed", (), {"filter_name": "", "bitflag_filter_item": 1 << 30})()
    for sort_by, key in [("VOLUME", lambda r: -r.volume_ml), ("NAME", lambda r: r.name.lower()),
                         ("LABEL", lambda r: r.label)]:
        listed.sort_by = sort_by
        flags, order = ul.filter_items(listed, bpy.context, vol.volumeevm, "label_measurements")
        shown_order = sorted(range(len(rows)), key=lambda i: order[i])
        assert [rows[i].label for i in shown_order] == [r.label for r in sorted(rows, key=key)]
    assert shown_order == list(range(len(rows)))
    # Picking a row selects the label's object; the sidebar still shows the volume.
    vol.volumeevm.label_measurement_index = 4
    assert bpy.context.view_layer.objects.active == made[rows[4].label]
    assert [o.name for o in bpy.context.selected_objects] == [made[rows[4].label].name]
    assert ext.blender.objects.active_volume(bpy.context) == vol
    # CSV: the core's writer; an existing file is never replaced without Overwrite.
    csv = tmp_path / "labels.csv"
    assert bpy.ops.volumeevm.export_label_measurements(filepath=str(csv)) == {"FINISHED"}
    reference = tmp_path / "reference.csv"
    regions.write_measurements(reference)
    assert csv.read_bytes() == reference.read_bytes()
    csv.write_text("mine")
    with pytest.raises(RuntimeError, match="labels.csv: exists; choose another name"):
        bpy.ops.volumeevm.export_label_measurements(filepath=str(csv))
    assert csv.read_text() == "mine"
    done = bpy.ops.volumeevm.export_label_measurements(filepath=str(csv), overwrite=True)
    assert done == {"FINISHED"}
    assert csv.read_bytes() == reference.read_bytes()
    written = api.export_label_measurements(vol, tmp_path / "api.csv")
    assert written.read_bytes() == reference.read_bytes()


def test_tools_cut_keep_and_add_on_every_label_live(ext, api, core, data_dir, segmentation):
    from test_blender_tools import expected_tool, tool_object, world_of_voxel

    vol = api.import_volume(segmentation)
    made = {o["volumeevm_label"]: o for o in api.make_label_meshes(vol)}
    regions = core.VolumeEVM.from_labels(core.read_volume(segmentation))
    grid = regions[1]
    nut = tool_object(data_dir, "mesh_tool_nut", 90.0,
                      at=world_of_voxel(core, grid, (64, 70, 17), vol))

    def assert_objects_show(expected):
        meshes = expected.meshes()  # each label's mesh depends on its neighbours too
        for label, obj in made.items():
            if label in expected:
                assert_mesh_is(obj, *meshes[label])
            else:
                assert len(obj.data.polygons) == len(obj.data.vertices) == 0, obj.name

    # No VolumeEVM built: the label objects are what the stack edits (the operator too).
    bpy.context.view_layer.objects.active = vol
    vol.volumeevm.tool_object = nut
    assert bpy.ops.volumeevm.tool_cut() == {"FINISHED"}
    tool = expected_tool(core, grid, vol, nut)[0]
    cut = regions.cut(tool)
    touched = [label for label in regions
               if cut.get(label) is None or cut[label].evm != regions[label].evm]
    assert len(touched) >= 3  # the nut cuts several structures at once
    assert_objects_show(cut)
    # Live: moving the tool re-cuts every label object.
    nut.location.x += 0.03
    bpy.context.view_layer.update()
    moved = regions.cut(expected_tool(core, grid, vol, nut)[0])
    assert any(moved[label].evm != cut[label].evm for label in moved if label in cut)
    assert_objects_show(moved)
    assert api.remove_tool(vol, 0) == ""
    assert_objects_show(regions)
    # Keep Inside keeps every label inside the tool.
    tool = expected_tool(core, grid, vol, nut)[0]
    result = api.add_tool(vol, nut, "keep")
    assert list(result) == list(regions.keep(tool)) and len(result) >= 3
    assert_objects_show(regions.keep(tool))
    api.remove_tool(vol, 0)
    # Add gives the tool's voxels to one label, taking them from the others.
    with pytest.raises(core.VolumeEVMError, match="needs the label that gets the material"):
        api.add_tool(vol, nut, "add")
    assert len(vol.volumeevm.tools) == 0
    added = regions.add(tool, 5)
    result = api.add_tool(vol, nut, "add", label=5)
    assert result[5].evm == added[5].evm and vol.volumeevm.tools[0].label == 5
    assert_objects_show(added)
    with pytest.raises(core.VolumeEVMError,
                       match=r"label 99 is not one of the label objects' labels "
                             r"\[1, 2, 3, 4, 5, 6"):
        api.add_tool(vol, nut, "add", label=99)
    with pytest.raises(core.VolumeEVMError, match="not for label maps"):
        api.apply_stack(vol)
