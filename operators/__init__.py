"""Blender operators, one module per user task, and the Python API for scripts (``api``).

``CLASSES`` lists every class to register, in order. Long work runs as jobs (``_jobs``);
VolumeEVM files beside the .blend are handled by ``sidecar``; CAD tool stacks by ``tools``;
the volume render composited into the scene by ``dvr`` (job) and ``render`` (operators).
"""

from . import build, import_volume, mesh, render, tools

CLASSES = [
    *import_volume.CLASSES,
    *build.CLASSES,
    *mesh.CLASSES,
    *tools.CLASSES,
    *render.CLASSES,
]
