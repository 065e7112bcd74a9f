"""Helpers for the Blender tests: load the extension from the source tree, reset Blender.

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
