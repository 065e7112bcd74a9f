"""CAD tools on a VolumeEVM: a non-destructive stack of cut / keep / add / largest / clip entries.

Each volume object keeps an ordered list of entries (``Object.volumeevm.tools``: tool object,
operation, enabled, density). The operators here add entries, reorder, remove and apply them;
the work is done by :mod:`.api` (``add_tool``, ``evaluate``, ``apply_stack``), which scripts call
the same way.

Live updates. ``depsgraph_update_post`` looks for transform or geometry updates of a stack's
tool objects (or their meshes) and of the volume object itself, and re-evaluates that volume's
stack (``api.refresh_quietly``); an entry's fields re-evaluate through their update callbacks
(property changes do not reach the depsgraph handler). The tools
are read from the evaluated depsgraph, each one is voxelized again only if its triangles or
placement changed (a cache keyed by a digest of both), the ``EditStack`` recomputes from the
first changed entry, and the surface mesh is rewritten in place (all or nothing: if writing
fails, its old geometry is put back). The surface stores a signature
of the base and entries it shows; when nothing changed (e.g. the update was our own mesh
write, or a property of the volume unrelated to the stack) nothing is written, so there is no
feedback loop. A failure (tool moved wholly outside, open mesh, empty result) is recorded as
the stack's problem, shown in the sidebar, and the last good mesh stays; handlers never raise.

Undo and redo restore the entries, ``vevm_path`` and the surface mesh with its signature;
``undo_post`` / ``redo_post`` re-sync the runtime stacks from those properties (a new
``EditStack`` when the base path changed) and rewrite the mesh only if it does not match.
"""

import traceback

import bpy
from bpy.props import BoolProperty, FloatProperty, IntProperty

from . import _jobs, _runtime, api
from .build import active_volume, poll_volume


class _AddToolOperator:
    """Shared part of the operators that add an entry to the active volume's stack."""

    bl_options = {"REGISTER", "UNDO"}
    operation = "cut"  # the api name

    @classmethod
    def poll(cls, context):
        obj = poll_volume(cls, context, built=True)
        if obj is None:
            return False
        if cls.operation != "largest":
            problem = api.tool_problem(obj, obj.volumeevm.tool_object)
            if problem:
                cls.poll_message_set(problem)
                return False
        return True

    def density_value(self):
        return None

    def execute(self, context):
        obj = active_volume(context)
        tool = None if self.operation == "largest" else obj.volumeevm.tool_object
        try:
            result = api.add_tool(obj, tool, self.operation, self.density_value())
        except Exception as error:
            return _jobs.report_failure(self, error, self.bl_label)
        timing = api.stack_state(obj).timing
        self.report({"INFO"}, f"{api.TOOL_LABELS[api.TOOL_OPERATIONS[self.operation]]}: "
                              f"{result.voxel_count:,} voxels, refreshed in "
                              f"{timing.get('total_s', 0.0):.2f} s")
        return {"FINISHED"}


class VOLUMEEVM_OT_tool_cut(_AddToolOperator, bpy.types.Operator):
    """Cut: remove the volume's material inside the chosen tool (any closed mesh), as a new
    entry of the tool stack"""

    bl_idname = "volumeevm.tool_cut"
    bl_label = "Cut"
    operation = "cut"


class VOLUMEEVM_OT_tool_keep(_AddToolOperator, bpy.types.Operator):
    """Keep inside: keep only the volume's material inside the chosen tool, as a new entry of
    the tool stack"""

    bl_idname = "volumeevm.tool_keep"
    bl_label = "Keep Inside"
    operation = "keep"


class VOLUMEEVM_OT_tool_add(_AddToolOperator, bpy.types.Operator):
    """Add: the chosen tool's inside becomes material with a density (default: the region's
    largest), as a new entry of the tool stack"""

    bl_idname = "volumeevm.tool_add"
    bl_label = "Add"
    operation = "add"

    use_density: BoolProperty(
        name="Own Density", default=False, options={"SKIP_SAVE"},
        description="Give added voxels this density; off: the region's largest density "
                    "(unset: the sidebar's choice)")
    density: FloatProperty(name="Density", description="Density of added voxels (data units)",
                           options={"SKIP_SAVE"})

    def density_value(self):
        if not (self.properties.is_property_set("use_density")
                or self.properties.is_property_set("density")):
            # From the sidebar button: its density settings (stored on the volume).
            s = active_volume(bpy.context).volumeevm
            self.use_density, self.density = s.tool_use_density, s.tool_density
        return self.density if self.use_density else None


class VOLUMEEVM_OT_tool_largest(_AddToolOperator, bpy.types.Operator):
    """Keep largest part: keep only the largest face-connected part of the region, as a new
    entry of the tool stack"""

    bl_idname = "volumeevm.tool_largest"
    bl_label = "Keep Largest Part"
    operation = "largest"


class VOLUMEEVM_OT_tool_clip(_AddToolOperator, bpy.types.Operator):
    """Clip to box: keep only the material inside the chosen object's bounding box, as a new
    entry of the tool stack"""

    bl_idname = "volumeevm.tool_clip"
    bl_label = "Clip to Box"
    operation = "clip"


