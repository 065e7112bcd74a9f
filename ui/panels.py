"""The 3D view sidebar tab "VolumeEVM", the job progress bar in the status bar, and the one
histogram drawer (the Histogram panel's, and the Render panel's beside the transfer function).
"""

import math
import textwrap

import bpy
import numpy as np

from ..blender import framing, jobs, labels, runtime, tool_stack, volumes
from ..blender.objects import active_volume

#: Histogram rows drawn in the Histogram panel (the stored bins are summed in groups).
HISTOGRAM_ROWS = 16


def human_bytes(n):
    """``1536`` -> ``"1.5 KiB"``."""
    n = float(n)
    for unit in ("B", "KiB", "MiB", "GiB"):
        if n < 1024 or unit == "GiB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1024
    return f"{n:.1f} GiB"


def _fmt(value):
    return f"{value:.4g}"


def draw_progress(layout):
    """Draw the running job's progress bar; True if a job runs."""
    job = jobs.CURRENT
    if job is None:
        return False
    layout.progress(factor=job.fraction, type="BAR", text=f"{job.label}: {job.text}")
    return True


class _Sidebar:
    bl_space_type = "VIEW_3D"
    bl_region_type = "UI"
    bl_category = "VolumeEVM"


class VOLUMEEVM_PT_main(_Sidebar, bpy.types.Panel):
    """Import a volume; the selected volume's data, region and surface in the sub-panels."""

    bl_label = "VolumeEVM"

    def draw(self, context):
        layout = self.layout
        layout.operator("volumeevm.import_volume", text="Import Volume", icon="IMPORT")
        if draw_progress(layout):
            layout.label(text="Press Esc to cancel", icon="INFO")
        obj = active_volume(context)
        if obj is None:
            layout.label(text="Select or import a volume", icon="INFO")
            return
        layout.label(text=obj.name, icon="MESH_CUBE")
        problem = runtime.status(obj.volumeevm.uid)
        if problem:
            box = layout.box()
            box.label(text="VolumeEVM problem:", icon="ERROR")
            for line in wrap(problem, 40):
                box.label(text=line)


def wrap(text, width):
    words, lines, line = text.split(), [], ""
    for word in words:
        if line and len(line) + 1 + len(word) > width:
            lines.append(line)
            line = word
        else:
            line = f"{line} {word}".strip()
    return lines + [line] if line else lines


class _VolumeSubpanel(_Sidebar):
    bl_parent_id = "VOLUMEEVM_PT_main"

    @classmethod
    def poll(cls, context):
        return active_volume(context) is not None


class VOLUMEEVM_PT_volume(_VolumeSubpanel, bpy.types.Panel):
    """Size, spacing and value range of the selected volume."""

    bl_label = "Volume"

    def draw(self, context):
        s = active_volume(context).volumeevm
        col = self.layout.column(align=True)
        x, y, z = s.shape
        col.label(text=f"Size: {x} × {y} × {z} voxels")
        sx, sy, sz = s.spacing
        col.label(text=f"Spacing: {sx:.4g} × {sy:.4g} × {sz:.4g} mm")
        col.label(text=f"Extent: {x * sx:.1f} × {y * sy:.1f} × {z * sz:.1f} mm")
        if not s.spacing_known:
            col.label(text="Spacing unknown: 1 mm assumed", icon="ERROR")
        units = f" {s.units}" if s.units else ""
        col.label(text=f"Values: {_fmt(s.value_min)} .. {_fmt(s.value_max)}{units}")
        col.prop(s, "units")
        col.label(text=units_source(s), icon="INFO")
        col.label(text=f"Type: {s.dtype}, dense {human_bytes(s.dense_bytes or _dense(s))}")
        if s.zarr_levels:
            draw_levels(col, active_volume(context))
        elif runtime.volume(s.uid) is None:
            col.label(text="Not in memory: Build re-reads the source", icon="FILE_REFRESH")
        col.prop(s, "source_path", text="")
        layout = self.layout
        layout.operator_menu_enum("volumeevm.frame_volume", "side", text="Frame Volume",
                                  icon="VIEW_CAMERA")
        enclosing = framing.enclosing_objects(active_volume(context), context.scene)
        if enclosing:
            box = layout.box()
            box.label(text=f"Hidden inside {', '.join(o.name for o in enclosing)}", icon="ERROR")
            box.operator("volumeevm.hide_enclosing", icon="HIDE_ON")


