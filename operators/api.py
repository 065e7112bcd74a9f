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

Errors: bad input raises :class:`VolumeEVMError` (and ``OSError`` for unreadable files).
Under ``blender --background`` progress lines ``[volumeevm] 42% building EVM`` are printed.
"""

import json
from pathlib import Path

import bpy
import numpy as np

from ..volumeevm_addon import BLENDER_UNITS_PER_MM, VolumeEVM, VolumeEVMError, read_volume
from ..volumeevm_addon._volume import index_to_physical
from . import _jobs, _runtime, sidecar

__all__ = ["import_volume", "build", "make_mesh", "volume_object", "get_vevm", "get_volume"]

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
        _runtime.put_volume(s.uid, vol)
        _link(context, obj)
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
        file = sidecar.save_new(uid, vevm)
        _runtime.put_volume(uid, vol)
        t = target.volumeevm
        report = vevm.size_report()
        t.threshold = threshold
        t.use_upper = upper is not None
        if upper is not None:
            t.upper = upper
        t.built_threshold = threshold
        t.built_use_upper = upper is not None
        t.built_upper = upper if upper is not None else 0.0
        t.voxel_count = vevm.voxel_count
        t.ev_count = len(vevm.evm)
        t.vevm_bytes = report["total_bytes"]
        t.dense_bytes = report["dense_bytes"]
        t.vevm_path = str(file)
        _runtime.set_status(uid, "")
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


def fill_mesh(mesh, co, polys):
    """Fill an empty mesh in bulk: vertices ``co`` (n, 3) and polygons (loops, starts)."""
    mesh.vertices.add(len(co))
    mesh.vertices.foreach_set("co", np.ascontiguousarray(co, np.float32).ravel())
    mesh.loops.add(len(polys.indices))
    mesh.loops.foreach_set("vertex_index", np.ascontiguousarray(polys.indices, np.int32))
    mesh.polygons.add(len(polys))
    mesh.polygons.foreach_set("loop_start", np.ascontiguousarray(polys.starts, np.int32))
    # Flat faces: a voxel boundary has no smooth normals (new meshes shade smooth since 4.1).
    mesh.polygons.foreach_set("use_smooth", np.zeros(len(polys), bool))
    mesh.update(calc_edges=True)


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
        surface = owner.volumeevm.surface
        # Refresh the owner's own surface (a duplicated volume still points at the original's).
        if (surface is not None and surface.type == "MESH"
                and surface.volumeevm.volume == owner):
            old = surface.data
            for material in old.materials:
                mesh.materials.append(material)
            surface.data = mesh
            if old.users == 0:
                bpy.data.meshes.remove(old)
        else:
            surface = bpy.data.objects.new(f"{name}_surface", mesh)
            surface.volumeevm.role = "SURFACE"
            surface.volumeevm.volume = owner
            surface.parent = owner
            owner.volumeevm.surface = surface
            _link(context, surface)
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
