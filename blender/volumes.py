"""Import a volume, build its VolumeEVM, make its surface mesh: the jobs and their script calls.

Each task is a job (:mod:`.jobs`): the operators run it from a modal timer, the script functions
(:func:`import_volume`, :func:`build`, :func:`make_mesh`) run it to its end, so a script and a
button give the same objects.

- ``import_volume`` makes a *volume object*: a wire box around the grid, in physical
  millimetres scaled by :data:`BLENDER_UNITS_PER_MM` (1 mm = 0.001 BU), LPS axes = Blender X, Y, Z,
  object matrix identity. The dense array stays in a runtime cache (not in the .blend).
  An OME-Zarr store (a ``*.zarr`` folder) is never read whole: import reads its metadata and
  its coarsest level (for the histogram and the suggested threshold); the object keeps the
  store's path, its levels (``zarr_levels``, JSON) and the level, channel and time to build
  (``level`` and ``reader_options``), all saved in the .blend.
  A label map's label table goes on the object (:mod:`.label_table`), its threshold at the
  smallest label so that ``build`` holds every label.
- ``build`` makes the VolumeEVM of ``threshold <= density (<= upper)`` and keeps it in a sidecar
  ``.vevm`` file (see :mod:`.sidecar`), of the whole grid or of a box of it (``crop``: the
  bounds of an object, the volume object's ``crop_object`` by default, or voxel indices).
- ``make_mesh`` makes (or refreshes) the *surface object*: the VolumeEVM's boundary polygons,
  child of the volume object with identity matrices, so moving the box moves the surface.

Whatever the error, they leave the scene as it was.
"""

import dataclasses
import functools
import json
import math
import queue
import threading
from pathlib import Path
from typing import NamedTuple

import bpy
import numpy as np
from mathutils import Vector

from ..volumeevm_addon import (
    VolumeEVM,
    VolumeEVMError,
    density_histogram,
    otsu_threshold,
    read_volume,
    volume_levels,
)
from ..volumeevm_addon.model import BLENDER_UNITS_PER_MM, chunked_build_memory, index_to_physical
from . import jobs, runtime, sidecar
from .label_table import store_labels
from .meshes import fill_mesh, surface_geometry, wire_mesh
from .objects import attach_surface, link, require_enabled, volume_object
from .preview import Preview
from .tool_stack import refresh_quietly

_COMPOUND_ENDINGS = (".nii.gz",)

#: Histogram bins kept on a volume object (bpy.props vectors hold at most 32 items).
HISTOGRAM_BINS = 32


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


def zarr_store(path):
    """The OME-Zarr store (a folder named ``*.zarr``) ``path`` is or lies in, else None (a file
    picked inside a store in the file browser names the store)."""
    if not isinstance(path, (str, Path)) or not str(path):
        return None
    path = Path(path)
    return next((p for p in (path, *path.parents) if p.name.lower().endswith(".zarr")), None)


def get_volume(obj):
    """The dense volume of a volume object (runtime cache, else re-read from its source); for an
    OME-Zarr store's object, its picked level as a lazy volume (nothing read yet)."""
    obj = volume_object(obj)
    return jobs.drain(read_steps(obj.volumeevm.uid, *source_of(obj)), verbose=False)


def source_of(obj):
    """The path and reader options a volume object is read with (an OME-Zarr store's with the
    level picked on the object)."""
    settings = obj.volumeevm
    options = json.loads(settings.reader_options or "{}")
    if settings.zarr_levels:
        options["level"] = settings.level
    return settings.source_path, options


def _grid_box(shape, spacing, origin, orientation):
    """The 8 corners of the grid (lattice -0.5 .. shape - 0.5) in Blender units, and 12 edges."""
    corners = np.array([[i, j, k] for i in (0, 1) for j in (0, 1) for k in (0, 1)], np.float64)
    corners = corners * np.asarray(shape, np.float64) - 0.5
    matrix = index_to_physical(spacing, origin, orientation)
    points = (corners @ matrix[:3, :3].T + matrix[:3, 3]) * BLENDER_UNITS_PER_MM
    edges = [(a, b) for a in range(8) for b in range(a + 1, 8) if bin(a ^ b).count("1") == 1]
    return points, np.array(edges, np.int32)


# ---------------------------------------------------------------------------- import
def read_steps(uid, path, options):
    """Steps: the cached volume of ``uid`` or a fresh read of ``path``."""
    vol = runtime.volume(uid)
    if vol is None:
        if not path:
            raise VolumeEVMError("the volume has no source file to read it again from")
        yield 0.0, f"reading {Path(str(path)).name}"
        vol = read_volume(path, **options)
    return vol


