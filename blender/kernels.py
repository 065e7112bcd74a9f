"""The core's compiled kernels inside Blender: their cache folder, their threads, their first use.

The core compiles its hot loops with Numba the first time each runs, and keeps the machine code
on disk (``volumeevm_addon.system.set_kernel_cache_dir``). Blender's side decides three things:

- **Where the cache lives**: :func:`register` puts it in the extension's user folder,
  ``bpy.utils.extension_path_user(<package>, path="numba")``, which Blender keeps across
  updates of the extension (the add-on's own folder is replaced on update and may be
  read-only). Loaded from source rather than installed (the tests, the demo), the package is no
  extension and the core's default stays: the platform's user cache.
- **How many threads**: while a job runs (:func:`job_settings`), kernels use the scene's render
  threads setting (Render Properties > Performance > Threads: Fixed gives the count, Auto-detect
  all cores); the previous count comes back when the job ends. Results never depend on it.
- **What the user sees on first use**: compiling takes seconds, once per machine and version.
  During a job, the first kernel loaded or compiled in the session shows :data:`FIRST_USE` in
  the job's progress, once per job. The core calls the hook on the thread running the kernel
  (maybe a worker), so the hook only hands the text to the job's ``show`` (which sets the
  progress text the UI reads, or prints a progress line under ``--background``).

Registration imports none of this work: Numba is imported by the first kernel call.
"""

import threading
from contextlib import contextmanager

import bpy

from ..volumeevm_addon import set_kernel_threads
from ..volumeevm_addon.system import set_kernel_cache_dir, set_kernel_compile_hook

#: The progress text while kernels are loaded or compiled for the first time in a session.
FIRST_USE = "compiling VolumeEVM's Numba kernels (first use only)"

_before = []  # the cache folder register() replaced, given back by unregister()


def register(package):
    """Keep compiled kernels in the user folder of the extension ``package`` (its
    ``__package__``); nothing changes when ``package`` is not an installed extension."""
    try:
        folder = bpy.utils.extension_path_user(package, path="numba", create=True)
    except ValueError:  # loaded from source: not an extension, the core's default cache stays
        return
    if folder:  # "" when Blender could not make the folder (it printed why)
        _before.append(set_kernel_cache_dir(folder))


def unregister():
    """Give the kernel cache folder back as it was before :func:`register` (the core is a
    process-wide module: another user of it in this Blender keeps its own choice)."""
    while _before:
        set_kernel_cache_dir(_before.pop())


def render_threads(scene):
    """The kernel thread count the scene's render threads setting asks for (None: all cores)."""
    if scene is not None and scene.render.threads_mode == "FIXED":
        return scene.render.threads
    return None


def _first_use_notice(show):
    """A compile hook calling ``show(FIRST_USE)`` once, from whichever thread gets there first."""
    lock = threading.Lock()
    shown = []

    def hook(_kernel_name):
        with lock:
            if shown:
                return
            shown.append(True)
        show(FIRST_USE)

    return hook


@contextmanager
def job_settings(show):
    """Run a job's steps with kernels on the context scene's render threads, calling
    ``show(FIRST_USE)`` once if a kernel is loaded or compiled for the first time meanwhile.
    Enter it on the main thread; the previous thread count and hook come back on exit."""
    threads = set_kernel_threads(render_threads(bpy.context.scene))
    hook = set_kernel_compile_hook(_first_use_notice(show))
    try:
        yield
    finally:
        set_kernel_threads(threads)
        set_kernel_compile_hook(hook)
