"""The tool stack runtime: a volume's non-destructive stack of CAD tools, evaluated and shown live.

Each volume object keeps an ordered list of entries (``Object.volumeevm.tools``: tool object,
operation, enabled, density). :func:`add_tool`, :func:`evaluate`, :func:`remove_tool`,
:func:`move_tool` and :func:`apply_stack` are what the operators and scripts call; the kinds of
entry are :data:`TOOL_KINDS`, the one table the properties, panels and operators are made from.

Refreshing. :func:`refresh` reads the entries and their tools from the evaluated depsgraph,
voxelizes each tool again only if its triangles or placement changed (a cache keyed by a digest
of both), lets the core's ``EditStack`` recompute from the first changed entry (in place, where
the moved tool's old and new voxels differ), updates the core's mesh of the last result where
the results differ and rewrites the surface mesh in place (all or nothing: if writing fails,
its old geometry is put back). The
surface stores a signature of the base and entries it shows; when nothing changed (e.g. the
update was our own mesh write, or a property of the volume unrelated to the stack) nothing is
written, so there is no feedback loop. A failure (tool moved wholly outside, open mesh, empty
result) is recorded as the stack's problem, shown in the sidebar, and the last good mesh stays.

Live updates. ``depsgraph_update_post`` looks for transform or geometry updates of a stack's tool
objects (or their meshes) and of the volume object itself, and refreshes that volume's stack.
Property changes do not reach that handler by themselves: editing an entry's field only marks
its volume and tags it for the depsgraph (:func:`entry_changed`, cheap enough for every edit),
so the next depsgraph update refreshes it through the same handler, or a script asking for the
stack first (:func:`stack_state`, :func:`evaluate`) gets it refreshed at once. Handlers never
raise. While the API evaluates or writes, the handlers stay out (:func:`is_busy`).

Label maps. A volume whose labels are mesh objects (Make Label Meshes, one object per label)
applies its stack to the label set as a whole, with the core's :class:`LabelSet` edits: a cut
removes the tool's voxels from every label, Keep Inside and Clip to Box keep every label's
voxels inside the tool, Add gives them to the entry's ``label`` (taking them from the others),
Keep Largest Part keeps each label's largest part. The base is the label set of the volume's
file (no VolumeEVM build needed); the same calls, handlers and undo drive it, and each label
object's mesh is rewritten only when it changed (a label the stack empties keeps its object,
with no faces). The label meshes are made together (:meth:`LabelSet.meshes`: where labels touch,
their polygons are the same), so a label's mesh changes too when a neighbour's region does.
Apply is for one region only.

Undo and redo restore the entries, ``vevm_path`` and the surface mesh with its signature;
``undo_post`` / ``redo_post`` re-sync the runtime stacks from those properties (a new
``EditStack`` when the base path changed) and rewrite the mesh only if it does not match.
"""

import functools
import hashlib
import time
import traceback
from contextlib import contextmanager
from dataclasses import dataclass

import bpy
import numpy as np

from ..volumeevm_addon import EVM, LabelSet, VolumeEVM, VolumeEVMError
from ..volumeevm_addon.model import (
    EditStack,
    Polygons,
    ToolOperation,
    box_evm,
    tool_to_grid,
    voxelize_mesh_evm,
)
from . import jobs, runtime, sidecar, volumes
from .meshes import (
    BOX_FACES,
    Faces,
    fill_mesh,
    label_geometry,
    refill_mesh,
    sizes,
    surface_geometry,
    tool_triangles,
)
from .objects import attach_surface, own_surface, volume_object


# ---------------------------------------------------------------------------- kinds of entry
@dataclass(frozen=True)
class ToolKind:
    """One kind of tool stack entry, as every part of the add-on names it."""

    identifier: str  # the entry's ``operation`` (stored in the .blend)
    name: str  # the script API's name (``add_tool(..., "cut")``) and the operator's suffix
    core: str  # the core's ``ToolOperation.operation`` (a clip box is a "keep" with a box)
    label: str
    description: str
    icon: str


