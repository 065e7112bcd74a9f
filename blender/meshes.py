"""Meshes in and out of Blender in bulk: a surface's polygons in, a tool's triangles out.

Arrays move with ``foreach_set`` / ``foreach_get`` through the mesh's attributes, with no Python
loop per vertex (the per-item ``MeshLoop.vertex_index`` path is several times slower on large
meshes).
"""

import numpy as np

from ..volumeevm_addon import Polygons
from . import jobs

#: Outward triangles of the box whose corner (i, j, k) in {0, 1}^3 is vertex 4 i + 2 j + k.
BOX_FACES = np.array([[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
                      [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]], np.int32)


def _attribute(mesh, name, kind, domain):
    found = mesh.attributes.get(name)
    return found if found is not None else mesh.attributes.new(name, kind, domain)


def _corner_vertices(mesh):
    """The corners' vertex indices of a mesh and their field name, for ``foreach_get/set``."""
    found = mesh.attributes.get(".corner_vert")
    return (found.data, "value") if found is not None else (mesh.loops, "vertex_index")


def fill_mesh(mesh, co, polys):
    """Fill an empty mesh in bulk: vertices ``co`` (n, 3) and polygons (loops, starts).

    Positions and corner vertices are written through the mesh's attributes (one copy each).
    """
    mesh.vertices.add(len(co))
    _attribute(mesh, "position", "FLOAT_VECTOR", "POINT").data.foreach_set(
        "vector", np.ascontiguousarray(co, np.float32).ravel())
    mesh.loops.add(len(polys.indices))
    corners, field = _corner_vertices(mesh)
    corners.foreach_set(field, np.ascontiguousarray(polys.indices, np.int32))
    mesh.polygons.add(len(polys))
    mesh.polygons.foreach_set("loop_start", np.ascontiguousarray(polys.starts, np.int32))
    # Flat faces: a voxel boundary has no smooth normals (new meshes shade smooth since 4.1).
    _attribute(mesh, "sharp_face", "BOOLEAN", "FACE").data.foreach_set(
        "value", np.ones(len(polys), bool))
    mesh.update(calc_edges=True)


def wire_mesh(mesh, points, edges):
    """Fill an empty mesh with vertices ``points`` (n, 3) and ``edges`` (m, 2), no faces."""
    mesh.vertices.add(len(points))
    mesh.vertices.foreach_set("co", np.asarray(points, np.float32).ravel())
    mesh.edges.add(len(edges))
    mesh.edges.foreach_set("vertices", np.asarray(edges, np.int32).ravel())
    mesh.update()


def mesh_geometry(mesh):
    """What :func:`fill_mesh` writes, read back from ``mesh``: ``(co, Polygons)``."""
    co = np.empty(len(mesh.vertices) * 3, np.float32)
    _attribute(mesh, "position", "FLOAT_VECTOR", "POINT").data.foreach_get("vector", co)
    indices = np.empty(len(mesh.loops), np.int32)
    corners, field = _corner_vertices(mesh)
    corners.foreach_get(field, indices)
    starts = np.empty(len(mesh.polygons), np.int32)
    mesh.polygons.foreach_get("loop_start", starts)
    sizes = np.diff(starts, append=np.int32(len(indices))).astype(np.int32)
    return co.reshape(-1, 3), Polygons(indices, starts, sizes)


def refill_mesh(mesh, co, polys):
    """Replace the geometry of ``mesh`` in place; in a :func:`.jobs.transaction` that fails
    (filling half way, or a later step) the old geometry is put back."""
    old = mesh_geometry(mesh)

    def restore():
        mesh.clear_geometry()
        fill_mesh(mesh, *old)

    jobs.on_undo(restore)
    mesh.clear_geometry()
    fill_mesh(mesh, co, polys)


def tool_triangles(tool_obj, depsgraph, *, box=False):
    """A tool's evaluated mesh as triangles in its local coordinates, and its placement.

    Parameters
    ----------
    tool_obj : bpy.types.Object
        A mesh object (modifiers applied through ``depsgraph``).
    depsgraph : bpy.types.Depsgraph or None
        Evaluated depsgraph (None: the object's own data, no modifiers).
    box : bool
        The tool's bounding box (8 corners, the 12 triangles :data:`BOX_FACES`) instead of
        its mesh.

    Returns
    -------
    vertices : (V, 3) ndarray of float64
        Local coordinates (Blender stores them as float32).
    faces : (F, 3) ndarray of int32
        The mesh's loop triangles (outward when the mesh's normals point outwards).
    matrix_world : (4, 4) ndarray of float64
    """
    evaluated = tool_obj if depsgraph is None else tool_obj.evaluated_get(depsgraph)
    matrix = np.array(evaluated.matrix_world, np.float64)
    if box:
        corners = np.array([tuple(c) for c in evaluated.bound_box], np.float64)
        lo, hi = corners.min(axis=0), corners.max(axis=0)
        ends = np.stack([lo, hi])
        grid = np.array([[i, j, k] for i in (0, 1) for j in (0, 1) for k in (0, 1)])
        return ends[grid, [0, 1, 2]], BOX_FACES, matrix
    mesh = evaluated.data
    co = np.empty(len(mesh.vertices) * 3, np.float32)
    mesh.vertices.foreach_get("co", co)
    tris = np.empty(len(mesh.loop_triangles) * 3, np.int32)
    mesh.loop_triangles.foreach_get("vertices", tris)
    return co.reshape(-1, 3).astype(np.float64), tris.reshape(-1, 3), matrix
