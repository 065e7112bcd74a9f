"""The compiled-kernel layer: Numba only on first use, its settings, its disk cache, its threads."""

import os
import subprocess
import sys
import textwrap
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from volumeevm_addon import VolumeEVMError, _jit, kernel_threads, set_kernel_threads
from volumeevm_addon.system import set_kernel_cache_dir, set_kernel_compile_hook

REPO = Path(__file__).resolve().parents[1]


def test_importing_the_package_leaves_numba_alone():
    code = "import sys, volumeevm_addon; assert 'numba' not in sys.modules, 'numba imported'"
    subprocess.run([sys.executable, "-c", code], cwd=REPO, check=True)


def test_settings_are_checked_and_threads_restorable():
    for bad in (0, -1, 1.5, True, "2"):
        with pytest.raises(VolumeEVMError,
                           match="^kernel threads must be a positive integer or None"):
            set_kernel_threads(bad)
    for bad in (3, "", b"folder"):
        with pytest.raises(VolumeEVMError, match="^kernel cache dir must be a folder path"):
            set_kernel_cache_dir(bad)
    assert set_kernel_cache_dir("/tmp/volumeevm-kernels") is None  # the default was set
    assert set_kernel_cache_dir(None) == Path("/tmp/volumeevm-kernels")  # the default is back
    assert set_kernel_cache_dir(None) is None
    with pytest.raises(VolumeEVMError, match="^kernel compile hook must be callable or None"):
        set_kernel_compile_hook(5)
    previous = set_kernel_threads(3)
    try:
        assert kernel_threads() == 3
    finally:
        assert set_kernel_threads(previous) == 3
    assert kernel_threads() >= 1


def test_parallel_map_keeps_the_task_order_on_several_threads():
    """The tasks run on the pool's threads and on the calling thread, which takes tasks too."""
    seen = set()

    def work(i, j):
        seen.add(threading.current_thread().name)
        return i * j

    previous = set_kernel_threads(4)
    try:
        assert _jit.parallel_map(work, [(i, 2) for i in range(50)]) == [2 * i for i in range(50)]
    finally:
        set_kernel_threads(previous)
    caller = threading.current_thread().name
    assert all(name.startswith("volumeevm") or name == caller for name in seen)


def test_a_map_inside_a_task_runs_on_its_thread():
    """A task that maps again (say, an EVM built inside a parallel task) must not wait for the
    pool it is part of: its map runs serially, on the task's thread."""
    previous = set_kernel_threads(2)
    try:
        def task(i):
            return _jit.parallel_map(lambda j: (i, j, threading.current_thread().name),
                                     [(j,) for j in range(3)])

        inner = _jit.parallel_map(task, [(i,) for i in range(4)])
    finally:
        set_kernel_threads(previous)
    assert ([[(i, j) for i, j, _ in row] for row in inner]
            == [[(i, j) for j in range(3)] for i in range(4)])
    assert all(len({name for _, _, name in row}) == 1 for row in inner)


@_jit.kernel
def _total(values):
    total = 0.0
    for v in values:
        total += v
    return total


@_jit.kernel
def _twice_total(values):
    return 2 * _total(values)  # a kernel calling a kernel


def test_compile_hook_runs_before_the_first_call_only():
    names = []
    before = set_kernel_compile_hook(names.append)
    try:
        assert _twice_total(np.arange(4.0)) == 12.0
        assert _twice_total(np.arange(5.0)) == 20.0
    finally:
        assert set_kernel_compile_hook(before) == names.append  # the hook set: given back
    assert names == ["_twice_total"] and _twice_total.compiled


def test_kernels_are_cached_in_the_chosen_folder(tmp_path):
    """A kernel compiled in one process is loaded from the folder set_kernel_cache_dir names
    (in a subfolder for these sources) by the next."""
    module = tmp_path / "cached_kernel.py"
    module.write_text(textwrap.dedent("""
        import sys
        import numpy as np
        sys.path.insert(0, sys.argv[1])
        import volumeevm_addon
        from volumeevm_addon._jit import kernel

        @kernel
        def cube(x):
            return x * x * x

        volumeevm_addon.system.set_kernel_cache_dir(sys.argv[2])
        assert cube(np.int64(3)) == 27
        stats = cube.dispatcher.stats
        print(sum(stats.cache_hits.values()), sum(stats.cache_misses.values()))
    """))
    cache = tmp_path / "cache"
    runs = [subprocess.run([sys.executable, str(module), str(REPO), str(cache)], check=True,
                           capture_output=True, text=True).stdout.split() for _ in range(2)]
    assert runs[0] == ["0", "1"] and runs[1] == ["1", "0"]  # compiled, then loaded
    (folder,) = (cache / "volumeevm_addon").iterdir()
    assert len(folder.name) == 16 and any(folder.rglob("*.nbi"))


def test_kernel_folders_of_other_sources_are_removed_only_when_unused_for_a_day(tmp_path):
    """Another Blender may be running other sources of the package now: its kernel folder stays
    while it is in use (written within a day), and goes once stale."""
    package = tmp_path / "volumeevm_addon"
    fresh, stale, other = (package / name for name in ("0123456789abcdef", "fedcba9876543210",
                                                       "not-a-digest"))
    for folder in (fresh, stale, other):
        folder.mkdir(parents=True)
    long_ago = time.time() - _jit.STALE_SECONDS - 60
    os.utime(stale, (long_ago, long_ago))
    os.utime(other, (long_ago, long_ago))
    ours = _jit._cache_folder.__wrapped__(tmp_path)  # white-box: the uncached function
    assert ours.parent == package and ours.name not in (fresh.name, stale.name)
    assert fresh.is_dir() and not stale.exists() and other.is_dir()