def _import_steps(path, options, units):
    yield 0.0, f"reading {default_name(path)}"
    vol = read_volume(path, **options)
    file_units = vol.units
    if units is not None:
        vol = dataclasses.replace(vol, units=str(units))
    yield 0.7, "histogram"
    counts, lo, hi = density_histogram(vol.array, bins=HISTOGRAM_BINS)
    threshold = otsu_threshold(vol.array)
    return vol, file_units, counts, lo, hi, threshold


def _zarr_import_steps(path, options, units):
    """An OME-Zarr store's levels, geometry (metadata only) and its coarsest level's histogram,
    read chunk by chunk (a store without a pyramid has only its full level, which may be larger
    than memory)."""
    yield 0.0, f"reading the levels of {default_name(path)}"
    levels = volume_levels(path)
    vol = read_volume(path, **options)  # lazy: metadata only
    file_units = vol.units
    if units is not None:
        vol = dataclasses.replace(vol, units=str(units))
    for level in levels:
        folder = Path(path) / level["path"]
        level["disk_bytes"] = sum(f.stat().st_size for f in folder.rglob("*") if f.is_file())
    coarsest = levels[-1]["level"]
    yield 0.3, f"histogram of level {coarsest}"
    options = dict(options, level=coarsest)
    coarse = read_volume(path, **options).array
    counts, lo, hi = density_histogram(coarse, bins=HISTOGRAM_BINS)
    return vol, file_units, counts, lo, hi, otsu_threshold(coarse), levels


def import_job(context, path, *, name=None, units=None, **reader_options):
    """The import job: read ``path`` and make a volume object (see :func:`import_volume`)."""
    require_enabled()
    store = zarr_store(path)
    if store is not None:
        path = store
    if isinstance(path, (str, Path)):
        source = str(Path(path))
    else:
        files = [str(p) for p in path]
        if not files:
            raise VolumeEVMError("no files given")
        path, source = files, str(Path(files[0]).parent)
    json.dumps(reader_options)  # options must be plain values (they are stored as JSON)
    name = name or default_name(path)
    level = reader_options.pop("level", 0) if store is not None else 0

    def commit(result):
        vol, file_units, counts, lo, hi, threshold, *levels = result
        mesh = bpy.data.meshes.new(name)
        wire_mesh(mesh, *_grid_box(vol.shape, vol.spacing, vol.origin, vol.orientation))
        obj = bpy.data.objects.new(name, mesh)
        obj.display_type = "WIRE"
        obj.hide_render = True
        s = obj.volumeevm
        s.role = "VOLUME"
        s.uid = runtime.new_uid()
        s.source_path = source
        s.reader_options = json.dumps(reader_options)
        if levels:
            s.zarr_levels = json.dumps(levels[0])
            s.level = level
        s.shape = vol.shape
        s.spacing = vol.spacing
        s.origin = vol.origin
        s.orientation = np.asarray(vol.orientation, np.float64).ravel().tolist()
        s.spacing_known = vol.spacing_known
        s.label_count = len(vol.labels) if vol.is_label_map else 0
        s.units = vol.units
        s.file_units = file_units
        s.dtype = str(vol.array.dtype)
        s.value_min, s.value_max = lo, hi
        s.histogram = counts.tolist()
        s.threshold = threshold
        s.upper = hi
        if vol.is_label_map:
            store_labels(obj, vol.labels)
            if vol.labels:  # Build's region holds every label
                s.threshold = min(vol.labels)
        link(context, obj)
        if not levels:  # a store's levels are read chunk by chunk when built, never kept
            runtime.put_volume(s.uid, vol)
        runtime.forget_except({o.volumeevm.uid for o in bpy.data.objects})
        return obj

    if store is not None:
        steps = _zarr_import_steps(path, dict(reader_options, level=level), units)
    else:
        steps = _import_steps(path, reader_options, units)
    return jobs.Job(f"Import {name}", steps, commit)