#: Every kind of entry, in the order the sidebar shows them.
TOOL_KINDS = (
    ToolKind("CUT", "cut", "cut", "Cut", "Remove the material inside the tool", "REMOVE"),
    ToolKind("KEEP", "keep", "keep", "Keep Inside", "Keep only the material inside the tool",
             "SELECT_INTERSECT"),
    ToolKind("ADD", "add", "add", "Add", "Add the tool's inside as material with a density",
             "ADD"),
    ToolKind("LARGEST", "largest", "largest", "Keep Largest Part",
             "Keep only the largest face-connected part", "STICKY_UVS_LOC"),
    ToolKind("CLIP", "clip", "keep", "Clip to Box",
             "Keep only the material inside the tool's bounding box", "MOD_WIREFRAME"),
)
#: Entry operation -> its kind.
KINDS = {kind.identifier: kind for kind in TOOL_KINDS}
#: The script API's operation names -> their kinds.
KINDS_BY_NAME = {kind.name: kind for kind in TOOL_KINDS}

#: The tool of a disabled entry: skipped by the stack, so it is never voxelized.
_SKIPPED = EVM()


# ---------------------------------------------------------------------------- busy, waiting
_busy = False  # True while the API evaluates or writes: the handlers stay out


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


_waiting = set()  # (uid, name) of volumes whose entries changed since their last refresh


def _waiting_key(vol_obj):
    return vol_obj.volumeevm.uid, vol_obj.name


# ---------------------------------------------------------------------------- entries
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


def voxelize_tool(vertices, faces, to_grid, shape):
    """The EVM of a tool's voxels (the core's :func:`voxelize_mesh_evm`); a clip box that is
    axis-aligned in the grid is made from its corners directly (:func:`box_evm`)."""
    matrix = np.asarray(to_grid, np.float64)
    linear = matrix[:3, :3]
    if faces is BOX_FACES and np.count_nonzero(linear - np.diag(np.diag(linear))) == 0:
        corners = np.asarray(vertices, np.float64) @ linear.T + matrix[:3, 3]
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

    def __init__(self, number, kind, enabled, density, tool_name, mesh, label=0):
        self.number, self.kind, self.enabled = number, kind, enabled
        self.density, self.tool_name, self.mesh = density, tool_name, mesh
        self.to_label = label  # Add on a label set: the label that gets the voxels
        self.digest = "" if mesh is None else _digest(*mesh)

    @property
    def label(self):
        what = self.kind.label
        return f"{what} with {self.tool_name}" if self.tool_name else what

    def key(self):
        return (f"{self.kind.identifier}:{int(self.enabled)}:{self.density!r}:{self.to_label}:"
                f"{self.digest}")


def _read_entry(vol_obj, vevm, depsgraph, number, operation, tool_obj, enabled, density, label=0):
    """An :class:`_Entry` (reading the tool's evaluated mesh); raises for a bad tool."""
    kind = KINDS.get(operation)
    if kind is None:
        raise VolumeEVMError(f"unknown tool operation {operation!r}")
    density = float(density) if kind.identifier == "ADD" and density is not None else None
    if kind.identifier == "LARGEST" or not enabled:
        name = "" if tool_obj is None or kind.identifier == "LARGEST" else tool_obj.name
        return _Entry(number, kind, enabled, density, name, None, label)
    if tool_obj is None:
        raise VolumeEVMError(f"entry {number} ({kind.label}): it has no tool object "
                             f"(deleted?); choose one or remove the entry")
    problem = tool_problem(vol_obj, tool_obj)
    if problem:
        raise VolumeEVMError(f"entry {number} ({kind.label}): {problem}")
    volume_matrix = np.array(
        (vol_obj if depsgraph is None else vol_obj.evaluated_get(depsgraph)).matrix_world)
    vertices, faces, matrix = tool_triangles(tool_obj, depsgraph, box=kind.identifier == "CLIP")
    to_grid = tool_to_grid(matrix, vevm.spacing, vevm.origin, vevm.orientation,
                           matrix_world=volume_matrix)
    return _Entry(number, kind, enabled, density, tool_obj.name,
                  (vertices, faces, to_grid, np.asarray(vevm.shape)), label)


def _read_entries(vol_obj, vevm, depsgraph):
    entries = []
    for number, e in enumerate(vol_obj.volumeevm.tools, 1):
        entries.append(_read_entry(vol_obj, vevm, depsgraph, number, e.operation, e.tool,
                                   e.enabled, e.density if e.use_density else None, e.label))
    return entries


def _signature(state, entries):
    """What the surface shows: "" for the bare VolumeEVM, else a digest of base and entries."""
    if not entries:
        return ""
    text = "|".join([state.base_digest, *(e.key() for e in entries)])
    return hashlib.blake2b(text.encode(), digest_size=16).hexdigest()


