"""CAD tools on a VolumeEVM: add cut / keep / add / largest / clip entries to the active volume's
tool stack, reorder, remove, refresh and apply them.

The work is done by :mod:`..blender.tool_stack` (``add_tool``, ``evaluate``, ``apply_stack``),
which scripts call the same way. One operator per kind of entry, ``volumeevm.tool_<name>``, made
from :data:`..blender.tool_stack.TOOL_KINDS` (its label and tooltip too).
"""

import bpy
from bpy.props import BoolProperty, FloatProperty, IntProperty

from ..blender import jobs, tool_stack
from ..blender.objects import active_volume, poll_volume


class _AddToolOperator:
    """Shared part of the operators that add an entry to the active volume's stack."""

    bl_options = {"REGISTER", "UNDO"}
    kind = None  # a ToolKind: each operator's own (see _add_tool_operator)

    @classmethod
    def poll(cls, context):
        obj = _poll_target(cls, context)
        if obj is None:
            return False
        if cls.kind.identifier != "LARGEST":
            problem = tool_stack.tool_problem(obj, obj.volumeevm.tool_object)
            if problem:
                cls.poll_message_set(problem)
                return False
        return True

    def density_value(self):
        return None

    def label_value(self):
        return 0

    def execute(self, context):
        obj = active_volume(context)
        tool = None if self.kind.identifier == "LARGEST" else obj.volumeevm.tool_object
        try:
            tool_stack.add_tool(obj, tool, self.kind.name, self.density_value(),
                                label=self.label_value())
        except Exception as error:
            return jobs.report_failure(self, error, self.bl_label)
        timing = tool_stack.stack_state(obj).timing
        self.report({"INFO"}, f"{self.kind.label}: {timing.get('voxels', 0):,} voxels, "
                              f"refreshed in {timing.get('total_s', 0.0):.2f} s")
        return {"FINISHED"}


class _AddWithDensity(_AddToolOperator):
    """The Add operator's density: its own properties, else the sidebar's (on the volume)."""

    use_density: BoolProperty(
        name="Own Density", default=False, options={"SKIP_SAVE"},
        description="Give added voxels this density; off: the region's largest density "
                    "(unset: the sidebar's choice)")
    density: FloatProperty(name="Density", description="Density of added voxels (data units)",
                           options={"SKIP_SAVE"})
    label: IntProperty(name="Label", min=0, options={"SKIP_SAVE"},
                       description="On a label map's label objects: the label that gets the "
                                   "material (unset: the sidebar's choice)")

    def label_value(self):
        if not self.properties.is_property_set("label"):
            self.label = active_volume(bpy.context).volumeevm.tool_label
        return self.label

    def density_value(self):
        if not (self.properties.is_property_set("use_density")
                or self.properties.is_property_set("density")):
            # From the sidebar button: its density settings (stored on the volume).
            s = active_volume(bpy.context).volumeevm
            self.use_density, self.density = s.tool_use_density, s.tool_density
        return self.density if self.use_density else None


def _add_tool_operator(kind):
    """The operator ``volumeevm.tool_<name>`` that adds a ``kind`` entry to the stack."""
    base = _AddWithDensity if kind.identifier == "ADD" else _AddToolOperator
    return type(f"VOLUMEEVM_OT_tool_{kind.name}", (base, bpy.types.Operator), {
        "__doc__": f"{kind.description}, as a new entry of the tool stack",
        "bl_idname": f"volumeevm.tool_{kind.name}",
        "bl_label": kind.label,
        "kind": kind,
    })


def _poll_target(cls, context):
    """The active volume if its stack has something to edit (a built VolumeEVM or label
    objects), else None with the poll message saying why."""
    obj = poll_volume(cls, context, built=False)
    if obj is not None and not tool_stack.has_target(obj):
        cls.poll_message_set("No VolumeEVM built yet: build one first (or Make Label Meshes)")
        return None
    return obj


class _StackOperator:
    bl_options = {"REGISTER", "UNDO"}

    @classmethod
    def poll(cls, context):
        obj = _poll_target(cls, context)
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
            return jobs.report_failure(self, error, self.bl_label)
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
        return self._done(lambda: tool_stack.remove_tool(obj, self._index(obj)))


class _MoveOperator(_StackOperator):
    offset = -1

    index: IntProperty(name="Index", default=-1, min=-1, options={"SKIP_SAVE"},
                       description="Entry to move (-1: the active one)")

    def execute(self, context):
        obj = active_volume(context)
        return self._done(lambda: tool_stack.move_tool(obj, self._index(obj), self.offset))


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
            tool_stack.evaluate(active_volume(context))
        except Exception as error:
            return jobs.report_failure(self, error, self.bl_label)
        return {"FINISHED"}


class VOLUMEEVM_OT_tool_apply(_StackOperator, bpy.types.Operator):
    """Apply the tool stack: its result becomes the volume's VolumeEVM (a new file beside the
    .blend when saved) and the stack is cleared"""

    bl_idname = "volumeevm.tool_apply"
    bl_label = "Apply Tools"

    def execute(self, context):
        try:
            result = tool_stack.apply_stack(active_volume(context))
        except Exception as error:
            return jobs.report_failure(self, error, self.bl_label)
        self.report({"INFO"}, f"Applied: the VolumeEVM has {result.voxel_count:,} voxels")
        return {"FINISHED"}


CLASSES = [
    *(_add_tool_operator(kind) for kind in tool_stack.TOOL_KINDS),
    VOLUMEEVM_OT_tool_remove,
    VOLUMEEVM_OT_tool_move_up,
    VOLUMEEVM_OT_tool_move_down,
    VOLUMEEVM_OT_tool_refresh,
    VOLUMEEVM_OT_tool_apply,
]
