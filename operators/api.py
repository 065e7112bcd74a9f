"""The Python API for scripts: import a volume, build its VolumeEVM, make its surface mesh.

The operators call the same jobs, so a script and a button give the same objects::

    import bpy
    from bl_ext.user_default.volumeevm.operators import api   # installed extension
    vol = api.import_volume("/data/head.nrrd")
    api.build(vol, threshold=300.0)                 # data units (HU for CT)
    surface = api.make_mesh(vol)

Objects and placement:

- ``import_volume`` makes a *volume object*: a wire box around the grid, in physical
  millimetres scaled by :data:`BLENDER_UNITS_PER_MM` (1 mm = 0.001 BU), LPS axes = Blender X, Y, Z,
  object matrix identity. The dense array stays in a runtime cache (not in the .blend).
- ``build`` makes the VolumeEVM of ``threshold <= density (<= upper)`` and keeps it in a sidecar
  ``.vevm`` file (see :mod:`.sidecar`).
- ``make_mesh`` makes (or refreshes) the *surface object*: the VolumeEVM's boundary polygons,
  child of the volume object with identity matrices, so moving the box moves the surface.

CAD tools (a non-destructive stack per volume object, see ``add_tool``)::

    api.add_tool(vol, drill, "cut")                 # any closed mesh object; also "keep", "add",
    api.add_tool(vol, None, "largest")              # "largest" (no tool), "clip" (tool's box)
    drill.location.x += 0.01; api.evaluate(vol)     # or any depsgraph update (handler)
    api.apply_stack(vol)                            # the result becomes the VolumeEVM

Errors: bad input raises :class:`VolumeEVMError` (and ``OSError`` for unreadable files). Whatever
the error, ``import_volume``, ``build``, ``make_mesh`` and ``add_tool`` leave the scene as it was.
Under ``blender --background`` progress lines ``[volumeevm] 42% building EVM`` are printed.
"""

import functools
import hashlib
import json
import time
from contextlib import contextmanager
from pathlib import Path

import bpy
import numpy as np

from ..volumeevm_addon import (
    BLENDER_UNITS_PER_MM,
    EVM,
    EditStack,
    Polygons,
    ToolOperation,
    VolumeEVM,
    VolumeEVMError,
    box_evm,
    grid_to_world,
    index_to_physical,
    read_volume,
    voxelize_mesh_evm,
)
from . import _jobs, _runtime, sidecar

__all__ = ["import_volume", "build", "make_mesh", "volume_object", "get_vevm", "get_volume",
           "add_tool", "evaluate", "apply_stack", "remove_tool", "move_tool", "tool_problem",
           "stack_state"]

_COMPOUND_ENDINGS = (".nii.gz",)

#: Histogram bins kept on a volume object (bpy.props vectors hold at most 32 items).
HISTOGRAM_BINS = 32


# ---------------------------------------------------------------------------- helpers
def default_name(path):
    """Object name for a volume read from ``path`` (file stem, or the folder's name)."""
    if not isinstance(path, (str, Path)):
        path = Path(list(path)[0]).parent
    path = Path(path)
    name = path.name
    for ending in _COMPOUND_ENDINGS:
        if name.lower().endswith(ending):
            return name[: -len(ending)] or "Volume"
    return (path.stem if path.suffix else name) or "Volume"


def histogram(array, bins=HISTOGRAM_BINS):
    """Voxel counts in ``bins`` equal bins over the data range, and that range."""
    lo, hi = float(array.min()), float(array.max())
    counts, _ = np.histogram(array, bins=bins, range=(lo, hi) if hi > lo else (lo, lo + 1.0))
    return counts.astype(np.float64), lo, hi


def otsu_threshold(array, bins=256):
    """Otsu's threshold (data units): a starting value for the threshold field."""
    lo, hi = float(array.min()), float(array.max())
    if hi <= lo:
        return lo
    counts, edges = np.histogram(array, bins=bins, range=(lo, hi))
    counts = counts.astype(np.float64)
    centres = 0.5 * (edges[:-1] + edges[1:])
    w0 = np.cumsum(counts)
    w1 = w0[-1] - w0
    s0 = np.cumsum(counts * centres)
    with np.errstate(divide="ignore", invalid="ignore"):
        between = w0 * w1 * (s0 / w0 - (s0[-1] - s0) / w1) ** 2
    between = np.nan_to_num(between[:-1], nan=-1.0)
    return float(edges[int(np.argmax(between)) + 1])


def volume_object(obj):
    """The volume object of ``obj`` (itself, or the volume a surface was made from).

    Raises
    ------
    VolumeEVMError
        If ``obj`` is not a VolumeEVM volume or surface object.
    """
    if obj is None:
        raise VolumeEVMError("no object given; select a volume made by Import Volume")
    settings = obj.volumeevm
    if settings.role == "VOLUME":
        return obj
    if settings.role == "SURFACE" and settings.volume is not None:
        return settings.volume
    raise VolumeEVMError(f"{obj.name}: not a VolumeEVM volume; import a volume first")