def import_volume(path, *, name=None, units=None, **reader_options):
    """Read a volume file (or DICOM folder / list of files) and make a volume object.

    Parameters
    ----------
    path : str, Path or sequence of str
        A file with a supported extension, a DICOM folder, the files of one DICOM series, or an
        OME-Zarr store (a ``*.zarr`` / ``*.ome.zarr`` folder, or a file in it): only its
        metadata and coarsest level are read; Build reads the object's ``level`` chunk by
        chunk.
    name : str, optional
        Object name (default: the file's stem).
    units : str, optional
        The data's units (e.g. ``"HU"``) when the file does not say them, or says them wrongly
        (default: as the file says). Stored as ``obj.volumeevm.units`` beside what the file
        said (``file_units``); the Volume panel shows and edits them.
    **reader_options
        Passed to :func:`volumeevm_addon.read_volume` (raw: ``shape``, ``dtype``, ...; OME-Zarr:
        ``level`` (the level to build, default 0, stored as ``obj.volumeevm.level``),
        ``channel``, ``time``).

    Returns
    -------
    bpy.types.Object
        The volume object (wire box, ``obj.volumeevm.role == "VOLUME"``), active and selected.

    Raises
    ------
    VolumeEVMError
        An unsupported or unreadable volume, bad reader options, the extension not enabled
        (``OSError`` for a file that cannot be read at all).
    """
    return jobs.run(import_job(bpy.context, path, name=name, units=units, **reader_options))


def region_fraction(settings):
    """The share of voxels in the object's density interval, by its stored histogram (bins'
    counts taken in proportion to their overlap with the interval); an estimate."""
    counts = np.asarray(settings.histogram, np.float64)
    if counts.sum() == 0:
        return 1.0
    upper = settings.upper if settings.use_upper else np.inf
    edges = np.linspace(settings.value_min, settings.value_max, len(counts) + 1)
    if edges[-1] == edges[0]:
        return float(settings.threshold <= edges[0] <= upper)
    overlap = (np.minimum(edges[1:], upper) - np.maximum(edges[:-1], settings.threshold))
    share = np.clip(overlap / (edges[1] - edges[0]), 0.0, 1.0)
    return float((counts * share).sum() / counts.sum())


def zarr_levels(obj):
    """The OME-Zarr levels of a store's volume object (empty for other sources), finest first:
    dicts of :func:`volumeevm_addon.volume_levels` with ``disk_bytes`` (its chunk files) and
    ``build_bytes``, the core's estimate of what building it needs
    (:func:`volumeevm_addon.model.chunked_build_memory`), the region's voxels estimated from the
    coarsest level's histogram at the object's threshold."""
    s = volume_object(obj).volumeevm
    levels = json.loads(s.zarr_levels or "[]")
    fraction = region_fraction(s)
    for level in levels:
        voxels = round(fraction * math.prod(level["shape"]))
        level["build_bytes"] = chunked_build_memory(level["chunks"], level["dtype"], voxels)
    return levels


# ---------------------------------------------------------------------------- build
class _Cancelled(Exception):
    """Raised in a build's progress callback once its steps were closed (Esc)."""


def _chunk_steps(vol, threshold, upper, crop, start, end, every_chunk):
    """Steps of ``VolumeEVM.from_volume`` run in a helper thread: ``(fraction, "building EVM:
    chunk n of N")`` as each chunk ends (an in-memory volume is one chunk), fractions from
    ``start`` to ``end``; returns the VolumeEVM, or raises the build's error.

    With ``every_chunk`` (under ``--background``, one progress line each) every chunk is a step;
    otherwise a step shows the latest chunk ended (the UI's timer takes one step per tick, and
    must not lag behind a fast build). Closing the generator (Esc) stops the build at its next
    chunk and waits for it: nothing of it is left running.
    """
    events = queue.Queue()
    closed = threading.Event()

    def progress(done, total):
        if closed.is_set():
            raise _Cancelled
        events.put(("chunk", (done, total)))

    def build():
        try:
            events.put(("done", VolumeEVM.from_volume(vol, threshold, upper, crop=crop,
                                                      progress=progress)))
        except BaseException as error:  # noqa: BLE001 - handed to the steps' thread
            events.put(("error", error))

    helper = threading.Thread(target=build, name="volumeevm-build", daemon=True)
    helper.start()
    try:
        while True:
            kind, value = events.get()
            while not every_chunk and kind == "chunk" and not events.empty():
                kind, value = events.get()
            if kind == "done":
                return value
            if kind == "error":
                raise value
            done, total = value
            yield start + (end - start) * done / total, f"building EVM: chunk {done} of {total}"
    finally:
        closed.set()
        helper.join()


def _preview_steps(name, path, options, coarsest, threshold, upper):
    """While a job runs from the UI and a store's level finer than its coarsest builds, build
    the coarsest level (in memory: it is small) and hand its surface's edges to the viewport
    (:mod:`.preview`). No preview when its region is empty or its chunks cannot be read (the
    build itself then says what is wrong)."""
    if coarsest is None or options["level"] >= coarsest or not jobs.wants_preview():
        return
    yield 0.05, f"preview from level {coarsest}"
    try:
        coarse = read_volume(path, **dict(options, level=coarsest))
        vevm = VolumeEVM.from_volume(dataclasses.replace(coarse, array=np.asarray(coarse.array)),
                                     threshold, upper)
    except VolumeEVMError:
        return
    vertices, polygons = vevm.mesh()
    co = (vertices * BLENDER_UNITS_PER_MM).astype(np.float32)
    jobs.show_preview(Preview(name, coarsest, co, polygons.unique_edges()[0]))


