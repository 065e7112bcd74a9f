"""Whether this Blender can draw on the GPU here: the GPU context the GPU method needs.

A GPU context is needed on the calling (main) thread: Blender with a window has one; in
background mode Blender 5.x makes one with ``gpu.init()``, Blender 4.5 after one small
Workbench render (:func:`ensure_context`, which raises :class:`GPUUnavailable` when neither
works, so the render can fall back to the CPU ray caster). Without EGL that attempt crashes
Blender instead of failing, so it is made first in a process of its own (:func:`_probe`).
A module of its own: the question comes before any texture or shader is made, and the render
job (its CPU fallback), the tests and the benchmarks ask it on its own.
"""

import subprocess
import sys

import bpy
import gpu

from ..volumeevm_addon import VolumeEVMError


class GPUUnavailable(VolumeEVMError):
    """No GPU context can be made on this thread (a headless machine without EGL, a worker
    thread): the GPU method cannot draw."""


_context = False


def ensure_context():
    """Make sure the calling thread can draw: in background mode make the process's GPU
    context once (Blender 5.x: ``gpu.init()``; 4.5: a 4x4 Workbench render of a temporary
    scene), then check that a texture can be made.

    Raises
    ------
    GPUUnavailable
        When no GPU context can be made (no EGL, a worker thread).
    """
    global _context
    if _context:
        return
    try:
        if bpy.app.background:
            _probe()
            if hasattr(gpu, "init"):
                gpu.init()
            else:
                _workbench_render()
        gpu.types.GPUTexture((1, 1), format="R32F")
    except (SystemError, RuntimeError) as error:
        raise GPUUnavailable(f"no GPU context ({error})") from error
    _context = True


_PROBE = """
import bpy, gpu
if hasattr(gpu, "init"):
    gpu.init()
else:
    render = bpy.context.scene.render
    render.engine = "BLENDER_WORKBENCH"
    render.resolution_x = render.resolution_y = 4
    bpy.ops.render.render()
gpu.types.GPUTexture((1, 1), format="R32F")
"""
"""What :func:`ensure_context` does in background mode, for a process of its own."""


def _probe():
    """Make a GPU context in another Blender process first: without EGL, making one crashes
    Blender (a segmentation fault, not an exception), which must not take this process down.

    Raises
    ------
    RuntimeError
        When that process fails.
    """
    if bpy.app.binary_path:  # Blender
        command = [bpy.app.binary_path, "--background", "--factory-startup",
                   "--python-exit-code", "1", "--python-expr", _PROBE]
    else:  # the bpy module
        command = [sys.executable, "-c", _PROBE]
    try:
        run = subprocess.run(command, capture_output=True, text=True, timeout=300)
    except (OSError, subprocess.TimeoutExpired) as error:
        raise RuntimeError(f"a test process could not run: {error}") from error
    if run.returncode != 0:
        raise RuntimeError(f"a test process failed with exit code {run.returncode}")


def _workbench_render():
    """Render a 4x4 Workbench image of a temporary scene with a temporary camera: Blender 4.5
    keeps the GPU context it makes for the rest of the process."""
    scene = bpy.data.scenes.new("VolumeEVM GPU context")
    camera_data = bpy.data.cameras.new("VolumeEVM GPU context")
    camera = bpy.data.objects.new("VolumeEVM GPU context", camera_data)
    try:
        scene.collection.objects.link(camera)
        scene.camera = camera
        scene.render.engine = "BLENDER_WORKBENCH"
        scene.render.resolution_x = scene.render.resolution_y = 4
        scene.render.resolution_percentage = 100
        bpy.ops.render.render(scene=scene.name)
    finally:
        bpy.data.objects.remove(camera)
        bpy.data.cameras.remove(camera_data)
        bpy.data.scenes.remove(scene)
