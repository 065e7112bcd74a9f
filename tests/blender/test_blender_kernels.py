"""The core's compiled kernels inside Blender (``blender/kernels.py``), real bpy, both lines.

While a job's steps run (the synchronous path of scripts and ``--background``, and the modal path
of the UI), kernels use the scene's render threads setting (Fixed: its count; Auto-detect: all
cores) and the count from before comes back afterwards; a kernel's first use in the session
shows "compiling VolumeEVM's Numba kernels (first use only)" once in the job's progress (a
progress line, or the progress text the UI draws). The source tree is no installed extension:
registering it keeps the core's default cache folder. The installed extension (its cache in the
extension's user folder, no Numba imported by enabling it) is tested in ``test_blender_extension``.
"""

import bpy
import numpy as np
import pytest
from test_blender_ui import _Context, _driver, _ticks

FIRST_USE = "compiling VolumeEVM's Numba kernels (first use only)"


def _sum_of(values):  # a kernel of this module: each test makes a new one, never called before
    total = 0.0
    for v in values:
        total += v
    return total


def _steps(ext, seen):
    """A job's steps: one calls a fresh kernel and records the threads and progress it sees."""
    fresh_kernel = ext.volumeevm_addon._jit.kernel(_sum_of)  # white-box: a kernel never run
    jobs = ext.blender.jobs

    def steps():
        yield 0.5, "summing"
        assert fresh_kernel(np.arange(4.0)) == 6.0
        seen.append((ext.volumeevm_addon.kernel_threads(),
                     jobs.CURRENT.text if jobs.CURRENT is not None else None))
        yield 0.75, "summing again"
        assert fresh_kernel(np.arange(5.0)) == 10.0
        return "done"

    return steps()


def _scene_threads(mode, count=3):
    render = bpy.context.scene.render
    render.threads_mode = mode
    if mode == "FIXED":
        render.threads = count


@pytest.mark.parametrize("mode", ["FIXED", "AUTO"])
def test_a_script_job_uses_the_render_threads_and_prints_the_first_use(ext, capsys, mode):
    core = ext.volumeevm_addon
    _scene_threads(mode)
    before = core.set_kernel_threads(5)  # what a caller had: it comes back after the job
    try:
        seen = []
        assert ext.blender.jobs.drain(_steps(ext, seen), verbose=True) == "done"
        assert core.kernel_threads() == 5
    finally:
        core.set_kernel_threads(before)
    cores = core.kernel_threads()  # all cores (the default is back)
    assert seen == [(3 if mode == "FIXED" else cores, None)]
    lines = capsys.readouterr().out.splitlines()
    assert lines == ["[volumeevm]  50% summing", f"[volumeevm]  50% {FIRST_USE}",
                     "[volumeevm]  75% summing again", "[volumeevm] 100% done"]


def test_a_ui_job_shows_the_first_use_in_its_progress_text(ext):
    core, jobs = ext.volumeevm_addon, ext.blender.jobs
    _scene_threads("FIXED", 2)
    seen = []
    op = _driver(ext, lambda: jobs.Job("Sum", _steps(ext, seen), lambda value: value))
    context = _Context()
    assert op.start(context) == {"RUNNING_MODAL"}
    assert _ticks(op, context) == {"FINISHED"}
    assert seen == [(2, FIRST_USE)]  # the worker's kernels ran on the scene's threads
    assert jobs.CURRENT is None
    assert core.set_kernel_threads(None) is None  # the default (all cores) is back


def test_from_source_the_default_cache_folder_stays(ext):
    """The tests load the source tree as package ``volumeevm``: no extension, so Blender has
    no user folder for it and registering left the core's default cache folder in place."""
    with pytest.raises(ValueError):
        bpy.utils.extension_path_user(ext.__name__, path="numba")
    assert ext.volumeevm_addon._jit._settings["cache_dir"] is None
