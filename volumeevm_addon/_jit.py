"""Compiled kernels: the core's hot loops, compiled by Numba on first use.

A kernel is a plain Python function of loops over NumPy arrays, decorated with :func:`kernel`
in the module it serves. Numba is imported when the first kernel is called, not before, so
importing ``volumeevm_addon`` (and registering the Blender add-on) stays instant. Every kernel
is compiled with ``nogil=True`` (a Blender job thread running one leaves the interface free) and
``cache=True``: the machine code is kept on disk and later sessions load it instead of compiling
again.

The disk cache lives outside the package, whose folder may be read-only or replaced on update:
by default in the platform's user cache (``~/.cache/volumeevm/numba`` on Linux,
``~/Library/Caches/volumeevm/numba`` on macOS, ``%LOCALAPPDATA%\\volumeevm\\numba`` on Windows).
Blender's side moves it into the extension's user folder at registration::

    set_kernel_cache_dir(bpy.utils.extension_path_user(__package__, path="numba", create=True))

Only kernels compiled after the call use the new folder, so it is called before the first one
runs. The setting is this package's own: other Numba users in the process keep theirs. Inside
that folder the kernels go in a subfolder named by the package's import name (plain Python
imports ``volumeevm_addon``, Blender ``bl_ext.<repository>.volumeevm.volumeevm_addon``: a cached
kernel refers to the kernels it calls by module name), and in it one named by a digest of all
the package's modules; the subfolders of other digests are removed once unused for a day (not
sooner: another Blender or script may be running other sources of the package right now, and
removing its folder while it compiles breaks its next cache write). Numba checks a cached
kernel against its own file only, not against the kernels and constants it takes from other
modules (a kernel's globals are frozen into its machine code), so any edit or update of the
package starts afresh.

All cores: :func:`parallel_map` runs independent kernel calls (chunks of planes, of polygons) on
the calling thread and a pool of threads, which run at once because kernels release the GIL.
Each call returns its own arrays and the caller joins them in task order, so results never
depend on the number of threads; chunks are cut by the data's size, not by the thread count.
:func:`set_kernel_threads` sets that number (all cores by default; Blender's side passes its
render threads setting). Plain Python threads rather than Numba's ``parallel=True`` keep a
chunk's output free in size, and leave Numba's own thread pool (whose fallback, ``workqueue``,
may not be entered from two threads at once) out of the way.

The first call of a kernel in a session either loads it from the disk cache (milliseconds) or
compiles it (seconds, once per machine and version). :func:`set_kernel_compile_hook` installs a
function called just before that happens, for a progress message such as "compiling
VolumeEVM's Numba kernels (first use only)".
"""

import functools
import hashlib
import os
import shutil
import sys
import threading
import time
from pathlib import Path

from ._errors import VolumeEVMError

_settings = {"cache_dir": None, "threads": None, "hook": None}
_lock = threading.Lock()
_pool = {"threads": 0, "executor": None}
_worker = threading.local()  # ``busy`` on the pool's threads: a map from there runs serially


def default_cache_dir():
    """The platform's user cache folder for compiled kernels (see the module docstring)."""
    if sys.platform == "win32":
        base = Path(os.environ.get("LOCALAPPDATA") or Path.home() / "AppData" / "Local")
    elif sys.platform == "darwin":
        base = Path.home() / "Library" / "Caches"
    else:
        base = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache")
    return base / "volumeevm" / "numba"


def set_kernel_cache_dir(path):
    """Keep compiled kernels in the folder ``path`` (made when first written).

    Call it before the first kernel runs: kernels already loaded keep their folder. Blender's
    side calls it at registration with the extension's user folder, so that compiled code never
    lands in the add-on's own (possibly read-only, replaced on update) folder, and gives the
    previous folder back when the extension is disabled.

    Parameters
    ----------
    path : str or os.PathLike or None
        The folder; a subfolder per import name and kernel version is made inside it. None: the
        platform's user cache (:func:`default_cache_dir`), the default.

    Returns
    -------
    pathlib.Path or None
        The folder set before (None: the default), to restore it later.

    Raises
    ------
    VolumeEVMError
        If ``path`` is neither None nor a path (``str`` or ``os.PathLike``), or is empty.
    """
    if path is not None and (not isinstance(path, (str, os.PathLike)) or not os.fspath(path)):
        raise VolumeEVMError(f"kernel cache dir must be a folder path or None, got {path!r}")
    previous = _settings["cache_dir"]
    _settings["cache_dir"] = None if path is None else Path(path)
    return previous


def set_kernel_threads(count):
    """Run kernels on up to ``count`` threads at once.

    Results never depend on the count: it changes only the speed. Blender's side passes its
    render threads setting.

    Parameters
    ----------
    count : int or None
        Threads to use; ``None`` (the default) means one per core.

    Returns
    -------
    int or None
        The previous setting, so that a caller can restore it.

    Raises
    ------
    VolumeEVMError
        If ``count`` is neither ``None`` nor a positive integer.
    """
    if count is not None and (isinstance(count, bool) or not isinstance(count, int) or count < 1):
        raise VolumeEVMError(f"kernel threads must be a positive integer or None, got {count!r}")
    previous = _settings["threads"]
    _settings["threads"] = count
    return previous