def draw_levels(layout, obj):
    """An OME-Zarr store's levels (size, spacing, bytes on disk and in memory, what building
    each needs) and the level Build reads."""
    box = layout.box()
    box.label(text="OME-Zarr levels (Build reads the picked one chunk by chunk):")
    picked = obj.volumeevm.level
    for level in volumes.zarr_levels(obj):
        x, y, z = level["shape"]
        sx, sy, sz = level["spacing"]
        icon = "RADIOBUT_ON" if level["level"] == picked else "RADIOBUT_OFF"
        col = box.column(align=True)
        col.label(text=f"{level['level']}: {x} × {y} × {z}, {sx:.3g} × {sy:.3g} × {sz:.3g} mm",
                  icon=icon)
        col.label(text=f"Disk {human_bytes(level['disk_bytes'])}, memory "
                       f"{human_bytes(level['bytes'])}, build ~{human_bytes(level['build_bytes'])}")
    box.prop(obj.volumeevm, "level")


def units_source(s):
    """Which units apply to a volume (``s`` is its ``volumeevm``) and where they come from."""
    said = f"the file says {s.file_units}" if s.file_units else "the file gives none"
    if s.units == s.file_units:
        return f"Units: {said}" if s.units else "Units unknown: CT presets mean HU"
    return f"Units set by you ({said})"


def _dense(s):
    try:
        itemsize = np.dtype(s.dtype).itemsize
    except TypeError:
        return 0
    return math.prod(s.shape) * itemsize


class VOLUMEEVM_PT_histogram(_VolumeSubpanel, bpy.types.Panel):
    """Histogram of the densities, with the chosen threshold marked."""

    bl_label = "Histogram"
    bl_options = {"DEFAULT_CLOSED"}

    def draw_header(self, context):
        self.layout.prop(context.scene.volumeevm, "histogram_log", text="Log")

    def draw(self, context):
        s = active_volume(context).volumeevm
        upper = s.upper if s.use_upper else math.inf
        if not draw_histogram(self.layout, context, s, HISTOGRAM_ROWS, low=s.threshold,
                              high=upper, marker=s.threshold):
            self.layout.label(text="No histogram")


def draw_histogram(layout, context, s, rows, *, low, high, marker=None):
    """Draw a volume's stored histogram (``s`` is its ``volumeevm``) as ``rows`` bars.

    The stored bins are summed in groups; each bar says its lowest density and its voxels. A
    bar whose range meets ``[low, high]`` is ticked, the bar holding ``marker`` (the threshold)
    is pointed at. Bars are on a log scale when the scene's ``histogram_log`` is on (CT is
    mostly air). Returns False, drawing nothing, when the volume has no histogram.
    """
    counts = np.asarray(s.histogram, np.float64)
    if counts.sum() == 0:
        return False
    counts = counts.reshape(rows, -1).sum(axis=1)
    heights = np.log1p(counts) if context.scene.volumeevm.histogram_log else counts
    heights = heights / heights.max()
    edges = np.linspace(s.value_min, s.value_max, rows + 1)
    col = layout.column(align=True)
    for i in range(rows):
        row = col.row(align=True)
        row.scale_y = 0.7
        lo, hi = edges[i], edges[i + 1]
        inside = hi > low and lo <= high
        pointed = marker is not None and (lo <= marker < hi or (i == rows - 1 and marker >= hi))
        row.label(text="", icon="TRIA_RIGHT" if pointed else
                  ("CHECKMARK" if inside else "BLANK1"))
        row.progress(factor=float(heights[i]), type="BAR", text=f"{_fmt(lo)}: {int(counts[i])}")
    return True


class VOLUMEEVM_PT_build(_VolumeSubpanel, bpy.types.Panel):
    """Threshold (data units) and the VolumeEVM built from it."""

    bl_label = "VolumeEVM"

    def draw(self, context):
        layout = self.layout
        s = active_volume(context).volumeevm
        layout.use_property_split = True
        layout.use_property_decorate = False
        col = layout.column(align=True)
        col.prop(s, "threshold", text=f"Threshold{' (' + s.units + ')' if s.units else ''}")
        row = col.row(align=True)
        row.prop(s, "use_upper", text="Upper Bound")
        sub = row.row(align=True)
        sub.active = s.use_upper
        sub.prop(s, "upper", text="")
        layout.prop(s, "crop_object", text="Crop To")
        # The button passes the settings explicitly, so the redo panel can adjust them.
        op = layout.operator("volumeevm.build_vevm", icon="MOD_REMESH")
        op.use_settings = False
        op.threshold = s.threshold
        op.use_upper = s.use_upper
        op.upper = s.upper
        if not s.vevm_path:
            layout.label(text="Not built yet")
            return
        col = layout.column(align=True)
        col.label(text=f"Voxels: {s.voxel_count:,}")
        col.label(text=f"Extreme vertices: {s.ev_count:,}")
        ratio = s.vevm_bytes / s.dense_bytes if s.dense_bytes else 0.0
        col.label(text=f"Size: {human_bytes(s.vevm_bytes)} of {human_bytes(s.dense_bytes)} "
                       f"dense ({100 * ratio:.1f}%)")
        stale = (s.threshold != s.built_threshold or s.use_upper != s.built_use_upper
                 or (s.use_upper and s.upper != s.built_upper))
        if stale:
            col.label(text=f"Built at {_fmt(s.built_threshold)}: build again", icon="ERROR")
        path = s.vevm_path
        col.label(text="Kept beside the .blend" if path.startswith("//")
                  else "Kept in a temporary folder until the .blend is saved",
                  icon="FILE")


