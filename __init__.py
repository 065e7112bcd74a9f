"""VolumeEVM Blender extension: registration only.

The core (``volumeevm_addon``) is NumPy only; ``blender`` holds the Blender-side machinery and
the script API (``blender.api``); ``operators`` the operator classes; ``ui`` the property groups
and the sidebar tab.

A process that registers the extension and ends without ``unregister()`` (a script under
``blender --background --python``, or the bpy module) gets it unregistered at interpreter exit:
the bpy module (4.5) crashes at exit while the viewport's draw handler remains, and hangs while
persistent handlers or the add-on's UI additions remain. ``unregister()`` does nothing when the
extension is not registered: Blender disables enabled add-ons at exit after that hook has run.
"""

import atexit

import bpy

from . import operators, ui
from .blender import (
    compositor,
    gpu_viewport,
    handlers,
    kernels,
    native_volume,
    preview,
    sidecar,
    tool_stack,
)
from .operators import import_volume
from .ui import panels, props

_POINTERS = (
    (bpy.types.Scene, "volumeevm", props.VolumeEVMSceneSettings),
    (bpy.types.Scene, "volumeevm_render", props.VolumeEVMRenderSettings),
    (bpy.types.Object, "volumeevm", props.VolumeEVMObjectSettings),
)


_registered = []


def register():
    kernels.register(__package__)
    for cls in ui.CLASSES:
        bpy.utils.register_class(cls)
    for owner, name, group in _POINTERS:
        setattr(owner, name, bpy.props.PointerProperty(type=group))
    for cls in operators.CLASSES:
        bpy.utils.register_class(cls)
    bpy.types.TOPBAR_MT_file_import.append(import_volume.menu_import)
    bpy.types.STATUSBAR_HT_header.append(panels.draw_status)
    handlers.install(compositor.HANDLERS + sidecar.HANDLERS + tool_stack.HANDLERS
                     + native_volume.HANDLERS + gpu_viewport.HANDLERS)
    gpu_viewport.register()
    preview.register()
    atexit.register(unregister)
    _registered.append(True)


def unregister():
    atexit.unregister(unregister)
    if not _registered:
        return
    _registered.clear()
    preview.unregister()
    gpu_viewport.unregister()
    handlers.uninstall()
    bpy.types.STATUSBAR_HT_header.remove(panels.draw_status)
    bpy.types.TOPBAR_MT_file_import.remove(import_volume.menu_import)
    for cls in reversed(operators.CLASSES):
        bpy.utils.unregister_class(cls)
    for owner, name, _group in reversed(_POINTERS):
        delattr(owner, name)
    for cls in reversed(ui.CLASSES):
        bpy.utils.unregister_class(cls)
    kernels.unregister()
