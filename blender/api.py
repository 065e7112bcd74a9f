"""The Python API for scripts: the functions the operators run, in one short import.

::

    import bpy
    from bl_ext.user_default.volumeevm.blender import api   # installed extension
    vol = api.import_volume("/data/head.nrrd")
    api.build(vol, threshold=300.0)                 # data units (HU for CT)
    api.build(vol, 300.0, crop=roi)                 # only a region: an object's bounds, or
    api.build(vol, 300.0, crop=((0, 64), (0, 64), (10, 40)))  # voxel indices x, y, z
    surface = api.make_mesh(vol)
    labels = api.make_label_meshes(api.import_volume("/data/seg.seg.nrrd"))  # one per label
    big = api.import_volume("/data/cells.ome.zarr")  # OME-Zarr: metadata, coarsest level
    big.volumeevm.level = 1                         # the level Build reads, chunk by chunk

Importing the API of an installed extension that is not enabled (a new session of the bpy module,
or a Blender whose preferences leave it off) enables it, as Preferences > Add-ons does.

CAD tools (a non-destructive stack per volume object, see :func:`add_tool`)::

    api.add_tool(vol, drill, "cut")                 # any closed mesh object; also "keep", "add",
    api.add_tool(vol, None, "largest")              # "largest" (no tool), "clip" (tool's box)
    drill.location.x += 0.01; api.evaluate(vol)     # or any depsgraph update (handler)
    api.apply_stack(vol)                            # the result becomes the VolumeEVM

A camera that shows the whole volume (the default cube, 2 m, hides a 0.26 m scan)::

    api.hide_enclosing(vol)                         # hide objects that enclose the volume
    api.frame_volume(vol, "FRONT")                  # or BACK, LEFT, RIGHT, TOP, BOTTOM

The region as a native Blender Volume (OpenVDB grid) that Cycles and EEVEE render, with a
material from the Render settings' transfer function (both follow their changes)::

    native = api.make_volume_object(vol)

A label map's look in the volume renders (its labels' colours by default, saved in the .blend)::

    seg = api.import_volume("/data/seg.seg.nrrd"); api.build(seg, seg.volumeevm.threshold)
    api.set_label(seg, 3, visible=False)            # hide the skin, show the organs
    api.set_label(seg, 5, color=(1, 0, 0), opacity=0.8)
    result = api.render_dvr(seg)                    # the label colours (no tf given)

Direct volume rendering into the scene::

    from bl_ext.user_default.volumeevm.volumeevm_addon import TransferFunction
    result = api.render_dvr(vol, TransferFunction.preset("ct_bone"), exr_path="//head.exr")
    api.setup_compositor(bpy.context.scene, result.dvr_image)   # F12 includes it

Errors: bad input raises :class:`VolumeEVMError` (and ``OSError`` for unreadable files). Whatever
the error, ``import_volume``, ``build``, ``make_mesh``, ``add_tool`` and ``render_dvr`` leave the
scene as it was. Under ``blender --background`` progress lines ``[volumeevm] 42% building EVM``
are printed. Each function is documented where it lives: :mod:`.volumes` (import, build, mesh),
:mod:`.labels` (label maps), :mod:`.tool_stack` (CAD tools), :mod:`.framing` (camera),
:mod:`.dvr` (rendering), :mod:`.transfer` (the Render settings' transfer function),
:mod:`.label_table` (a label map's colours),
:mod:`.compositor` (F12).
"""

import os
import sys

import addon_utils
import bpy

from .compositor import setup_compositor
from .dvr import DVRResult, render_dvr, render_dvr_animation
from .framing import enclosing_objects, frame_volume, hide_enclosing
from .label_table import get_label, label_transfer_function, set_label
from .labels import export_label_measurements, make_label_meshes, measure_labels
from .native_volume import make_volume_object
from .objects import get_vevm, volume_object
from .tool_stack import (
    add_tool,
    apply_stack,
    evaluate,
    move_tool,
    remove_tool,
    stack_state,
    tool_problem,
)
from .transfer import (
    load_preset,
    set_transfer_function,
    transfer_function,
    volume_transfer_function,
)
from .volumes import build, get_volume, import_volume, make_mesh

__all__ = ["import_volume", "build", "make_mesh", "make_label_meshes", "measure_labels",
           "export_label_measurements", "set_label", "get_label", "label_transfer_function",
           "volume_transfer_function", "make_volume_object", "volume_object", "get_vevm",
           "get_volume",
           "add_tool", "evaluate", "apply_stack", "remove_tool", "move_tool", "tool_problem",
           "stack_state", "render_dvr", "render_dvr_animation", "DVRResult",
           "transfer_function", "set_transfer_function", "load_preset", "setup_compositor",
           "frame_volume", "enclosing_objects", "hide_enclosing"]


def _enable_installed():
    """Enable the installed extension this API belongs to when it is not registered (a source
    tree loaded by hand, not an extension, is left to its loader)."""
    package = __package__.rpartition(".")[0]
    if package.startswith("bl_ext.") and not hasattr(bpy.types.Object, "volumeevm"):
        def fail(error):
            raise error

        module = sys.modules[package]  # imported already: addon_utils would reload it otherwise
        module.__time__ = os.path.getmtime(module.__file__)
        addon_utils.enable(package, default_set=True, handle_error=fail)


_enable_installed()