def get_volume(obj):
    """The dense volume of a volume object (runtime cache, else re-read from its source)."""
    obj = volume_object(obj)
    return drain_quietly(_read_steps(obj.volumeevm.uid, *_source_of(obj)))


def get_vevm(obj):
    """The VolumeEVM of a volume (or surface) object, from the cache or its sidecar."""
    return sidecar.load_vevm(volume_object(obj))


def drain_quietly(steps):
    return _jobs.drain(steps, verbose=False)


def _source_of(obj):
    settings = obj.volumeevm
    return settings.source_path, json.loads(settings.reader_options or "{}")


def _physical_box(shape, spacing, origin, orientation):
    """The 8 corners of the grid (lattice -0.5 .. shape - 0.5) in Blender units, and 12 edges."""
    corners = np.array([[i, j, k] for i in (0, 1) for j in (0, 1) for k in (0, 1)], np.float64)
    corners = corners * np.asarray(shape, np.float64) - 0.5
    matrix = index_to_physical(spacing, origin, orientation)
    points = (corners @ matrix[:3, :3].T + matrix[:3, 3]) * BLENDER_UNITS_PER_MM
    edges = [(a, b) for a in range(8) for b in range(a + 1, 8) if bin(a ^ b).count("1") == 1]
    return points, np.array(edges, np.int32)


def _link(context, obj):
    """Link ``obj`` into the active collection and make it the only selected, active object."""
    collection = context.collection or context.scene.collection
    collection.objects.link(obj)
    view_layer = context.view_layer
    if view_layer is None:
        return
    view_layer.update()  # sync the layer with the collection before selecting
    if view_layer.objects.get(obj.name) is None:
        return  # the active collection is excluded from the view layer
    for other in view_layer.objects:
        if other.select_get():
            other.select_set(False)
    obj.select_set(True)
    view_layer.objects.active = obj


# ---------------------------------------------------------------------------- import
def _read_steps(uid, path, options):
    """Steps: the cached volume of ``uid`` or a fresh read of ``path``."""
    vol = _runtime.volume(uid)
    if vol is None:
        if not path:
            raise VolumeEVMError("the volume has no source file to read it again from")
        yield 0.0, f"reading {Path(str(path)).name}"
        vol = read_volume(path, **options)
    return vol


def _import_steps(path, options):
    yield 0.0, f"reading {default_name(path)}"
    vol = read_volume(path, **options)
    yield 0.7, "histogram"
    counts, lo, hi = histogram(vol.array)
    threshold = otsu_threshold(vol.array)
    return vol, counts, lo, hi, threshold


def import_job(context, path, *, name=None, **reader_options):
    """The import job: read ``path`` and make a volume object (see :func:`import_volume`)."""
    if isinstance(path, (str, Path)):
        source = str(Path(path))
    else:
        files = [str(p) for p in path]
        if not files:
            raise VolumeEVMError("no files given")
        path, source = files, str(Path(files[0]).parent)
    json.dumps(reader_options)  # options must be plain values (they are stored as JSON)
    name = name or default_name(path)

    def commit(result):
        vol, counts, lo, hi, threshold = result
        points, edges = _physical_box(vol.shape, vol.spacing, vol.origin, vol.orientation)
        mesh = bpy.data.meshes.new(name)
        mesh.vertices.add(len(points))
        mesh.vertices.foreach_set("co", points.astype(np.float32).ravel())
        mesh.edges.add(len(edges))
        mesh.edges.foreach_set("vertices", edges.ravel())
        mesh.update()
        obj = bpy.data.objects.new(name, mesh)
        obj.display_type = "WIRE"
        obj.hide_render = True
        s = obj.volumeevm
        s.role = "VOLUME"
        s.uid = _runtime.new_uid()
        s.source_path = source
        s.reader_options = json.dumps(reader_options)
        s.shape = vol.shape
        s.spacing = vol.spacing
        s.origin = vol.origin
        s.orientation = np.asarray(vol.orientation, np.float64).ravel().tolist()
        s.spacing_known = vol.spacing_known
        s.units = vol.units
        s.dtype = str(vol.array.dtype)
        s.value_min, s.value_max = lo, hi
        s.histogram = counts.tolist()
        s.threshold = threshold
        s.upper = hi
        _link(context, obj)
        _runtime.put_volume(s.uid, vol)
        _runtime.forget_except({o.volumeevm.uid for o in bpy.data.objects})
        return obj

    return _jobs.Job(f"Import {name}", _import_steps(path, reader_options), commit)