class CropBounds(NamedTuple):
    """A build's crop given as physical bounds (LPS mm), made voxel indices once the grid
    is read."""

    lo_mm: np.ndarray
    hi_mm: np.ndarray


def crop_bounds(vol_obj, crop_obj):
    """The box, in the volume's physical frame (LPS mm), that encloses ``crop_obj``'s bounding
    box: its 8 corners placed in the world, the volume object's placement undone, Blender units
    made mm. With the volume object unmoved (its import placement) it is the object's world
    bounds; the core's ``Volume.index_box`` turns it into voxel indices."""
    try:
        to_volume = vol_obj.matrix_world.inverted() @ crop_obj.matrix_world
    except ValueError as error:  # mathutils: a scale of 0
        raise VolumeEVMError(f"crop: {vol_obj.name}'s placement cannot be inverted") from error
    corners = np.array([tuple(to_volume @ Vector(c)) for c in crop_obj.bound_box], np.float64)
    corners /= BLENDER_UNITS_PER_MM
    return CropBounds(corners.min(axis=0), corners.max(axis=0))


def _build_steps(uid, path, options, threshold, upper, crop, every_chunk, preview):
    """Read the volume (unless cached) and build it; ``crop`` is None (the whole grid), a box
    of voxel indices, or :class:`CropBounds` made voxel indices in the grid read."""
    yield from preview
    vol = yield from read_steps(uid, path, options)
    if isinstance(crop, CropBounds):
        crop = vol.index_box(crop.lo_mm, crop.hi_mm)
    yield 0.3, "building EVM"
    vevm = yield from _chunk_steps(vol, threshold, upper, crop, 0.3, 0.9, every_chunk)
    yield 0.9, "saving VolumeEVM"
    return vol, vevm


def build_job(obj, threshold=None, upper=None, crop=None):
    """The build job (see :func:`build`)."""
    obj = volume_object(obj)
    s = obj.volumeevm
    crop = s.crop_object if crop is None else crop
    if isinstance(crop, bpy.types.Object):
        crop = crop_bounds(obj, crop)
    if threshold is None:
        threshold = s.threshold
        upper = s.upper if s.use_upper else None
    threshold = float(threshold)
    upper = None if upper is None else float(upper)
    if upper is not None and upper < threshold:
        raise VolumeEVMError(f"{obj.name}: upper bound {upper} is below the threshold {threshold}")
    name, uid = obj.name, s.uid
    path, options = source_of(obj)

    def commit(result):
        vol, vevm = result
        target = bpy.data.objects.get(name)
        if target is None:
            raise VolumeEVMError(f"{name}: the volume object was deleted while building")
        report = vevm.size_report()
        file = sidecar.save_new(uid, vevm)
        jobs.on_undo(functools.partial(file.unlink, missing_ok=True))
        values = dict(threshold=threshold, use_upper=upper is not None,
                      built_threshold=threshold, built_use_upper=upper is not None,
                      built_upper=upper if upper is not None else 0.0,
                      voxel_count=vevm.voxel_count, ev_count=len(vevm.evm),
                      vevm_bytes=report["total_bytes"], dense_bytes=report["dense_bytes"],
                      vevm_path=str(file), built_level=options.get("level", 0))
        if upper is not None:
            values["upper"] = upper
        jobs.assign(target.volumeevm, **values)
        jobs.on_undo(functools.partial(runtime.set_status, uid, runtime.status(uid)))
        runtime.set_status(uid, "")
        if "level" not in options:  # a store's level is read chunk by chunk, never kept
            runtime.put_volume(uid, vol)
        return vevm

    at = f" (level {options['level']})" if "level" in options else ""
    coarsest = len(json.loads(s.zarr_levels)) - 1 if s.zarr_levels else None
    preview = _preview_steps(name, path, options, coarsest, threshold, upper)
    steps = _build_steps(uid, path, options, threshold, upper, crop, bpy.app.background,
                         preview)
    return jobs.Job(f"Build VolumeEVM of {name}{at}", steps, commit)