def set_kernel_compile_hook(hook):
    """Call ``hook(name)`` just before a kernel is first loaded or compiled in this session.

    It runs on the thread calling the kernel (a worker of :func:`parallel_map`, maybe several
    at once), before the wait: a hook should only set a progress message such as "compiling
    VolumeEVM's Numba kernels (first use only)".

    Parameters
    ----------
    hook : callable or None
        Called with the kernel's name; ``None`` removes the hook.

    Returns
    -------
    callable or None
        The hook set before (to put back afterwards, as :func:`set_kernel_threads` returns
        the count before).

    Raises
    ------
    VolumeEVMError
        If ``hook`` is neither callable nor ``None``.
    """
    if hook is not None and not callable(hook):
        raise VolumeEVMError(f"kernel compile hook must be callable or None, got {hook!r}")
    previous, _settings["hook"] = _settings["hook"], hook
    return previous


def kernel_threads():
    """The number of threads kernels run on.

    Returns
    -------
    int
        The count given to :func:`set_kernel_threads`, else the cores this process may use.
    """
    if _settings["threads"] is not None:
        return _settings["threads"]
    cores = os.sched_getaffinity(0) if hasattr(os, "sched_getaffinity") else None
    return len(cores) if cores else os.cpu_count() or 1


def parallel_map(function, tasks):
    """``[function(*task) for task in tasks]``, the calls spread over :func:`kernel_threads`
    threads; results in task order. One task, one thread, or a call from inside a task (which
    could otherwise wait for a pool it fills) runs on the calling thread.

    The calling thread and ``threads - 1`` pool threads each take the next task not taken yet
    until none is left: one hand-over per thread rather than per task."""
    tasks = list(tasks)
    threads = min(kernel_threads(), len(tasks))
    if threads <= 1 or getattr(_worker, "busy", False):
        return [function(*task) for task in tasks]
    from concurrent.futures import ThreadPoolExecutor  # here: it costs the package's import 10 ms

    with _lock:
        if _pool["threads"] < threads - 1:
            if _pool["executor"] is not None:
                _pool["executor"].shutdown(wait=False)
            _pool["executor"] = ThreadPoolExecutor(threads - 1, thread_name_prefix="volumeevm")
            _pool["threads"] = threads - 1
        executor = _pool["executor"]
    results = [None] * len(tasks)
    pending = iter(range(len(tasks)))
    taking = threading.Lock()

    def work():
        _worker.busy = True
        while True:
            with taking:
                index = next(pending, None)
            if index is None:
                return
            results[index] = function(*tasks[index])

    helpers = [executor.submit(work) for _ in range(threads - 1)]
    try:
        work()
    finally:
        _worker.busy = False
        for helper in helpers:
            helper.exception()  # waits for it; its error, if any, is raised below
    for helper in helpers:
        helper.result()
    return results


STALE_SECONDS = 24 * 3600
"""A kernel folder of other sources is removed when nothing was written in it for this long."""


@functools.cache
def _cache_folder(parent):
    """The subfolder of ``parent`` for this import of the package's sources (see the module
    docstring); removes the subfolders of other sources not written for :data:`STALE_SECONDS`."""
    package = Path(__file__).parent
    digest = hashlib.sha256()
    for path in sorted(package.rglob("*.py")):
        digest.update(str(path.relative_to(package)).encode() + b"\0" + path.read_bytes())
    name = digest.hexdigest()[:16]
    imported = parent / __name__.rpartition(".")[0]
    if imported.is_dir():
        for old in imported.iterdir():
            if (old.name != name and len(old.name) == 16
                    and set(old.name) <= set("0123456789abcdef")):
                try:
                    stale = time.time() - old.stat().st_mtime > STALE_SECONDS
                except OSError:  # removed meanwhile by another process
                    continue
                if stale:
                    shutil.rmtree(old, ignore_errors=True)
    return imported / name


@functools.cache
def _numba():
    """Import Numba, and teach it that a :class:`Kernel` inside a kernel is its dispatcher."""
    import numba
    from numba.extending import typeof_impl

    @typeof_impl.register(Kernel)
    def _typeof_kernel(value, context):
        return numba.typeof(value.dispatcher)

    return numba


class Kernel:
    """A function compiled by Numba on its first call; see :func:`kernel`."""

    def __init__(self, function):
        functools.update_wrapper(self, function)
        self._dispatcher = None
        self._called = False

    @property
    def dispatcher(self):
        """The Numba dispatcher, made on first use with this package's cache folder."""
        if self._dispatcher is None:
            with _lock:
                if self._dispatcher is None:
                    numba = _numba()
                    # Numba reads its cache folder when a dispatcher is made: set it for ours only.
                    shared = numba.config.CACHE_DIR
                    numba.config.CACHE_DIR = str(_cache_folder(_settings["cache_dir"]
                                                               or default_cache_dir()))
                    try:
                        self._dispatcher = numba.njit(nogil=True, cache=True)(self.__wrapped__)
                    finally:
                        numba.config.CACHE_DIR = shared
        return self._dispatcher

    @property
    def compiled(self):
        """True once the kernel has been loaded or compiled in this session."""
        return self._dispatcher is not None and bool(self._dispatcher.signatures)

    def __call__(self, *args):
        if self._called:
            return self._dispatcher(*args)
        if not self.dispatcher.signatures and _settings["hook"] is not None:
            _settings["hook"](self.__name__)
        result = self._dispatcher(*args)
        self._called = True
        return result

    def __repr__(self):
        return f"<kernel {self.__module__}.{self.__qualname__}>"


def kernel(function):
    """Decorate a function of loops over NumPy arrays as a compiled kernel.

    Numba is not imported until the first call. A kernel may call other kernels.
    """
    return Kernel(function)