class VOLUMEEVM_PT_mesh(_VolumeSubpanel, bpy.types.Panel):
    """The VolumeEVM's surface as a mesh object."""

    bl_label = "Surface"

    def draw(self, context):
        layout = self.layout
        s = active_volume(context).volumeevm
        layout.operator("volumeevm.make_mesh", icon="MESH_DATA")
        layout.operator("volumeevm.make_mesh", text="Make Manifold Mesh (3D print)").manifold = True
        layout.operator("volumeevm.make_mesh", text="Make Smooth Mesh (display)",
                        icon="MOD_SMOOTH").smooth = True
        if s.label_count:  # a label map: every label its own object
            row = layout.row(align=True)
            row.operator("volumeevm.make_label_meshes", icon="GROUP_VERTEX").single_mesh = False
            row.operator("volumeevm.make_label_meshes", text="One Mesh").single_mesh = True
        surface = s.surface
        if surface is not None and surface.type == "MESH":
            mesh = surface.data
            layout.label(text=f"{surface.name}: {len(mesh.vertices):,} vertices, "
                              f"{len(mesh.polygons):,} faces")
        layout.operator("volumeevm.make_volume_object", icon="VOLUME_DATA")


class VOLUMEEVM_UL_labels(bpy.types.UIList):
    """A label map's exact measurements, one row per label; picking a row selects its object."""

    sort_by: bpy.props.EnumProperty(
        name="Sort By", default="LABEL",
        items=(("LABEL", "Label", "In label order"), ("NAME", "Name", "Alphabetically"),
               ("VOLUME", "Volume", "Largest first")))

    def draw_item(self, context, layout, data, item, icon, active_data, active_propname,
                  index=0, flt_flag=0):
        split = layout.split(factor=0.4, align=True)
        split.label(text=item.name)
        split.label(text=f"{item.volume_ml:.4g} mL")
        split.label(text=f"{item.area_mm2:.5g} mm²")
        split.label(text=f"{item.components} part{'s' if item.components != 1 else ''}")

    def draw_filter(self, context, layout):
        row = layout.row(align=True)
        row.prop(self, "filter_name", text="")
        row.prop(self, "sort_by", expand=True)
        row.prop(self, "use_filter_sort_reverse", text="", icon="SORT_DESC")

    def filter_items(self, context, data, propname):
        rows = getattr(data, propname)
        flags = bpy.types.UI_UL_list.filter_items_by_name(self.filter_name,
                                                          self.bitflag_filter_item, rows, "name")
        keys = {"LABEL": lambda row: row.label, "NAME": lambda row: row.name.lower(),
                "VOLUME": lambda row: -row.volume_ml}[self.sort_by]
        ranked = sorted(range(len(rows)), key=lambda i: (keys(rows[i]), rows[i].label))
        order = [0] * len(rows)
        for place, i in enumerate(ranked):
            order[i] = place
        return flags, order


class VOLUMEEVM_PT_labels(_VolumeSubpanel, bpy.types.Panel):
    """A label map's exact measurements per label, sortable, exported as CSV."""

    bl_label = "Label Measurements"

    @classmethod
    def poll(cls, context):
        obj = active_volume(context)
        return obj is not None and obj.volumeevm.label_count > 0

    def draw(self, context):
        layout = self.layout
        s = active_volume(context).volumeevm
        row = layout.row(align=True)
        row.operator("volumeevm.measure_labels", icon="DRIVER_DISTANCE")
        row.operator("volumeevm.export_label_measurements", text="CSV", icon="EXPORT")
        if not s.label_measurements:
            layout.label(text="Not measured yet")
            return
        layout.template_list("VOLUMEEVM_UL_labels", "", s, "label_measurements", s,
                             "label_measurement_index", rows=min(8, len(s.label_measurements)))
        col = layout.column(align=True)
        col.scale_y = 0.7
        for line in textwrap.wrap(labels.SMOOTH_AREA_NOTE, 48):
            col.label(text=line)