def build(obj, threshold=None, upper=None, crop=None):
    """Build the VolumeEVM of a volume object at ``threshold <= density (<= upper)``.

    Parameters
    ----------
    obj : bpy.types.Object
        A volume object (or its surface).
    threshold, upper : float, optional
        In the data's own units; default: the object's ``volumeevm.threshold`` (and ``upper``
        when ``use_upper`` is set). Stored on the object.
    crop : bpy.types.Object or sequence of 3 (int, int) pairs, optional
        Build only a region of interest: the voxels whose cells meet an object's bounds (its
        bounding box in the volume's frame, :func:`crop_bounds`), or a box of voxel indices
        ``((i0, i1), (j0, j1), (k0, k1))`` (half-open, along x, y, z; of the level built for an
        OME-Zarr store). Default: the object's ``volumeevm.crop_object`` (the build panel's
        Crop To), else the whole grid. The VolumeEVM's grid is the box, each voxel where it
        sat (``VolumeEVM.from_volume``'s ``crop``); only the box is read and held.

    The build runs chunk by chunk for a lazy volume (an OME-Zarr store's object builds its
    ``volumeevm.level``, never reading the store whole), a progress step after each chunk.
    Run from the UI (the Build button), a store's level finer than its coarsest shows the
    coarsest level's surface edges in the viewport until the build ends (:mod:`.preview`).

    Returns
    -------
    VolumeEVM
        Also saved to a sidecar file whose path is ``obj.volumeevm.vevm_path``.

    Raises
    ------
    VolumeEVMError
        Not a volume object, an upper bound below the threshold, an empty region, a crop that
        misses the grid or is not a box of voxel indices (naming ``crop``), a source file that
        is gone, a store's chunk that cannot be read (naming store, level and chunk), not
        enough memory.
    """
    return jobs.run(build_job(obj, threshold, upper, crop))


# ---------------------------------------------------------------------------- mesh
def _mesh_steps(vevm_or_path, manifold, smooth):
    if isinstance(vevm_or_path, VolumeEVM):
        vevm = vevm_or_path
    else:
        yield 0.0, "loading VolumeEVM"
        vevm = VolumeEVM.load(vevm_or_path)
    yield 0.2, "meshing"
    co, faces, _ = surface_geometry(vevm, manifold=manifold, smooth=smooth)
    yield 0.9, "making the mesh object"
    return vevm, co, faces


def mesh_job(context, obj, manifold=False, smooth=False):
    """The make-mesh job (see :func:`make_mesh`)."""
    vol_obj = volume_object(obj)
    s = vol_obj.volumeevm
    if not s.vevm_path:
        raise VolumeEVMError(f"{vol_obj.name}: no VolumeEVM built yet; build one first")
    path = sidecar.resolve(vol_obj)
    if path is None:
        raise VolumeEVMError(
            f"{vol_obj.name}: VolumeEVM file {s.vevm_path!r} not found; build it again")
    cached = runtime.vevm(path)
    name = vol_obj.name

    def commit(result):
        vevm, co, faces = result
        runtime.put_vevm(path, vevm)
        owner = bpy.data.objects.get(name)
        if owner is None:
            raise VolumeEVMError(f"{name}: the volume object was deleted while meshing")
        mesh = bpy.data.meshes.new(f"{name}_surface")
        fill_mesh(mesh, co, faces, smooth=smooth)
        surface = attach_surface(context, owner, mesh)
        jobs.assign(surface.volumeevm, stack_signature="")
        if len(owner.volumeevm.tools):
            # The surface shows the tool stack's result, not the bare VolumeEVM.
            refresh_quietly(owner, context.evaluated_depsgraph_get())
        return surface

    steps = _mesh_steps(cached if cached is not None else path, manifold, smooth)
    return jobs.Job(f"Mesh of {name}", steps, commit)


def make_mesh(obj, manifold=False, smooth=False):
    """Make (or refresh) the surface mesh object of a volume's VolumeEVM.

    With ``manifold`` the mesh is the one for 3D printing (``vevm.mesh(manifold=True)``):
    every edge with two faces, every vertex one fan. With ``smooth`` it is the smooth display
    surface (``vevm.mesh(manifold, smooth=True)``: every vertex within half a voxel of the
    exact boundary), shaded smooth. A tool stack's refresh shows its result's exact mesh.

    Returns
    -------
    bpy.types.Object
        The surface object: polygons of the VolumeEVM's boundary (vertices in Blender units,
        ``vevm.mesh()`` times 0.001), child of the volume object, identity matrices.

    Raises
    ------
    VolumeEVMError
        Not a volume object, no VolumeEVM built yet, a sidecar file that is gone.
    """
    return jobs.run(mesh_job(bpy.context, obj, manifold, smooth))