# ---------------------------------------------------------------------------- state, evaluation
def _stack_state_of(vol_obj):
    """The runtime stack state of a volume object (an empty one made on first use)."""
    uid = vol_obj.volumeevm.uid
    state = runtime.stack_state(uid, vol_obj.name)
    if state is None:
        state = runtime.StackState()
        runtime.put_stack_state(uid, vol_obj.name, state)
    return state


def _synced_state(vol_obj):
    """The stack state of a volume object, re-synced to its base (see :func:`stack_state`)."""
    state = _stack_state_of(vol_obj)
    base = sidecar.load_vevm(vol_obj)
    path = str(sidecar.resolve(vol_obj))
    if state.stack is None or state.base_path != path or state.stack.base is not base:
        state.base_path = path
        state.base_digest = _base_digest(base)
        state.stack = EditStack(base)
        state.result = state.shown = None
    return state


def stack_state(obj):
    """The runtime state of a volume's tool stack (made, or re-synced, from its properties).

    The stack's base is the VolumeEVM of ``volumeevm.vevm_path``; when that path changed (a
    build, Apply, or undo/redo restoring another path) a new ``EditStack`` starts from it.
    Entries changed since the last refresh are evaluated first (see :func:`entry_changed`).
    """
    vol_obj = volume_object(obj)
    if _waiting_key(vol_obj) in _waiting:
        _refresh_safely(vol_obj, bpy.context.evaluated_depsgraph_get())
    return _stack_state_of(vol_obj) if label_objects(vol_obj) else _synced_state(vol_obj)


def _operation(state, entry, timing):
    """The core's ToolOperation for an entry, voxelizing its tool unless it is cached."""
    core = entry.kind.core
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


