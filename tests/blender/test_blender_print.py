"""3D printing: Make Mesh's manifold option, exported with Blender's own STL exporter and read
back with its importer, is closed and manifold (bmesh's own checks); the plain mesh is not.

Runs under both pinned bpy versions (4.5 on Python 3.11, 5.2 on Python 3.13).
"""

import bmesh  # bpy's own module, importable once bpy is
import bpy
import numpy as np

from blender_helpers import CT_BONE_HU, assert_surface_is


def round_trip(surface, path):
    """Export ``surface`` alone with Blender's own exporter of ``path``'s format (STL, OBJ or
    PLY; in mm: 1 mm = 0.001 Blender units) and import it again; returns the imported object."""
    bpy.ops.object.select_all(action="DESELECT")
    surface.select_set(True)
    fmt = path.suffix[1:]
    export, load = getattr(bpy.ops.wm, f"{fmt}_export"), getattr(bpy.ops.wm, f"{fmt}_import")
    written = export(filepath=str(path), export_selected_objects=True, global_scale=1000.0)
    assert written == {"FINISHED"}
    assert load(filepath=str(path)) == {"FINISHED"}
    return bpy.context.selected_objects[0]


def manifold_counts(obj):
    """(non-manifold edges, boundary edges, vertices merged at distance 0) of a mesh object."""
    mesh = bmesh.new()
    mesh.from_mesh(obj.data)
    try:
        non_manifold = sum(not edge.is_manifold for edge in mesh.edges)
        boundary = sum(edge.is_boundary for edge in mesh.edges)
        before = len(mesh.verts)
        bmesh.ops.remove_doubles(mesh, verts=mesh.verts, dist=0.0)
        return non_manifold, boundary, before - len(mesh.verts)
    finally:
        mesh.free()


def test_manifold_mesh_exports_to_a_closed_manifold_stl(tmp_path, ct_crop_npy, core):
    assert bpy.ops.volumeevm.import_volume(filepath=str(ct_crop_npy)) == {"FINISHED"}
    volume = bpy.context.active_object
    assert bpy.ops.volumeevm.build_vevm(use_settings=False, threshold=CT_BONE_HU) == {"FINISHED"}
    vevm = core.VolumeEVM.load(bpy.path.abspath(volume.volumeevm.vevm_path))

    # The plain mesh has edges where bone voxels touch along an edge only: not manifold.
    assert bpy.ops.volumeevm.make_mesh() == {"FINISHED"}
    plain = round_trip(bpy.context.active_object, tmp_path / "plain.stl")
    assert manifold_counts(plain)[0] > 0

    bpy.context.view_layer.objects.active = volume
    assert bpy.ops.volumeevm.make_mesh(manifold=True) == {"FINISHED"}
    surface = volume.volumeevm.surface
    assert_surface_is(surface, vevm, manifold=True)
    vertices = vevm.mesh(manifold=True)[0]
    assert manifold_counts(surface) == (0, 0, 0)

    printed = round_trip(surface, tmp_path / "bone.stl")
    # Blender's importer merges coincident points: none of the split copies merged.
    assert len(printed.data.vertices) == len(vertices)
    assert manifold_counts(printed) == (0, 0, 0)
    imported = np.empty(3 * len(printed.data.vertices), np.float32)
    printed.data.vertices.foreach_get("co", imported)
    expected = (vertices * 0.001).astype(np.float32) * np.float32(1000.0)
    np.testing.assert_allclose(np.unique(imported.reshape(-1, 3), axis=0),
                               np.unique(expected, axis=0), rtol=0, atol=1e-4)
    for fmt in ("obj", "ply"):  # n-gons kept as they are
        printed = round_trip(surface, tmp_path / f"bone.{fmt}")
        assert len(printed.data.vertices) == len(vertices)
        assert manifold_counts(printed) == (0, 0, 0), fmt


def test_make_manifold_mesh_api(api, core, data_dir, tmp_path):
    """The script API's ``make_mesh(obj, manifold=True)`` on two voxels touching at an edge."""
    mask = np.zeros((4, 4, 3), np.uint8)
    mask[1, 1, 1] = mask[2, 2, 1] = 1
    path = tmp_path / "edge.npy"
    np.save(path, mask)
    obj = api.import_volume(path)
    api.build(obj, 1)
    surface = api.make_mesh(obj, manifold=True)
    assert len(surface.data.vertices) == 16 and len(surface.data.polygons) == 12
    assert manifold_counts(surface) == (0, 0, 0)
    assert manifold_counts(api.make_mesh(obj))[0] == 1  # the plain mesh: the shared edge
