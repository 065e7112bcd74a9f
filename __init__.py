"""VolumeEVM Blender extension: registration only.

The core (``volumeevm_addon``) is NumPy only; ``operators`` holds the Blender tasks and the
Python API (``operators.api``); ``ui`` the property groups and the sidebar tab.
"""

import bpy

from . import operators, ui
from .operators import _handlers, import_volume, render, sidecar, tools
from .ui import panels, props, render_panel


def register():
    for cls in ui.CLASSES:
        bpy.utils.register_class(cls)
    bpy.types.Scene.volumeevm = bpy.props.PointerProperty(type=props.VolumeEVMSceneSettings)
    bpy.types.Object.volumeevm = bpy.props.PointerProperty(type=props.VolumeEVMObjectSettings)
    for cls in operators.CLASSES:
        bpy.utils.register_class(cls)
    bpy.types.TOPBAR_MT_file_import.append(import_volume.menu_import)
    bpy.types.STATUSBAR_HT_header.append(panels.draw_status)
    render_panel.register()
    _handlers.install(render.HANDLERS + sidecar.HANDLERS + tools.HANDLERS)


def unregister():
    _handlers.uninstall()
    render_panel.unregister()
    bpy.types.STATUSBAR_HT_header.remove(panels.draw_status)
    bpy.types.TOPBAR_MT_file_import.remove(import_volume.menu_import)
    for cls in reversed(operators.CLASSES):
        bpy.utils.unregister_class(cls)
    del bpy.types.Object.volumeevm
    del bpy.types.Scene.volumeevm
    for cls in reversed(ui.CLASSES):
        bpy.utils.unregister_class(cls)