def _write_surface(context, state, vol_obj, result, signature, timing, *, create):
    """Put the result's mesh into the volume's surface (in place), or make the surface.

    The core's mesh of the last result written is updated where the regions differ
    (:func:`.meshes.surface_geometry`); when they do not (a tool moved by less than changes a
    voxel), the mesh is not written again. All or nothing: if writing fails, the surface keeps
    its old mesh (or none is made): the arrays written last, while the surface still shows them
    (same signature and sizes), else its mesh read back.
    """
    surface = own_surface(vol_obj)
    if surface is None and not create:
        return None
    start = time.perf_counter()
    shown, old_co, old_faces, old_boundary = state.shown or (None, None, None, None)
    co, faces, boundary = surface_geometry(
        result, None if old_boundary is None else (old_co, old_boundary))
    middle = time.perf_counter()
    with jobs.transaction():
        if surface is None:
            mesh = bpy.data.meshes.new(f"{vol_obj.name}_surface")
            fill_mesh(mesh, co, faces)
            surface = attach_surface(context, vol_obj, mesh)
        else:
            old = None
            if (shown == surface.volumeevm.stack_signature
                    and (len(old_co), *old_faces.sizes()) == sizes(surface.data)):
                old = old_co, old_faces
            if old is None or boundary is not old_boundary:
                refill_mesh(surface.data, co, faces, old)
        jobs.assign(surface.volumeevm, stack_signature=signature)
    state.shown = signature, co, faces, boundary
    end = time.perf_counter()
    timing["mesh_s"], timing["write_s"] = middle - start, end - middle
    timing["polygons"] = len(faces.polygons)
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
        ``(kind, tool_obj, density, label)``: an entry to evaluate after the stored ones (not
        stored); ``kind`` is an entry operation (``"CUT"``, ...).

    Returns
    -------
    VolumeEVM, LabelSet or None
        The stack's result (a LabelSet for a volume with label objects, see the module
        docstring); None when nothing needed evaluating.

    Raises
    ------
    VolumeEVMError
        A bad tool (open mesh, wholly outside, not a mesh), an empty result, a missing
        sidecar. The surface keeps its last good mesh; ``stack_state(obj).problem`` says why.
    """
    timing = {"voxelize_s": 0.0, "voxelized": 0, "evaluate_s": 0.0, "recomputed": 0,
              "mesh_s": 0.0, "write_s": 0.0}
    start = time.perf_counter()
    if extra is None:
        _waiting.discard(_waiting_key(vol_obj))  # the entries are read as they are now
    with _exclusive():
        state = None
        try:
            if label_objects(vol_obj):
                state = _stack_state_of(vol_obj)
                result = _refresh_labels(vol_obj, state, depsgraph, extra, force, timing)
                state.problem = ""
                if result is None:
                    return None
                timing["total_s"] = time.perf_counter() - start
                timing["voxels"] = sum(region.voxel_count for region in result.values())
                state.timing = timing
                return result
            state = _synced_state(vol_obj)
            vevm = state.stack.base
            entries = _read_entries(vol_obj, vevm, depsgraph)
            if extra is not None:
                entries.append(_read_entry(vol_obj, vevm, depsgraph, len(entries) + 1, *extra[:2],
                                           True, *extra[2:]))
            timing["read_s"] = time.perf_counter() - start
            signature = _signature(state, entries)
            surface = own_surface(vol_obj)
            shown = surface is not None and surface.volumeevm.stack_signature == signature
            if shown and not force and extra is None:
                state.problem = ""
                return None
            result = _evaluate(state, entries, timing)
            if extra is None and not shown:
                _write_surface(bpy.context, state, vol_obj, result, signature, timing,
                               create=create)
        except jobs.REPORTED_ERRORS as error:
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
    except jobs.REPORTED_ERRORS as error:
        print(f"[volumeevm] {vol_obj.name}: {error}")
        return str(error)
    return ""


def _refresh_safely(obj, depsgraph):
    """Refresh one volume from a handler; never raises (the problem shows in the sidebar)."""
    try:
        refresh_quietly(obj, depsgraph)
    except Exception as error:  # noqa: BLE001 - a handler must not raise; keep the last mesh
        traceback.print_exc()
        stack_problem(obj, f"unexpected error while refreshing: {error!r}")


# ---------------------------------------------------------------------------- changed entries
def entry_changed(vol_obj):
    """Update callback of a stack entry's fields: mark the volume's stack for a refresh.

    Cheap, so editing a field never waits for an evaluation: the volume object is tagged for
    the depsgraph, whose next update refreshes it (:func:`on_depsgraph_update_post`), unless a
    script asks for the stack first. Nothing is marked while the API writes entries itself, or
    when the volume has no surface to show the result.
    """
    if _busy or vol_obj is None or (own_surface(vol_obj) is None and not label_objects(vol_obj)):
        return
    _waiting.add(_waiting_key(vol_obj))
    vol_obj.update_tag(refresh={"OBJECT"})


# ---------------------------------------------------------------------------- script API
def _commit_entry(vol_obj, kind, tool_obj, density, label):
    s = vol_obj.volumeevm
    entry = s.tools.add()
    entry.label = label
    jobs.on_undo(functools.partial(s.tools.remove, len(s.tools) - 1))
    entry.operation = kind.identifier
    entry.tool = tool_obj if kind.identifier != "LARGEST" else None
    entry.use_density = density is not None
    entry.density = 0.0 if density is None else float(density)
    jobs.assign(s, tool_index=len(s.tools) - 1)
    return entry


def add_tool(volume_obj, tool_obj, operation, density=None, *, label=0):
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
    label : int, optional
        ``"add"`` on a label map's label objects: the label that gets the voxels (required).

    Returns
    -------
    VolumeEVM or LabelSet
        The stack's result (its mesh is now the surface object's, made if missing; for a
        volume with label objects the label set, each label's mesh now its object's).

    Raises
    ------
    VolumeEVMError
        An open tool mesh (with its number of open edges), a tool wholly outside the volume,
        an empty result, a tool that is not a mesh or is the volume's own surface. Nothing is
        changed then.
    """
    vol_obj = volume_object(volume_obj)
    kind = KINDS_BY_NAME.get(operation)
    if kind is None:
        raise VolumeEVMError(f"operation must be one of {sorted(KINDS_BY_NAME)}, "
                             f"got {operation!r}")
    if kind.identifier != "LARGEST":
        problem = tool_problem(vol_obj, tool_obj)
        if problem:
            raise VolumeEVMError(f"{vol_obj.name}: {problem}")
    if density is not None and kind.identifier != "ADD":
        raise VolumeEVMError(f"density is for 'add' only, not {operation!r}")
    if label and kind.identifier != "ADD":
        raise VolumeEVMError(f"label is for 'add' only, not {operation!r}")
    depsgraph = bpy.context.evaluated_depsgraph_get()
    refresh(vol_obj, depsgraph, extra=(kind.identifier, tool_obj, density, label))
    with jobs.transaction():  # an error now (e.g. making the mesh) takes the entry back
        with _exclusive():
            _commit_entry(vol_obj, kind, tool_obj, density, label)
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