def import_volume(path, *, name=None, **reader_options):
    """Read a volume file (or DICOM folder / list of files) and make a volume object.

    Parameters
    ----------
    path : str, Path or sequence of str
        A file with a supported extension, a DICOM folder, or the files of one DICOM series.
    name : str, optional
        Object name (default: the file's stem).
    **reader_options
        Passed to :func:`volumeevm_addon.read_volume` (raw: ``shape``, ``dtype``, ...).

    Returns
    -------
    bpy.types.Object
        The volume object (wire box, ``obj.volumeevm.role == "VOLUME"``), active and selected.
    """
    return _jobs.run(import_job(bpy.context, path, name=name, **reader_options))


# ---------------------------------------------------------------------------- build
def _build_steps(uid, path, options, threshold, upper):
    vol = yield from _read_steps(uid, path, options)
    yield 0.3, "building EVM"
    vevm = VolumeEVM.from_volume(vol, threshold, upper)
    yield 0.9, "saving VolumeEVM"
    return vol, vevm


def build_job(obj, threshold=None, upper=None):
    """The build job (see :func:`build`)."""
    obj = volume_object(obj)
    s = obj.volumeevm
    if threshold is None:
        threshold = s.threshold
        upper = s.upper if s.use_upper else None
    threshold = float(threshold)
    upper = None if upper is None else float(upper)
    if upper is not None and upper < threshold:
        raise VolumeEVMError(f"{obj.name}: upper bound {upper} is below the threshold {threshold}")
    name, uid = obj.name, s.uid
    path, options = _source_of(obj)

    def commit(result):
        vol, vevm = result
        target = bpy.data.objects.get(name)
        if target is None:
            raise VolumeEVMError(f"{name}: the volume object was deleted while building")
        report = vevm.size_report()
        file = sidecar.save_new(uid, vevm)
        _jobs.on_undo(functools.partial(file.unlink, missing_ok=True))
        values = dict(threshold=threshold, use_upper=upper is not None,
                      built_threshold=threshold, built_use_upper=upper is not None,
                      built_upper=upper if upper is not None else 0.0,
                      voxel_count=vevm.voxel_count, ev_count=len(vevm.evm),
                      vevm_bytes=report["total_bytes"], dense_bytes=report["dense_bytes"],
                      vevm_path=str(file))
        if upper is not None:
            values["upper"] = upper
        _jobs.assign(target.volumeevm, **values)
        _jobs.on_undo(functools.partial(_runtime.set_status, uid, _runtime.status(uid)))
        _runtime.set_status(uid, "")
        _runtime.put_volume(uid, vol)
        return vevm

    return _jobs.Job(f"Build VolumeEVM of {name}",
                     _build_steps(uid, path, options, threshold, upper), commit)


def build(obj, threshold=None, upper=None):
    """Build the VolumeEVM of a volume object at ``threshold <= density (<= upper)``.

    Parameters
    ----------
    obj : bpy.types.Object
        A volume object (or its surface).
    threshold, upper : float, optional
        In the data's own units; default: the object's ``volumeevm.threshold`` (and ``upper``
        when ``use_upper`` is set). Stored on the object.

    Returns
    -------
    VolumeEVM
        Also saved to a sidecar file whose path is ``obj.volumeevm.vevm_path``.
    """
    return _jobs.run(build_job(obj, threshold, upper))


# ---------------------------------------------------------------------------- mesh
def _mesh_steps(vevm_or_path):
    if isinstance(vevm_or_path, VolumeEVM):
        vevm = vevm_or_path
    else:
        yield 0.0, "loading VolumeEVM"
        vevm = VolumeEVM.load(vevm_or_path)
    yield 0.2, "meshing"
    verts_mm, polys = vevm.mesh()
    yield 0.9, "making the mesh object"
    co = (np.asarray(verts_mm, np.float64) * BLENDER_UNITS_PER_MM).astype(np.float32)
    return vevm, co, polys


def _attribute(mesh, name, kind, domain):
    found = mesh.attributes.get(name)
    return found if found is not None else mesh.attributes.new(name, kind, domain)


def _corner_vertices(mesh):
    """The corners' vertex indices of a mesh and their field name, for ``foreach_get/set``."""
    found = mesh.attributes.get(".corner_vert")
    return (found.data, "value") if found is not None else (mesh.loops, "vertex_index")


