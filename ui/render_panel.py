"""The sidebar's Render section: the settings of ``Scene.volumeevm_render`` (``props.py``), the
transfer function's colour ramp with the volume's histogram beside it (a label map: its label
list, each label's visibility, colour and opacity), the render buttons."""

import bpy

from ..blender import gpu_viewport, jobs
from ..blender.compositor import stale_dvr
from ..blender.label_table import uses_labels
from ..blender.objects import render_volume
from ..blender.transfer import preset_note
from ..volumeevm_addon.rendering import render_options
from .panels import draw_histogram, wrap

#: Histogram rows drawn beside the ramp.
HISTOGRAM_ROWS = 8
#: Settings only some methods have: drawn when the method's renderer takes an option of that name.
METHOD_SETTINGS = ("slices_per_voxel", "classification", "jitter", "preintegrate")
#: Settings of X-ray mode.
XRAY_SETTINGS = ("xray_scale", "xray_offset")


class VOLUMEEVM_PT_render(bpy.types.Panel):
    """Direct volume rendering from the VolumeEVM, composited into the scene render."""

    bl_space_type = "VIEW_3D"
    bl_region_type = "UI"
    bl_category = "VolumeEVM"
    bl_label = "Render"
    bl_parent_id = "VOLUMEEVM_PT_main"

    def draw(self, context):
        layout = self.layout
        settings = context.scene.volumeevm_render
        layout.use_property_split = True
        layout.use_property_decorate = False
        layout.prop(settings, "volume")
        vol = render_volume(context, settings)
        if settings.volume is None and vol is not None:
            layout.label(text=f"Rendering {vol.name}", icon="INFO")
        layout.prop(settings, "viewport")
        if settings.viewport:
            layout.prop(settings, "viewport_fast")
            colours = gpu_viewport.colour_problem(context.scene)
            if colours:
                for line in wrap(colours, 40):
                    layout.label(text=line, icon="ERROR")
            if vol is not None:
                problem, level = gpu_viewport.problem(vol), gpu_viewport.shown_level(vol)
                if problem:
                    layout.label(text=problem, icon="ERROR")
                elif level:
                    layout.label(text=level, icon="INFO")
        col = layout.column(align=True)
        for name in ("method", "mode", "quality", "resolution", "termination"):
            col.prop(settings, name)
        takes = render_options(settings.method)
        for name in METHOD_SETTINGS:
            if name in takes:
                col.prop(settings, name)
        if "shading" in takes:
            col.prop(settings, "shading")
        if settings.mode == "xray":
            for name in XRAY_SETTINGS:
                col.prop(settings, name)

        box = layout.box()
        box.label(text="Transfer Function", icon="COLOR")
        if vol is not None and len(vol.volumeevm.labels):
            box.prop(vol.volumeevm, "use_label_colors")
        if uses_labels(vol):
            draw_label_colors(box, vol)
        else:
            draw_ramp(box, context, settings, vol)
        box.prop(settings, "unit_length_mm", text="Alpha per mm")

        col = layout.column(align=True)
        col.prop(settings, "image_name")
        col.prop(settings, "hide_surface")
        for kind in ("exr", "png"):
            row = col.row(align=True)
            row.prop(settings, f"use_{kind}", text=kind.upper())
            sub = row.row(align=True)
            sub.active = getattr(settings, f"use_{kind}")
            sub.prop(settings, f"{kind}_path", text="")
        col.prop(settings, "overwrite")

        if jobs.CURRENT is not None:
            layout.label(text="Press Esc to cancel", icon="INFO")
        layout.operator("volumeevm.render_dvr", icon="RENDER_STILL")
        layout.operator("volumeevm.render_dvr_animation", icon="RENDER_ANIMATION")
        layout.operator("volumeevm.setup_compositor", icon="NODE_COMPOSITING")
        layout.prop(settings, "allow_stale_dvr")
        stale = stale_dvr(context.scene)
        if stale:
            box = layout.box()
            box.label(text="F12 leaves the DVR out:", icon="ERROR")
            for line in wrap(stale, 40):
                box.label(text=line)
            box.label(text="Render VolumeEVM again for this view")
        if context.scene.camera is None:
            layout.label(text="The scene has no camera", icon="ERROR")


def draw_ramp(box, context, settings, vol):
    """The colour ramp's part of the Transfer Function box: preset, ramp, value range and the
    volume's histogram beside it."""
    row = box.row(align=True)
    row.prop(settings, "preset", text="")
    row.operator("volumeevm.load_tf_preset", text="", icon="FILE_REFRESH")
    box.prop(settings, "preset_stretch")
    note = preset_note(settings, vol)
    if note:
        box.label(text=note, icon="ERROR" if not settings.preset_stretch else "INFO")
    if settings.ramp is not None and settings.ramp.color_ramp is not None:
        box.template_color_ramp(settings.ramp, "color_ramp", expand=True)
    else:
        box.label(text="Load a preset to edit the ramp")
    units = vol.volumeevm.units if vol is not None else ""
    row = box.row(align=True)
    row.prop(settings, "value_lo", text="")
    row.prop(settings, "value_hi", text="")
    if units:
        row.label(text=units)
    if vol is not None:
        draw_histogram(box, context, vol.volumeevm, HISTOGRAM_ROWS, low=settings.value_lo,
                       high=settings.value_hi)


class VOLUMEEVM_UL_label_colors(bpy.types.UIList):
    """A label map's labels as the volume renders show them: shown, colour, name, opacity."""

    def draw_item(self, context, layout, data, item, icon, active_data, active_propname,
                  index=0, flt_flag=0):
        row = layout.row(align=True)
        row.prop(item, "show", text="", emboss=False,
                 icon="HIDE_OFF" if item.show else "HIDE_ON")
        sub = row.row(align=True)
        sub.active = item.show
        sub.prop(item, "color", text="")
        sub.label(text=item.name)
        sub.prop(item, "opacity", text="", slider=True)


def draw_label_colors(box, vol):
    """A label map's part of the Transfer Function box: its label list."""
    s = vol.volumeevm
    box.template_list("VOLUMEEVM_UL_label_colors", "", s, "labels", s, "label_index",
                      rows=min(8, len(s.labels)))
    box.label(text="Each sample takes its nearest voxel's label", icon="INFO")


CLASSES = [VOLUMEEVM_UL_label_colors, VOLUMEEVM_PT_render]