def _checked_index(vol_obj, index):
    count = len(vol_obj.volumeevm.tools)
    if not 0 <= index < count:
        raise VolumeEVMError(f"{vol_obj.name}: no tool entry {index} (the stack has {count})")
    return index


def remove_tool(obj, index):
    """Remove entry ``index`` (0-based) of the stack and refresh; returns the problem or "".

    A problem of the new stack (shown in the sidebar; the surface keeps its last good mesh) is
    returned with the entry removed; any other error puts the entry back and is raised.
    """
    vol_obj = volume_object(obj)
    s = vol_obj.volumeevm
    index = _checked_index(vol_obj, index)
    with jobs.transaction():  # an unexpected error while refreshing puts the entry back
        with _exclusive():
            values = {p.identifier: getattr(s.tools[index], p.identifier)
                      for p in s.tools[index].bl_rna.properties if p.identifier != "rna_type"}
            s.tools.remove(index)
            jobs.on_undo(functools.partial(_insert_entry, s, index, values))
            jobs.assign(s, tool_index=max(0, min(s.tool_index, len(s.tools) - 1)))
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
    index = _checked_index(vol_obj, index)
    target = max(0, min(len(s.tools) - 1, index + int(offset)))
    with jobs.transaction():  # an unexpected error while refreshing moves the entry back
        with _exclusive():
            s.tools.move(index, target)
            jobs.on_undo(functools.partial(s.tools.move, target, index))
            jobs.assign(s, tool_index=target)
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
    if label_objects(vol_obj):
        raise VolumeEVMError(f"{vol_obj.name}: the stack edits its label objects live; Apply "
                             f"makes one region's VolumeEVM permanent and is not for label maps")
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
        state = _synced_state(vol_obj)
        state.result = result
    return result


# ---------------------------------------------------------------------------- handlers
def stack_volumes():
    """Volume objects whose surface shows (or should show) a tool stack's result."""
    found = []
    for obj in bpy.data.objects:
        s = obj.volumeevm
        if s.role != "VOLUME" or obj.library is not None or not s.vevm_path:
            continue
        surface = own_surface(obj)
        if surface is not None and (len(s.tools) or surface.volumeevm.stack_signature):
            found.append(obj)
    return found + [obj for obj in bpy.data.objects
                    if obj.volumeevm.role == "VOLUME" and obj.library is None and obj not in found
                    and (len(obj.volumeevm.tools) or _labels_edited(obj)) and label_objects(obj)]


def _touches(tool, objects, meshes):
    if tool is None:
        return False
    if tool.session_uid in objects:
        return True
    return tool.type == "MESH" and tool.data is not None and tool.data.session_uid in meshes


@bpy.app.handlers.persistent
def on_depsgraph_update_post(scene, depsgraph):
    """Re-evaluate the stacks whose tools (or volume) moved or changed shape."""
    if _busy:
        return
    objects, meshes = set(), set()
    for update in depsgraph.updates:
        data = update.id.original
        if isinstance(data, bpy.types.Object):
            if update.is_updated_transform or update.is_updated_geometry:
                objects.add(data.session_uid)
        elif isinstance(data, bpy.types.Mesh):
            meshes.add(data.session_uid)
    if not objects and not meshes:
        return
    for obj in stack_volumes():
        if obj.session_uid in objects or any(_touches(e.tool, objects, meshes)
                                             for e in obj.volumeevm.tools):
            _refresh_safely(obj, depsgraph)


@bpy.app.handlers.persistent
def on_undo_redo(*_args):
    """After undo/redo: re-sync the runtime stacks from the restored properties."""
    if _busy:
        return
    volumes = [o for o in bpy.data.objects if o.volumeevm.role == "VOLUME"]
    runtime.forget_stacks_except({(o.volumeevm.uid, o.name) for o in volumes})
    stacked = stack_volumes()
    if not stacked:
        return
    depsgraph = bpy.context.evaluated_depsgraph_get()
    for obj in stacked:
        _refresh_safely(obj, depsgraph)


HANDLERS = (("depsgraph_update_post", on_depsgraph_update_post), ("undo_post", on_undo_redo),
            ("redo_post", on_undo_redo))


# ---------------------------------------------------------------------------- label sets
def label_objects(vol_obj):
    """``label -> object`` of the label objects Make Label Meshes made for ``vol_obj`` (one per
    label); empty when it made none (or one mesh for all labels)."""
    collection = bpy.data.collections.get(f"{vol_obj.name} labels")
    if collection is None:
        return {}
    return {int(o["volumeevm_label"]): o for o in collection.objects
            if "volumeevm_label" in o and o.type == "MESH"}


