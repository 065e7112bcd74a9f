"""Meshes in and out of Blender in bulk: a surface's polygons in, a tool's triangles out.

Arrays move with ``foreach_set`` / ``foreach_get`` through the mesh's attributes, with no Python
loop per vertex (the per-item ``MeshLoop.vertex_index`` path is several times slower on large
meshes). A surface comes with its edges (:class:`Faces`, from the core's
:class:`BoundaryMesh`), written like the rest: Blender's own edge pass (``calc_edges``, a
hash of every corner) takes longer than all the other arrays together.
"""

from dataclasses import dataclass

import numpy as np

from ..volumeevm_addon.model import BLENDER_UNITS_PER_MM, BoundaryMesh, Polygons
from . import jobs

#: Outward triangles of the box whose corner (i, j, k) in {0, 1}^3 is vertex 4 i + 2 j + k.
BOX_FACES = np.array([[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
                      [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]], np.int32)


@dataclass(frozen=True)
class Faces:
    """A surface's polygons with its edges, as Blender stores them (int32 arrays).

    Attributes
    ----------
    polygons : Polygons
        Loops (corner vertices), loop starts and sizes.
    edges : (E, 2) ndarray of np.int32
        Each edge's two vertices, once.
    corner_edges : (L,) ndarray of np.int32
        The edge from each loop corner to the next corner of its polygon.
    """

    polygons: Polygons
    edges: np.ndarray
    corner_edges: np.ndarray

    def sizes(self):
        """The counts Blender keeps: (edges, loops, polygons)."""
        return len(self.edges), len(self.polygons.indices), len(self.polygons)


def surface_geometry(vevm, previous=None, manifold=False, smooth=False):
    """The boundary mesh of a VolumeEVM, ready for :func:`fill_mesh`.

    Parameters
    ----------
    vevm : VolumeEVM
    previous : tuple, optional
        ``(co, boundary)`` of an earlier region of the same grid (what this returned for it):
        the mesh is updated where the two differ (:meth:`BoundaryMesh.updated`), and only the
        new vertices are placed (the others keep their positions).
    manifold : bool
        Make the manifold mesh for 3D printing instead (``vevm.mesh(manifold=True)``), from
        scratch; ``boundary`` is then None.
    smooth : bool
        Make the smooth display surface instead (``vevm.mesh(manifold, smooth=True)``), from
        scratch; ``boundary`` is then None.

    Returns
    -------
    co : (n, 3) ndarray of np.float32
        Vertices in Blender units: ``vevm.mesh()``'s times :data:`BLENDER_UNITS_PER_MM`.
    faces : Faces
    boundary : BoundaryMesh
        The core's mesh, to update the next one from.
    """
    if manifold or smooth:
        vertices, polygons = vevm.evm.mesh(manifold=manifold, smooth=smooth)
        return _blender_units(vevm, vertices), Faces(polygons, *polygons.unique_edges()), None
    if previous is None:
        boundary = BoundaryMesh(vevm.evm)
        co = _blender_units(vevm, boundary.vertices)
    else:
        old_co, old = previous
        boundary = old.updated(vevm.evm)
        if boundary is old:
            co = old_co
        else:
            co, fresh = boundary.carry(old_co)
            co[fresh] = _blender_units(vevm, boundary.points(fresh))
    return co, Faces(boundary.polygons, *boundary.edges()), boundary


def label_geometry(regions, manifold=False):
    """Every label's mesh of a label set (:meth:`LabelSet.meshes`: where labels touch, their
    polygons are the same, reversed), ready for :func:`fill_mesh`.

    Parameters
    ----------
    regions : LabelSet
    manifold : bool
        The manifold meshes for 3D printing instead.

    Returns
    -------
    dict
        ``label -> (co, Faces)``, vertices in Blender units (float32), in label order.
    """
    return {label: ((vertices * BLENDER_UNITS_PER_MM).astype(np.float32),
                    Faces(polygons, *polygons.unique_edges()))
            for label, (vertices, polygons) in regions.meshes(manifold=manifold).items()}


def _blender_units(vevm, points):
    """Lattice points of ``vevm``'s grid in Blender units, float32 (as Blender keeps them)."""
    return (vevm.corner_positions(points) * BLENDER_UNITS_PER_MM).astype(np.float32)


def _attribute(mesh, name, kind, domain):
    found = mesh.attributes.get(name)
    return found if found is not None else mesh.attributes.new(name, kind, domain)


def _corner_vertices(mesh):
    """The corners' vertex indices of a mesh and their field name, for ``foreach_get/set``."""
    found = mesh.attributes.get(".corner_vert")
    return (found.data, "value") if found is not None else (mesh.loops, "vertex_index")


def _write(mesh, co, faces):
    """Write every array of ``co`` and ``faces`` into a mesh that has their sizes."""
    polygons = faces.polygons
    _attribute(mesh, "position", "FLOAT_VECTOR", "POINT").data.foreach_set("vector", co.ravel())
    _attribute(mesh, ".edge_verts", "INT32_2D", "EDGE").data.foreach_set("value",
                                                                         faces.edges.ravel())
    corners, field = _corner_vertices(mesh)
    corners.foreach_set(field, polygons.indices)
    _attribute(mesh, ".corner_edge", "INT", "CORNER").data.foreach_set("value", faces.corner_edges)
    mesh.polygons.foreach_set("loop_start", polygons.starts)
    mesh.update()


def fill_mesh(mesh, co, faces, smooth=False):
    """Fill an empty mesh in bulk: vertices ``co`` (n, 3) float32 and :class:`Faces`.

    Positions, edges, corner vertices and corner edges are written through the mesh's
    attributes (one copy each). Faces are flat (a voxel boundary has no smooth normals; new
    meshes shade smooth since 4.1), or with ``smooth`` shaded smooth (the smooth surface).
    """
    mesh.vertices.add(len(co))
    mesh.edges.add(len(faces.edges))
    mesh.loops.add(len(faces.polygons.indices))
    mesh.polygons.add(len(faces.polygons))
    _attribute(mesh, "sharp_face", "BOOLEAN", "FACE").data.foreach_set(
        "value", np.full(len(faces.polygons), not smooth))
    _write(mesh, co, faces)


def wire_mesh(mesh, points, edges):
    """Fill an empty mesh with vertices ``points`` (n, 3) and ``edges`` (m, 2), no faces."""
    mesh.vertices.add(len(points))
    mesh.vertices.foreach_set("co", np.asarray(points, np.float32).ravel())
    mesh.edges.add(len(edges))
    mesh.edges.foreach_set("vertices", np.asarray(edges, np.int32).ravel())
    mesh.update()


def mesh_geometry(mesh):
    """What :func:`fill_mesh` writes, read back from ``mesh``: ``(co, Faces)``."""
    co = np.empty((len(mesh.vertices), 3), np.float32)
    _attribute(mesh, "position", "FLOAT_VECTOR", "POINT").data.foreach_get("vector", co.ravel())
    edges = np.empty((len(mesh.edges), 2), np.int32)
    _attribute(mesh, ".edge_verts", "INT32_2D", "EDGE").data.foreach_get("value", edges.ravel())
    indices = np.empty(len(mesh.loops), np.int32)
    corners, field = _corner_vertices(mesh)
    corners.foreach_get(field, indices)
    corner_edges = np.empty(len(mesh.loops), np.int32)
    _attribute(mesh, ".corner_edge", "INT", "CORNER").data.foreach_get("value", corner_edges)
    starts = np.empty(len(mesh.polygons), np.int32)
    mesh.polygons.foreach_get("loop_start", starts)
    sizes = np.diff(starts, append=np.int32(len(indices))).astype(np.int32)
    return co, Faces(Polygons(indices, starts, sizes), edges, corner_edges)


def sizes(mesh):
    """The counts of a Blender mesh: (vertices, edges, loops, polygons)."""
    return len(mesh.vertices), len(mesh.edges), len(mesh.loops), len(mesh.polygons)


def refill_mesh(mesh, co, faces, old=None):
    """Replace the geometry of ``mesh`` in place; in a :func:`.jobs.transaction` that fails
    (filling half way, or a later step) the old geometry is put back: ``old``, the ``(co,
    Faces)`` the caller knows the mesh holds (what it wrote last), else read from the mesh.
    Arrays of the sizes the mesh has are written over its own (no new geometry); others
    replace it."""
    if old is None:
        old = mesh_geometry(mesh)

    def restore():
        mesh.clear_geometry()
        fill_mesh(mesh, *old)

    jobs.on_undo(restore)
    if (len(co), *faces.sizes()) == sizes(mesh):
        _write(mesh, co, faces)
    else:
        mesh.clear_geometry()
        fill_mesh(mesh, co, faces)


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
