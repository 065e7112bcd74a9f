"""Memory checked before it is spent: how much is free, and refusing work that would not fit.

Before a step that allocates in proportion to the data (reading a volume, building a VolumeEVM,
making a mesh, rendering) the caller estimates the step's peak from the sizes involved and calls
:func:`check_memory`. When the estimate exceeds what the machine has free, the step is refused
with a :class:`~volumeevm_addon.VolumeEVMError` that says how much is needed, how much
is free and what to do, instead of failing half-way with a bare ``MemoryError`` (or the system
swapping until it stalls).

"Free" is the memory the operating system says it can give without swapping (``MemAvailable``
on Linux, ``vm_stat`` free + inactive pages on macOS, ``ullAvailPhys`` on Windows). A budget can
lower it: the environment variable ``VOLUMEEVM_MEMORY_LIMIT`` (bytes, or with a suffix K, M or
G: ``"512M"``) caps it, which is how the tests force a small budget without exhausting the
machine, and how a user keeps VolumeEVM to a share of a shared machine. Where the free memory
cannot be read and no budget is set, nothing is refused.
"""

import ctypes
import os
import subprocess
import sys

from ._errors import VolumeEVMError

#: Environment variable capping the memory VolumeEVM plans to use (bytes, or K/M/G suffix).
LIMIT_VARIABLE = "VOLUMEEVM_MEMORY_LIMIT"

_SUFFIXES = {"": 1, "K": 1 << 10, "M": 1 << 20, "G": 1 << 30, "T": 1 << 40}


def memory_limit():
    """The budget set by :data:`LIMIT_VARIABLE` in bytes, or ``None`` when it is not set.

    Raises
    ------
    VolumeEVMError
        If the variable is set but is not a positive size such as ``1073741824`` or ``"512M"``.
    """
    text = os.environ.get(LIMIT_VARIABLE, "").strip()
    if not text:
        return None
    number = text.rstrip("KMGTkmgtBb")
    suffix = text[len(number):].upper().rstrip("B")
    try:
        value = float(number) * _SUFFIXES[suffix]
    except (ValueError, KeyError):
        value = float("nan")
    if not value > 0 or value == float("inf"):
        raise VolumeEVMError(f"{LIMIT_VARIABLE}={text!r}: expected a positive size such as 512M "
                             f"or 2G")
    return int(value)


def available_memory():
    """Bytes this process may still allocate: free memory, capped by :func:`memory_limit`.

    Returns
    -------
    int or None
        ``None`` when the operating system does not tell and no budget is set.

    Raises
    ------
    VolumeEVMError
        If :data:`LIMIT_VARIABLE` is set but is not a size (:func:`memory_limit`).
    """
    free = _system_available()
    limit = memory_limit()
    if limit is None:
        return free
    return limit if free is None else min(free, limit)


def check_memory(needed, what, *, source, advice=""):
    """Refuse a step whose estimated peak ``needed`` (bytes) exceeds :func:`available_memory`.

    Parameters
    ----------
    needed : int
        Estimated peak allocation of the step, in bytes.
    what : str
        The step, for the message ("reading the volume", "building the VolumeEVM").
    source : str
        The file or parameter the step works on, named first in the message.
    advice : str, optional
        What the user can do instead (crop, a higher threshold, a coarser level).
        ``source`` and ``advice`` are keyword-only.

    Raises
    ------
    VolumeEVMError
        When the step would need more than is available.
    """
    free = available_memory()
    if free is None or needed <= free:
        return
    tail = f"; {advice}" if advice else ""
    raise VolumeEVMError(
        f"{source}: {what} needs about {format_bytes(needed)} of memory but only "
        f"{format_bytes(free)} is available{tail}"
    )


def format_bytes(count):
    """``count`` bytes for a message, in bytes, KiB, MiB or GiB (``"3.2 GiB"``)."""
    value = float(count)
    if value < 1024:
        return f"{value:.0f} bytes"
    for unit in ("KiB", "MiB"):
        value /= 1024
        if value < 1024:
            return f"{value:.1f} {unit}"
    return f"{value / 1024:.1f} GiB"


def _system_available():
    try:
        if sys.platform.startswith("linux"):
            return _linux_available()
        if sys.platform == "darwin":
            return _macos_available()
        if sys.platform == "win32":
            return _windows_available()
    except (OSError, ValueError, subprocess.SubprocessError):
        return None
    return None


def _linux_available():
    with open("/proc/meminfo", encoding="ascii") as meminfo:
        for line in meminfo:
            if line.startswith("MemAvailable:"):
                return int(line.split()[1]) * 1024
    return None


def _macos_available():
    text = subprocess.run(["vm_stat"], capture_output=True, text=True, check=True, timeout=5).stdout
    lines = text.splitlines()
    page = int(lines[0].split("page size of")[1].split()[0])
    pages = {}
    for line in lines[1:]:
        name, _, count = line.partition(":")
        if count.strip().rstrip(".").isdigit():
            pages[name.strip()] = int(count.strip().rstrip("."))
    return page * (pages.get("Pages free", 0) + pages.get("Pages inactive", 0)
                   + pages.get("Pages speculative", 0))


def _windows_available():
    class MemoryStatus(ctypes.Structure):
        _fields_ = [("dwLength", ctypes.c_ulong), ("dwMemoryLoad", ctypes.c_ulong),
                    ("ullTotalPhys", ctypes.c_ulonglong), ("ullAvailPhys", ctypes.c_ulonglong),
                    ("ullTotalPageFile", ctypes.c_ulonglong),
                    ("ullAvailPageFile", ctypes.c_ulonglong),
                    ("ullTotalVirtual", ctypes.c_ulonglong),
                    ("ullAvailVirtual", ctypes.c_ulonglong),
                    ("ullAvailExtendedVirtual", ctypes.c_ulonglong)]

    status = MemoryStatus()
    status.dwLength = ctypes.sizeof(MemoryStatus)
    if not ctypes.windll.kernel32.GlobalMemoryStatusEx(ctypes.byref(status)):
        return None
    return int(status.ullAvailPhys)