def has_target(vol_obj):
    """Whether the volume's stack has something to edit: a built VolumeEVM or label objects."""
    return bool(vol_obj.volumeevm.vevm_path) or bool(label_objects(vol_obj))


def _labels_edited(vol_obj):
    """Whether a label object shows a stack's result (its signature is set)."""
    return any(o.get("volumeevm_stack") for o in label_objects(vol_obj).values())


def _label_base(vol_obj, state):
    """The label set of the volume's file (cached in the stack state)."""
    if state.labels is None:
        path, options = volumes.source_of(vol_obj)
        volume = jobs.drain(volumes.read_steps(vol_obj.volumeevm.uid, path, options), verbose=False)
        state.labels = VolumeEVM.from_labels(volume)
    return state.labels


def _label_edit(labels, entry, tool, shown):
    """One entry applied to a label set (the core's LabelSet edits); Add must name one of the
    ``shown`` labels (those with an object)."""
    core = entry.kind.core
    if core == "cut":
        return labels.cut(tool)
    if core == "keep":
        return labels.keep(tool)
    if core == "largest":
        return LabelSet({label: region.largest_component() for label, region in labels.items()},
                        labels.infos)
    if not entry.to_label:
        raise VolumeEVMError("Add on a label map needs the label that gets the material")
    if entry.to_label not in shown:
        raise VolumeEVMError(f"label {entry.to_label} is not one of the label objects' labels "
                             f"{sorted(shown)}")
    return labels.add(tool, entry.to_label)


def _same_geometry(a, b):
    """Whether two ``(co, Faces)`` (or None: no mesh) hold the same vertices and polygons."""
    if a is None or b is None:
        return a is b
    (co_a, faces_a), (co_b, faces_b) = a, b
    return (np.array_equal(co_a, co_b)
            and np.array_equal(faces_a.polygons.indices, faces_b.polygons.indices)
            and np.array_equal(faces_a.polygons.sizes, faces_b.polygons.sizes))


def _refresh_labels(vol_obj, state, depsgraph, extra, force, timing):
    """:func:`refresh` of a volume with label objects: the stack on its label set, each label
    object's mesh rewritten where its region changed (None when nothing needed it)."""
    base = _label_base(vol_obj, state)
    grid = next(iter(base.values()))
    entries = _read_entries(vol_obj, grid, depsgraph)
    if extra is not None:
        entries.append(_read_entry(vol_obj, grid, depsgraph, len(entries) + 1, *extra[:2], True,
                                   *extra[2:]))
    text = "|".join(e.key() for e in entries)
    signature = hashlib.blake2b(text.encode(), digest_size=16).hexdigest() if entries else ""
    objects = label_objects(vol_obj)
    shown = all(o.get("volumeevm_stack", "") == signature for o in objects.values())
    if shown and not force and extra is None:
        return None
    if not state.labels_shown and not any(o.get("volumeevm_stack") for o in objects.values()):
        state.labels_shown = label_geometry(base)  # the objects show the label set as made
    result = base
    for entry in entries:
        if not entry.enabled:
            continue
        tool = None if entry.kind.core == "largest" else _operation(state, entry, timing).tool
        start = time.perf_counter()
        try:
            result = _label_edit(result, entry, tool, objects)
        except VolumeEVMError as error:
            raise VolumeEVMError(f"{entry.label}: {error}") from None
        timing["evaluate_s"] += time.perf_counter() - start
    if extra is None:
        start = time.perf_counter()
        meshes = label_geometry(result)  # a label's mesh depends on its neighbours too
        with jobs.transaction():
            for label, obj in objects.items():
                mesh = meshes.get(label)
                if (_same_geometry(mesh, state.labels_shown.get(label))
                        and obj.get("volumeevm_stack", "") == signature):
                    continue
                if mesh is None:
                    none = np.zeros(0, np.int32)
                    faces = Faces(Polygons(none, none, none), np.zeros((0, 2), np.int32), none)
                    refill_mesh(obj.data, np.zeros((0, 3), np.float32), faces)
                else:
                    refill_mesh(obj.data, *mesh)
                jobs.assign_item(obj, "volumeevm_stack", signature)
        state.labels_shown = {label: meshes.get(label) for label in objects}
        timing["mesh_s"] = time.perf_counter() - start
    return result
