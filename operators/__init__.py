"""Blender operators, one module per user task; only operator classes (and the File > Import
entry) live here.

Each operator reads its properties and Blender state, calls one function of the Blender side
(``blender/``: jobs, tool stack, render) and reports. ``CLASSES`` lists every class to register,
in order.
"""

from . import build, framing, import_volume, labels, mesh, native_volume, render, tools

CLASSES = [
    *import_volume.CLASSES,
    *framing.CLASSES,
    *build.CLASSES,
    *mesh.CLASSES,
    *native_volume.CLASSES,
    *labels.CLASSES,
    *tools.CLASSES,
    *render.CLASSES,
]