def fill_mesh(mesh, co, polys):
    """Fill an empty mesh in bulk: vertices ``co`` (n, 3) and polygons (loops, starts).

    Positions and corner vertices are written through the mesh's attributes (one copy each;
    the per-item ``MeshLoop.vertex_index`` path is several times slower on large meshes).
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


def own_surface(vol_obj):
    """The surface object made from this volume (not one a duplicate still points at), or None."""
    surface = vol_obj.volumeevm.surface
    if surface is not None and surface.type == "MESH" and surface.volumeevm.volume == vol_obj:
        return surface
    return None


def _attach_surface(context, owner, mesh):
    """Give ``mesh`` to the owner's surface object (keeping its materials), or make one.

    In a job's commit the change is undone if the job fails (:func:`._jobs.transaction`), and
    the replaced mesh is removed only once it succeeded.
    """
    surface = own_surface(owner)
    if surface is not None:
        old = surface.data
        for material in old.materials:
            mesh.materials.append(material)
        _jobs.assign(surface, data=mesh)
        _jobs.on_success(functools.partial(_remove_unused_mesh, old))
        return surface
    surface = bpy.data.objects.new(f"{owner.name}_surface", mesh)
    surface.volumeevm.role = "SURFACE"
    surface.volumeevm.volume = owner
    surface.parent = owner
    _jobs.assign(owner.volumeevm, surface=surface)
    _link(context, surface)
    return surface


def _remove_unused_mesh(mesh):
    if mesh.users == 0:
        bpy.data.meshes.remove(mesh)


def mesh_job(context, obj):
    """The make-mesh job (see :func:`make_mesh`)."""
    vol_obj = volume_object(obj)
    s = vol_obj.volumeevm
    if not s.vevm_path:
        raise VolumeEVMError(f"{vol_obj.name}: no VolumeEVM built yet; build one first")
    path = sidecar.resolve(vol_obj)
    if path is None:
        raise VolumeEVMError(
            f"{vol_obj.name}: VolumeEVM file {s.vevm_path!r} not found; build it again")
    cached = _runtime.vevm(path)
    name = vol_obj.name

    def commit(result):
        vevm, co, polys = result
        _runtime.put_vevm(path, vevm)
        owner = bpy.data.objects.get(name)
        if owner is None:
            raise VolumeEVMError(f"{name}: the volume object was deleted while meshing")
        mesh = bpy.data.meshes.new(f"{name}_surface")
        fill_mesh(mesh, co, polys)
        surface = _attach_surface(context, owner, mesh)
        _jobs.assign(surface.volumeevm, stack_signature="")
        if len(owner.volumeevm.tools):
            # The surface shows the tool stack's result, not the bare VolumeEVM.
            refresh_quietly(owner, context.evaluated_depsgraph_get())
        return surface

    return _jobs.Job(f"Mesh of {name}", _mesh_steps(cached if cached is not None else path),
                     commit)


def make_mesh(obj):
    """Make (or refresh) the surface mesh object of a volume's VolumeEVM.

    Returns
    -------
    bpy.types.Object
        The surface object: polygons of the VolumeEVM's boundary (vertices in Blender units,
        ``vevm.mesh()`` times 0.001), child of the volume object, identity matrices.
    """
    return _jobs.run(mesh_job(bpy.context, obj))


# ---------------------------------------------------------------------------- tool stack
#: API operation names -> the stack entries' operation identifiers (``ui/props.py``).
TOOL_OPERATIONS = {"cut": "CUT", "keep": "KEEP", "add": "ADD", "largest": "LARGEST",
                   "clip": "CLIP"}
#: Entry operation -> what the core does (a clip box is a "keep" with the tool's box).
_CORE_OPERATION = {"CUT": "cut", "KEEP": "keep", "ADD": "add", "CLIP": "keep",
                   "LARGEST": "largest"}
TOOL_LABELS = {"CUT": "Cut", "KEEP": "Keep inside", "ADD": "Add", "LARGEST": "Keep largest part",
               "CLIP": "Clip to box"}
#: The tool of a disabled entry: skipped by the stack, so it is never voxelized.
_SKIPPED = EVM()
#: Outward triangles of the box whose corner (i, j, k) in {0, 1}^3 is vertex 4 i + 2 j + k.
_BOX_FACES = np.array([[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
                       [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]], np.int32)

_busy = False  # True while the API evaluates or writes: the depsgraph handler stays out


def is_busy():
    """True while a stack evaluation runs (handlers must not start another one)."""
    return _busy


@contextmanager
def _exclusive():
    global _busy
    previous, _busy = _busy, True
    try:
        yield
    finally:
        _busy = previous


def tool_problem(vol_obj, tool_obj):
    """Why ``tool_obj`` cannot be a tool of volume ``vol_obj`` ("" if it can)."""
    if tool_obj is None:
        return "Choose a tool object (any closed mesh)"
    if tool_obj.type != "MESH":
        return f"{tool_obj.name} is not a mesh ({tool_obj.type.lower()})"
    if tool_obj == vol_obj or tool_obj.volumeevm.role == "VOLUME":
        return f"{tool_obj.name} is a volume's box, not a tool"
    if tool_obj == vol_obj.volumeevm.surface or (
            tool_obj.volumeevm.role == "SURFACE" and tool_obj.volumeevm.volume == vol_obj):
        return f"{tool_obj.name} is the volume's own surface"
    return ""


def tool_triangles(tool_obj, depsgraph, *, box=False):
    """A tool's evaluated mesh as triangles in its local coordinates, and its placement.

    Parameters
    ----------
    tool_obj : bpy.types.Object
        A mesh object (modifiers applied through ``depsgraph``).
    depsgraph : bpy.types.Depsgraph or None
        Evaluated depsgraph (None: the object's own data, no modifiers).
    box : bool
        The tool's bounding box (8 corners, 12 triangles) instead of its mesh.

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
        return ends[grid, [0, 1, 2]], _BOX_FACES, matrix
    mesh = evaluated.data
    co = np.empty(len(mesh.vertices) * 3, np.float32)
    mesh.vertices.foreach_get("co", co)
    tris = np.empty(len(mesh.loop_triangles) * 3, np.int32)
    mesh.loop_triangles.foreach_get("vertices", tris)
    return co.reshape(-1, 3).astype(np.float64), tris.reshape(-1, 3), matrix


def tool_to_grid(vevm, volume_matrix, tool_matrix):
    """4x4 matrix from a tool's local coordinates to the volume's voxel-centre indices."""
    world = grid_to_world(vevm.spacing, vevm.origin, vevm.orientation, volume_matrix)
    to_grid = np.linalg.inv(world) @ np.asarray(tool_matrix, np.float64)
    to_grid[3] = (0.0, 0.0, 0.0, 1.0)  # affine exactly (the inverse may leave rounding there)
    return to_grid


def voxelize_tool(vertices, faces, to_grid, shape):
    """The EVM of a tool's voxels (the core's :func:`voxelize_mesh_evm`); a clip box that is
    axis-aligned in the grid is made from its corners directly (:func:`box_evm`)."""
    matrix = np.asarray(to_grid, np.float64)
    if faces is _BOX_FACES and np.count_nonzero(matrix[:3, :3] - np.diag(np.diag(matrix[:3, :3]))) == 0:
        corners = np.asarray(vertices, np.float64) @ matrix[:3, :3].T + matrix[:3, 3]
        return box_evm(corners.min(axis=0), corners.max(axis=0), shape)
    return voxelize_mesh_evm(vertices, faces, shape, to_grid)


def _digest(*arrays):
    h = hashlib.blake2b(digest_size=16)
    for a in arrays:
        a = np.ascontiguousarray(a)
        h.update(str((a.dtype.str, a.shape)).encode())
        h.update(a.tobytes())
    return h.hexdigest()


def _base_digest(vevm):
    return _digest(vevm.evm.vertices, vevm.table(0), np.asarray(vevm.shape),
                   vevm.index_to_physical())


class _Entry:
    """One stack entry read from Blender: what to do, and the tool's triangles and placement."""

    def __init__(self, number, kind, enabled, density, tool_name, mesh):
        self.number, self.kind, self.enabled = number, kind, enabled
        self.density, self.tool_name, self.mesh = density, tool_name, mesh
        self.digest = "" if mesh is None else _digest(*mesh)

    @property
    def label(self):
        what = TOOL_LABELS[self.kind]
        return f"{what} with {self.tool_name}" if self.tool_name else what

    def key(self):
        return f"{self.kind}:{int(self.enabled)}:{self.density!r}:{self.digest}"


def _read_entry(vol_obj, vevm, depsgraph, number, kind, tool_obj, enabled, density):
    """An :class:`_Entry` (reading the tool's evaluated mesh); raises for a bad tool."""
    if kind not in _CORE_OPERATION:
        raise VolumeEVMError(f"unknown tool operation {kind!r}")
    density = float(density) if kind == "ADD" and density is not None else None
    if kind == "LARGEST" or not enabled:
        name = "" if tool_obj is None or kind == "LARGEST" else tool_obj.name
        return _Entry(number, kind, enabled, density, name, None)
    if tool_obj is None:
        raise VolumeEVMError(f"entry {number} ({TOOL_LABELS[kind]}): it has no tool object "
                             f"(deleted?); choose one or remove the entry")
    problem = tool_problem(vol_obj, tool_obj)
    if problem:
        raise VolumeEVMError(f"entry {number} ({TOOL_LABELS[kind]}): {problem}")
    volume_matrix = np.array(
        (vol_obj if depsgraph is None else vol_obj.evaluated_get(depsgraph)).matrix_world)
    vertices, faces, matrix = tool_triangles(tool_obj, depsgraph, box=kind == "CLIP")
    to_grid = tool_to_grid(vevm, volume_matrix, matrix)
    return _Entry(number, kind, enabled, density, tool_obj.name,
                  (vertices, faces, to_grid, np.asarray(vevm.shape)))


def _read_entries(vol_obj, vevm, depsgraph):
    entries = []
    for number, e in enumerate(vol_obj.volumeevm.tools, 1):
        entries.append(_read_entry(vol_obj, vevm, depsgraph, number, e.operation, e.tool,
                                   e.enabled, e.density if e.use_density else None))
    return entries


def _signature(state, entries):
    """What the surface shows: "" for the bare VolumeEVM, else a digest of base and entries."""
    if not entries:
        return ""
    text = "|".join([state.base_digest, *(e.key() for e in entries)])
    return hashlib.blake2b(text.encode(), digest_size=16).hexdigest()


def _stack_state_of(vol_obj):
    """The runtime stack state of a volume object (an empty one made on first use)."""
    uid = vol_obj.volumeevm.uid
    state = _runtime.stack_state(uid, vol_obj.name)
    if state is None:
        state = _runtime.StackState()
        _runtime.put_stack_state(uid, vol_obj.name, state)
    return state


def stack_state(obj):
    """The runtime state of a volume's tool stack (made, or re-synced, from its properties).

    The stack's base is the VolumeEVM of ``volumeevm.vevm_path``; when that path changed (a
    build, Apply, or undo/redo restoring another path) a new ``EditStack`` starts from it.
    """
    vol_obj = volume_object(obj)
    state = _stack_state_of(vol_obj)
    base = sidecar.load_vevm(vol_obj)
    path = str(sidecar.resolve(vol_obj))
    if state.stack is None or state.base_path != path or state.stack.base is not base:
        state.base_path = path
        state.base_digest = _base_digest(base)
        state.stack = EditStack(base)
        state.result = None
    return state


def _operation(state, entry, timing):
    """The core's ToolOperation for an entry, voxelizing its tool unless it is cached."""
    core = _CORE_OPERATION[entry.kind]
    if not entry.enabled:
        return ToolOperation(None if core == "largest" else _SKIPPED, core, enabled=False)
    if core == "largest":
        return ToolOperation(operation="largest")
    tool = state.tools.get(entry.digest)
    if tool is None:
        start = time.perf_counter()
        try:
            tool = voxelize_tool(*entry.mesh)
        except VolumeEVMError as error:
            raise VolumeEVMError(f"{entry.label}: {error}") from None
        timing["voxelize_s"] += time.perf_counter() - start
        timing["voxelized"] += 1
    state.remember_tool(entry.digest, tool)
    return ToolOperation(tool, core, density=entry.density)


def _evaluate(state, entries, timing):
    """The stack's result for ``entries`` (cached prefix reused)."""
    operations = [_operation(state, e, timing) for e in entries]
    start = time.perf_counter()
    try:
        result = state.stack.evaluate(operations)
    except VolumeEVMError:
        # Find the entry that fails (cached prefixes make this cheap) and name it.
        for count in range(1, len(operations) + 1):
            try:
                state.stack.evaluate(operations[:count])
            except VolumeEVMError as error:
                raise VolumeEVMError(f"{entries[count - 1].label}: {error}") from None
        raise
    timing["evaluate_s"] = time.perf_counter() - start
    timing["recomputed"] = state.stack.last_recomputed
    state.result = result
    return result


def _mesh_geometry(mesh):
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


def _refill_mesh(mesh, co, polys):
    """Replace the geometry of ``mesh`` in place; in a :func:`._jobs.transaction` that fails
    (filling half way, or a later step) the old geometry is put back."""
    old = _mesh_geometry(mesh)

    def restore():
        mesh.clear_geometry()
        fill_mesh(mesh, *old)

    _jobs.on_undo(restore)
    mesh.clear_geometry()
    fill_mesh(mesh, co, polys)


def _write_surface(context, vol_obj, result, signature, timing, *, create):
    """Put the result's mesh into the volume's surface (in place), or make the surface.

    All or nothing: if writing fails, the surface keeps its old mesh (or none is made).
    """
    surface = own_surface(vol_obj)
    if surface is None and not create:
        return None
    start = time.perf_counter()
    verts_mm, polys = result.mesh()
    co = (np.asarray(verts_mm, np.float64) * BLENDER_UNITS_PER_MM).astype(np.float32)
    middle = time.perf_counter()
    with _jobs.transaction():
        if surface is None:
            mesh = bpy.data.meshes.new(f"{vol_obj.name}_surface")
            fill_mesh(mesh, co, polys)
            surface = _attach_surface(context, vol_obj, mesh)
        else:
            _refill_mesh(surface.data, co, polys)
        _jobs.assign(surface.volumeevm, stack_signature=signature)
    end = time.perf_counter()
    timing["mesh_s"], timing["write_s"] = middle - start, end - middle
    timing["polygons"] = len(polys)
    return surface


def refresh(vol_obj, depsgraph, *, create=False, force=False, extra=None):
    """Evaluate a volume's tool stack and refresh its surface mesh if what it shows changed.

    Parameters
    ----------
    vol_obj : bpy.types.Object
        A volume object.
    depsgraph : bpy.types.Depsgraph
        Evaluated depsgraph the tools' meshes and placements are read from.
    create : bool
        Make the surface object if the volume has none (the API does; handlers do not).
    force : bool
        Evaluate even when the surface already shows this stack (returns the result).
    extra : tuple, optional
        ``(kind, tool_obj, density)``: an entry to evaluate after the stored ones (not stored).

    Returns
    -------
    VolumeEVM or None
        The stack's result (None when nothing needed evaluating).

    Raises
    ------
    VolumeEVMError
        A bad tool (open mesh, wholly outside, not a mesh), an empty result, a missing
        sidecar. The surface keeps its last good mesh; ``stack_state(obj).problem`` says why.
    """
    timing = {"voxelize_s": 0.0, "voxelized": 0, "evaluate_s": 0.0, "recomputed": 0,
              "mesh_s": 0.0, "write_s": 0.0}
    start = time.perf_counter()
    with _exclusive():
        state = None
        try:
            state = stack_state(vol_obj)
            vevm = state.stack.base
            entries = _read_entries(vol_obj, vevm, depsgraph)
            if extra is not None:
                kind, tool_obj, density = extra
                entries.append(_read_entry(vol_obj, vevm, depsgraph, len(entries) + 1, kind,
                                           tool_obj, True, density))
            timing["read_s"] = time.perf_counter() - start
            signature = _signature(state, entries)
            surface = own_surface(vol_obj)
            shown = surface is not None and surface.volumeevm.stack_signature == signature
            if shown and not force and extra is None:
                state.problem = ""
                return None
            result = _evaluate(state, entries, timing)
            if extra is None and not shown:
                _write_surface(bpy.context, vol_obj, result, signature, timing, create=create)
        except _jobs.REPORTED_ERRORS as error:
            stack_problem(vol_obj, str(error))
            raise
        state.problem = ""
        timing["total_s"] = time.perf_counter() - start
        timing["voxels"] = result.voxel_count
        state.timing = timing
        return result


def stack_problem(obj, text):
    """Record a problem of a volume's tool stack (shown in the sidebar)."""
    _stack_state_of(volume_object(obj)).problem = text


def refresh_quietly(vol_obj, depsgraph):
    """:func:`refresh` for handlers: a problem is recorded (shown in the sidebar), not raised."""
    try:
        refresh(vol_obj, depsgraph)
    except _jobs.REPORTED_ERRORS as error:
        print(f"[volumeevm] {vol_obj.name}: {error}")
        return str(error)
    return ""


def entry_changed(vol_obj):
    """Update callback of a stack entry's fields: re-evaluate (unless the API is writing)."""
    if _busy or vol_obj is None or own_surface(vol_obj) is None:
        return
    refresh_quietly(vol_obj, bpy.context.evaluated_depsgraph_get())


def _commit_entry(vol_obj, kind, tool_obj, density):
    s = vol_obj.volumeevm
    entry = s.tools.add()
    _jobs.on_undo(functools.partial(s.tools.remove, len(s.tools) - 1))
    entry.operation = kind
    entry.tool = tool_obj if kind != "LARGEST" else None
    entry.use_density = density is not None
    entry.density = 0.0 if density is None else float(density)
    _jobs.assign(s, tool_index=len(s.tools) - 1)
    return entry


def add_tool(volume_obj, tool_obj, operation, density=None):
    """Add a tool operation to a volume's stack, evaluate it and refresh the surface mesh.

    Parameters
    ----------
    volume_obj : bpy.types.Object
        A volume object (or its surface) with a built VolumeEVM.
    tool_obj : bpy.types.Object or None
        A closed mesh object (modifiers applied); None for ``"largest"``. For ``"clip"`` its
        bounding box is the tool.
    operation : {"cut", "keep", "add", "largest", "clip"}
        Remove the tool's inside, keep only it, add it as material, keep the largest
        face-connected part, keep only the inside of the tool's bounding box.
    density : float, optional
        Density of added voxels (``"add"``), in data units; default: the region's largest.

    Returns
    -------
    VolumeEVM
        The stack's result (its mesh is now the surface object's, made if missing).

    Raises
    ------
    VolumeEVMError
        An open tool mesh (with its number of open edges), a tool wholly outside the volume,
        an empty result, a tool that is not a mesh or is the volume's own surface. Nothing is
        changed then.
    """
    vol_obj = volume_object(volume_obj)
    if operation not in TOOL_OPERATIONS:
        raise VolumeEVMError(f"operation must be one of {sorted(TOOL_OPERATIONS)}, "
                             f"got {operation!r}")
    kind = TOOL_OPERATIONS[operation]
    if kind != "LARGEST":
        problem = tool_problem(vol_obj, tool_obj)
        if problem:
            raise VolumeEVMError(f"{vol_obj.name}: {problem}")
    if density is not None and kind != "ADD":
        raise VolumeEVMError(f"density is for 'add' only, not {operation!r}")
    depsgraph = bpy.context.evaluated_depsgraph_get()
    refresh(vol_obj, depsgraph, extra=(kind, tool_obj, density))
    with _jobs.transaction():  # an error now (e.g. making the mesh) takes the entry back
        with _exclusive():
            _commit_entry(vol_obj, kind, tool_obj, density)
        return refresh(vol_obj, depsgraph, create=True, force=True)


def evaluate(obj):
    """Re-evaluate a volume's tool stack (tools as they are now) and refresh its surface mesh.

    Returns
    -------
    VolumeEVM
        The result; raises :class:`VolumeEVMError` (surface unchanged) if it cannot be made.
    """
    vol_obj = volume_object(obj)
    return refresh(vol_obj, bpy.context.evaluated_depsgraph_get(), create=True, force=True)


def remove_tool(obj, index):
    """Remove entry ``index`` (0-based) of the stack and refresh; returns the problem or "".

    A problem of the new stack (shown in the sidebar; the surface keeps its last good mesh) is
    returned with the entry removed; any other error puts the entry back and is raised.
    """
    vol_obj = volume_object(obj)
    s = vol_obj.volumeevm
    if not 0 <= index < len(s.tools):
        raise VolumeEVMError(f"{vol_obj.name}: no tool entry {index} (the stack has "
                             f"{len(s.tools)})")
    with _jobs.transaction():  # an unexpected error while refreshing puts the entry back
        with _exclusive():
            values = {p.identifier: getattr(s.tools[index], p.identifier)
                      for p in s.tools[index].bl_rna.properties if p.identifier != "rna_type"}
            s.tools.remove(index)
            _jobs.on_undo(functools.partial(_insert_entry, s, index, values))
            _jobs.assign(s, tool_index=max(0, min(s.tool_index, len(s.tools) - 1)))
        return refresh_quietly(vol_obj, bpy.context.evaluated_depsgraph_get())


def _insert_entry(settings, index, values):
    """Put a removed entry back at ``index`` (undoing :func:`remove_tool`)."""
    with _exclusive():
        entry = settings.tools.add()
        for name, value in values.items():
            setattr(entry, name, value)
        settings.tools.move(len(settings.tools) - 1, index)


def move_tool(obj, index, offset):
    """Move entry ``index`` by ``offset`` places (clamped) and refresh; returns the problem.

    As for :func:`remove_tool`: any error but a problem of the new stack moves the entry back.
    """
    vol_obj = volume_object(obj)
    s = vol_obj.volumeevm
    if not 0 <= index < len(s.tools):
        raise VolumeEVMError(f"{vol_obj.name}: no tool entry {index} (the stack has "
                             f"{len(s.tools)})")
    target = max(0, min(len(s.tools) - 1, index + int(offset)))
    with _jobs.transaction():  # an unexpected error while refreshing moves the entry back
        with _exclusive():
            s.tools.move(index, target)
            _jobs.on_undo(functools.partial(s.tools.move, target, index))
            _jobs.assign(s, tool_index=target)
        return refresh_quietly(vol_obj, bpy.context.evaluated_depsgraph_get())


def apply_stack(obj):
    """Make the tool stack permanent: its result becomes the volume's VolumeEVM.

    The result is written to a new sidecar file (the previous one stays, so undo can go back
    to it), ``vevm_path`` and the counts are updated and the stack is cleared; the surface
    already shows the result.

    Returns
    -------
    VolumeEVM
        The new VolumeEVM.
    """
    vol_obj = volume_object(obj)
    s = vol_obj.volumeevm
    if not len(s.tools):
        raise VolumeEVMError(f"{vol_obj.name}: the tool stack is empty; nothing to apply")
    result = refresh(vol_obj, bpy.context.evaluated_depsgraph_get(), create=True, force=True)
    with _exclusive():
        path = sidecar.save_new(s.uid, result)
        report = result.size_report()
        s.vevm_path = str(path)
        s.voxel_count = result.voxel_count
        s.ev_count = len(result.evm)
        s.vevm_bytes = report["total_bytes"]
        s.tools.clear()
        s.tool_index = 0
        surface = own_surface(vol_obj)
        if surface is not None:
            surface.volumeevm.stack_signature = ""  # it shows the (new) VolumeEVM itself
        state = stack_state(vol_obj)
        state.result = result
    return result


from .dvr import render_dvr, render_dvr_animation  # noqa: E402,F401  (Render VolumeEVM, see dvr)
