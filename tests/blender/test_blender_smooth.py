"""Make Mesh's smooth option: the operator and ``api.make_mesh(obj, smooth=True)`` put the
core's smooth mesh into the surface object, shaded smooth, while the plain mesh stays flat.

Runs under both pinned bpy versions (4.5 on Python 3.11, 5.2 on Python 3.13).
"""

import bpy
import numpy as np

from blender_helpers import CT_BONE_HU, assert_surface_is, mesh_arrays


def shaded_smooth(mesh):
    flags = np.empty(len(mesh.polygons), bool)
    mesh.polygons.foreach_get("use_smooth", flags)
    return flags


def test_smooth_mesh_operator_and_api(ct_crop_npy, core, api):
    assert bpy.ops.volumeevm.import_volume(filepath=str(ct_crop_npy)) == {"FINISHED"}
    volume = bpy.context.active_object
    assert bpy.ops.volumeevm.build_vevm(use_settings=False, threshold=CT_BONE_HU) == {"FINISHED"}
    vevm = core.VolumeEVM.load(bpy.path.abspath(volume.volumeevm.vevm_path))

    assert bpy.ops.volumeevm.make_mesh() == {"FINISHED"}
    assert not shaded_smooth(volume.volumeevm.surface.data).any()

    bpy.context.view_layer.objects.active = volume
    assert bpy.ops.volumeevm.make_mesh(smooth=True) == {"FINISHED"}
    surface = volume.volumeevm.surface
    assert_surface_is(surface, vevm, smooth=True)
    co = mesh_arrays(surface.data)[0]
    assert shaded_smooth(surface.data).all()
    exact, _ = vevm.mesh()
    offset = np.abs(co[:len(exact)].astype(np.float64) * 1000.0 - exact)
    assert (offset <= np.array(vevm.spacing) / 2 + 1e-3).all()
    assert offset.max() > 0.1  # it moved

    again = api.make_mesh(volume, smooth=True)
    assert again == volume.volumeevm.surface
    np.testing.assert_array_equal(mesh_arrays(again.data)[0], co)
    assert shaded_smooth(again.data).all()