class VOLUMEEVM_UL_tools(bpy.types.UIList):
    """The tool stack of a volume: entries apply from top to bottom."""

    def draw_item(self, context, layout, data, item, icon, active_data, active_propname,
                  index=0, flt_flag=0):
        row = layout.row(align=True)
        row.prop(item, "enabled", text="")
        sub = row.row(align=True)
        sub.active = item.enabled
        kind = tool_stack.KINDS[item.operation]
        sub.label(text=kind.label, icon=kind.icon)
        if item.operation != "LARGEST":
            sub.prop(item, "tool", text="")
        if item.operation == "ADD" and tool_stack.label_objects(data.id_data):
            sub.prop(item, "label", text="Label")
        elif item.operation == "ADD":
            sub.prop(item, "use_density", text="", icon="DRIVER_DISTANCE")
            if item.use_density:
                sub.prop(item, "density", text="")


def timing_text(timing):
    """The last refresh's time and its parts, for the sidebar."""
    parts = [f"voxelize {timing.get('voxelize_s', 0.0):.2f}",
             f"stack {timing.get('evaluate_s', 0.0):.2f}",
             f"mesh {timing.get('mesh_s', 0.0) + timing.get('write_s', 0.0):.2f}"]
    return f"Last refresh: {timing['total_s']:.2f} s ({', '.join(parts)})"


class VOLUMEEVM_PT_tools(_VolumeSubpanel, bpy.types.Panel):
    """CAD tools: any closed mesh cuts, keeps or adds material, as a non-destructive stack that
    follows the tools when they move."""

    bl_label = "Tools"

    def draw(self, context):
        layout = self.layout
        obj = active_volume(context)
        s = obj.volumeevm
        labelled = bool(tool_stack.label_objects(obj))
        if not (s.vevm_path or labelled):
            layout.label(text="Build the VolumeEVM first (or Make Label Meshes)", icon="INFO")
            return
        if labelled:
            layout.label(text="Tools edit every label object", icon="GROUP_VERTEX")
        layout.prop(s, "tool_object", text="Tool")
        if s.tool_object is not None:
            problem = tool_stack.tool_problem(obj, s.tool_object)
            if problem:
                layout.label(text=problem, icon="ERROR")
        grid = layout.grid_flow(columns=2, align=True)
        for kind in tool_stack.TOOL_KINDS:
            if kind.identifier != "ADD":
                grid.operator(f"volumeevm.tool_{kind.name}", icon=kind.icon)
        add = tool_stack.KINDS["ADD"]
        row = layout.row(align=True)
        row.operator(f"volumeevm.tool_{add.name}", icon=add.icon)  # uses the settings below
        if labelled:
            row.prop(s, "tool_label", text="Label")
        else:
            row.prop(s, "tool_use_density", text="", icon="DRIVER_DISTANCE")
            sub = row.row(align=True)
            sub.active = s.tool_use_density
            sub.prop(s, "tool_density", text="")

        row = layout.row()
        row.template_list("VOLUMEEVM_UL_tools", "", s, "tools", s, "tool_index", rows=3)
        col = row.column(align=True)
        col.operator("volumeevm.tool_move_up", text="", icon="TRIA_UP")
        col.operator("volumeevm.tool_move_down", text="", icon="TRIA_DOWN")
        col.separator()
        col.operator("volumeevm.tool_remove", text="", icon="X")
        row = layout.row(align=True)
        row.operator("volumeevm.tool_refresh", icon="FILE_REFRESH")
        row.operator("volumeevm.tool_apply", icon="CHECKMARK")

        state = runtime.stack_state(s.uid, obj.name)
        if state is None:
            return
        if state.timing.get("total_s") is not None:
            col = layout.column(align=True)
            col.label(text=timing_text(state.timing), icon="TIME")
            if "voxels" in state.timing:
                col.label(text=f"Result: {state.timing['voxels']:,} voxels")
        if state.problem:
            box = layout.box()
            box.label(text="Tool stack problem:", icon="ERROR")
            for line in wrap(state.problem, 40):
                box.label(text=line)


def draw_status(self, context):
    """Status-bar progress of a running job."""
    if jobs.CURRENT is not None:
        draw_progress(self.layout.row())


#: UI lists (registered before the panels that draw them).
LISTS = [VOLUMEEVM_UL_tools, VOLUMEEVM_UL_labels]

CLASSES = [
    VOLUMEEVM_PT_main,
    VOLUMEEVM_PT_volume,
    VOLUMEEVM_PT_histogram,
    VOLUMEEVM_PT_build,
    VOLUMEEVM_PT_mesh,
    VOLUMEEVM_PT_labels,
    VOLUMEEVM_PT_tools,
]