class _StackOperator:
    bl_options = {"REGISTER", "UNDO"}

    @classmethod
    def poll(cls, context):
        obj = poll_volume(cls, context, built=True)
        if obj is None:
            return False
        if not len(obj.volumeevm.tools):
            cls.poll_message_set("The tool stack is empty")
            return False
        return True

    def _index(self, obj):
        tools = obj.volumeevm.tools
        index = obj.volumeevm.tool_index if self.index < 0 else self.index
        return min(index, len(tools) - 1)

    def _done(self, change):
        """Run ``change`` (it returns the stack's problem or ""); report the problem or error."""
        try:
            problem = change()
        except Exception as error:
            return _jobs.report_failure(self, error, self.bl_label)
        if problem:
            self.report({"WARNING"}, problem)
        return {"FINISHED"}


class VOLUMEEVM_OT_tool_remove(_StackOperator, bpy.types.Operator):
    """Remove the entry from the tool stack (the tool object stays)"""

    bl_idname = "volumeevm.tool_remove"
    bl_label = "Remove Tool Entry"

    index: IntProperty(name="Index", default=-1, min=-1, options={"SKIP_SAVE"},
                       description="Entry to remove (-1: the active one)")

    def execute(self, context):
        obj = active_volume(context)
        return self._done(lambda: api.remove_tool(obj, self._index(obj)))


class _MoveOperator(_StackOperator):
    offset = -1

    index: IntProperty(name="Index", default=-1, min=-1, options={"SKIP_SAVE"},
                       description="Entry to move (-1: the active one)")

    def execute(self, context):
        obj = active_volume(context)
        return self._done(lambda: api.move_tool(obj, self._index(obj), self.offset))


class VOLUMEEVM_OT_tool_move_up(_MoveOperator, bpy.types.Operator):
    """Move the entry up the tool stack (entries apply from top to bottom)"""

    bl_idname = "volumeevm.tool_move_up"
    bl_label = "Move Tool Entry Up"
    offset = -1


class VOLUMEEVM_OT_tool_move_down(_MoveOperator, bpy.types.Operator):
    """Move the entry down the tool stack (entries apply from top to bottom)"""

    bl_idname = "volumeevm.tool_move_down"
    bl_label = "Move Tool Entry Down"
    offset = 1


class VOLUMEEVM_OT_tool_refresh(_StackOperator, bpy.types.Operator):
    """Evaluate the tool stack again with the tools as they are now and refresh the surface"""

    bl_idname = "volumeevm.tool_refresh"
    bl_label = "Refresh"

    def execute(self, context):
        try:
            api.evaluate(active_volume(context))
        except Exception as error:
            return _jobs.report_failure(self, error, self.bl_label)
        return {"FINISHED"}


class VOLUMEEVM_OT_tool_apply(_StackOperator, bpy.types.Operator):
    """Apply the tool stack: its result becomes the volume's VolumeEVM (a new file beside the
    .blend when saved) and the stack is cleared"""

    bl_idname = "volumeevm.tool_apply"
    bl_label = "Apply Tools"

    def execute(self, context):
        try:
            result = api.apply_stack(active_volume(context))
        except Exception as error:
            return _jobs.report_failure(self, error, self.bl_label)
        self.report({"INFO"}, f"Applied: the VolumeEVM has {result.voxel_count:,} voxels")
        return {"FINISHED"}


# ---------------------------------------------------------------------------- handlers
def stack_volumes():
    """Volume objects whose surface shows (or should show) a tool stack's result."""
    found = []
    for obj in bpy.data.objects:
        s = obj.volumeevm
        if s.role != "VOLUME" or obj.library is not None or not s.vevm_path:
            continue
        surface = api.own_surface(obj)
        if surface is not None and (len(s.tools) or surface.volumeevm.stack_signature):
            found.append(obj)
    return found


def _touches(tool, objects, meshes):
    if tool is None:
        return False
    if tool.session_uid in objects:
        return True
    return tool.type == "MESH" and tool.data is not None and tool.data.session_uid in meshes


def _refresh_safely(obj, depsgraph):
    """Refresh one volume from a handler; never raises (the problem shows in the sidebar)."""
    try:
        api.refresh_quietly(obj, depsgraph)
    except Exception as error:  # noqa: BLE001 - a handler must not raise; keep the last mesh
        traceback.print_exc()
        api.stack_problem(obj, f"unexpected error while refreshing: {error!r}")


@bpy.app.handlers.persistent
def on_depsgraph_update_post(scene, depsgraph):
    """Re-evaluate the stacks whose tools (or volume) moved or changed shape."""
    if api.is_busy():
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
    if api.is_busy():
        return
    volumes = [o for o in bpy.data.objects if o.volumeevm.role == "VOLUME"]
    _runtime.forget_stacks_except({(o.volumeevm.uid, o.name) for o in volumes})
    stacked = stack_volumes()
    if not stacked:
        return
    depsgraph = bpy.context.evaluated_depsgraph_get()
    for obj in stacked:
        _refresh_safely(obj, depsgraph)


HANDLERS = (("depsgraph_update_post", on_depsgraph_update_post), ("undo_post", on_undo_redo),
            ("redo_post", on_undo_redo))


CLASSES = [
    VOLUMEEVM_OT_tool_cut,
    VOLUMEEVM_OT_tool_keep,
    VOLUMEEVM_OT_tool_add,
    VOLUMEEVM_OT_tool_largest,
    VOLUMEEVM_OT_tool_clip,
    VOLUMEEVM_OT_tool_remove,
    VOLUMEEVM_OT_tool_move_up,
    VOLUMEEVM_OT_tool_move_down,
    VOLUMEEVM_OT_tool_refresh,
    VOLUMEEVM_OT_tool_apply,
]
