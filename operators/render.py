"""Render VolumeEVM (DVR composited into the scene), its animation, the compositor set-up for
F12 and the transfer function presets.

- ``volumeevm.render_dvr``: the sidebar's Render settings (``Scene.volumeevm_render``) ->
  :func:`..blender.dvr.render_dvr_job` (scene pass, volume render, alpha over, images, files).
- ``volumeevm.render_dvr_animation``: the same for every frame of the scene's range.
- ``volumeevm.setup_compositor``: :func:`..blender.compositor.setup_compositor`, so F12 renders
  and animations include the DVR image (render it first, with the same camera and frame).
- ``volumeevm.load_tf_preset``: a preset into the transfer function's colour ramp.
"""

import bpy
import numpy as np
from bpy.props import StringProperty

from ..blender import dvr, images, jobs
from ..blender.compositor import setup_compositor
from ..blender.objects import render_volume
from ..blender.transfer import load_preset
from ..volumeevm_addon import VolumeEVMError


def _render_problem(context):
    """Why the render cannot start now, or "". A missing camera is not one: the job reports it
    (the panel shows it too), so the button stays clickable and says what is wrong."""
    vol = render_volume(context, context.scene.volumeevm_render)
    if vol is None:
        return "Choose the volume to render (or select one)"
    if not vol.volumeevm.vevm_path:
        return f"{vol.name}: build the VolumeEVM first"
    if jobs.CURRENT is not None:
        return f"Busy: {jobs.CURRENT.label}"
    return ""


class VOLUMEEVM_OT_render_dvr(jobs.JobOperator, bpy.types.Operator):
    """Render the scene with its depth pass, render the volume from the scene camera with rays
    stopped by that depth, lay it over the render and keep the result in an image (and files)"""

    bl_idname = "volumeevm.render_dvr"
    bl_label = "Render VolumeEVM"
    bl_options = {"REGISTER"}

    volume: StringProperty(
        name="Volume", options={"SKIP_SAVE"},
        description="Name of the volume object (default: the Render settings' volume, else the "
                    "active one)")

    @classmethod
    def poll(cls, context):
        if not hasattr(context.scene, "volumeevm_render"):
            return False
        problem = _render_problem(context)
        if problem:
            cls.poll_message_set(problem)
            return False
        return True

    def job(self, context):
        scene = context.scene
        vol, tf, kwargs = dvr.job_arguments(context, scene.volumeevm_render, self.volume)
        return dvr.render_dvr_job(scene, vol, tf, **kwargs)

    def finished(self, context, result):
        h, w = result.rgba.shape[:2]
        files = [p for p in (result.exr_path, result.png_path) if p]
        if result.note:
            self.report({"WARNING"}, result.note)
        if not result.visible:
            self.report({"WARNING"}, "The camera sees nothing of the volume (outside the view, "
                                     "hidden by scene geometry or transparent): the DVR is empty")
        else:
            self.report({"INFO"}, f"{result.image.name}: {w}x{h}"
                                  + (f", wrote {', '.join(files)}" if files else ""))
        # Show the result in an open Image Editor, if any.
        screen = context.screen
        for area in (screen.areas if screen is not None else ()):
            if area.type == "IMAGE_EDITOR":
                jobs.assign(area.spaces.active, image=result.image)


class VOLUMEEVM_OT_render_dvr_animation(bpy.types.Operator):
    """Render VolumeEVM for every frame of the scene's range (scene pass, volume render and
    composite per frame), writing the EXR/PNG files with the frame number ('#' in the names)"""

    bl_idname = "volumeevm.render_dvr_animation"
    bl_label = "Render VolumeEVM Animation"
    bl_options = {"REGISTER"}

    volume: StringProperty(name="Volume", options={"SKIP_SAVE"},
                           description="Name of the volume object (default: as Render VolumeEVM)")

    @classmethod
    def poll(cls, context):
        return VOLUMEEVM_OT_render_dvr.poll(context)

    def execute(self, context):
        scene = context.scene
        wm = context.window_manager
        try:
            vol, tf, kwargs = dvr.job_arguments(context, scene.volumeevm_render, self.volume)
            if not (kwargs["exr_path"] or kwargs["png_path"]):
                raise VolumeEVMError("choose an EXR or PNG file name for the frames")
            wm.progress_begin(scene.frame_start, scene.frame_end)
            try:
                results = dvr.render_dvr_animation(vol, tf, scene=scene, **kwargs)
            finally:
                wm.progress_end()
        except jobs.REPORTED_ERRORS as error:
            return jobs.report_failure(self, error)
        notes = {result.note for _, result in results if result.note}
        for note in sorted(notes):
            self.report({"WARNING"}, note)
        empty = [frame for frame, result in results if not result.visible]
        if empty:
            self.report({"WARNING"}, f"nothing of the volume seen in frames {empty}")
        self.report({"INFO"}, f"rendered {len(results)} frames")
        return {"FINISHED"}


class VOLUMEEVM_OT_setup_compositor(bpy.types.Operator):
    """Lay the rendered volume image over the Render Layers in the compositor, so F12 renders
    include it (render the volume first, with the same camera and frame)"""

    bl_idname = "volumeevm.setup_compositor"
    bl_label = "Set Up Compositor"
    bl_options = {"REGISTER", "UNDO"}

    def execute(self, context):
        scene = context.scene
        settings = scene.volumeevm_render
        name = f"{settings.image_name or dvr.DEFAULT_IMAGE} DVR"
        image = bpy.data.images.get(name)
        if image is None:
            r = scene.render
            w = r.resolution_x * r.resolution_percentage // 100
            h = r.resolution_y * r.resolution_percentage // 100
            image = images.put_image(name, np.zeros((h, w, 4), np.float32))
            self.report({"WARNING"}, f"{name} is empty: Render VolumeEVM first, then F12")
        setup_compositor(scene, image)
        return {"FINISHED"}


class VOLUMEEVM_OT_load_tf_preset(bpy.types.Operator):
    """Load the chosen preset into the transfer function's colour ramp and value range"""

    bl_idname = "volumeevm.load_tf_preset"
    bl_label = "Load Preset"
    bl_options = {"REGISTER", "UNDO"}

    preset: StringProperty(name="Preset", options={"SKIP_SAVE"},
                           description="Preset name (default: the Render settings' preset)")

    def execute(self, context):
        settings = context.scene.volumeevm_render
        try:
            load_preset(settings, self.preset or settings.preset,
                        render_volume(context, settings))
        except VolumeEVMError as error:
            return jobs.report_failure(self, error)
        return {"FINISHED"}


CLASSES = [VOLUMEEVM_OT_render_dvr, VOLUMEEVM_OT_render_dvr_animation,
           VOLUMEEVM_OT_setup_compositor, VOLUMEEVM_OT_load_tf_preset]
