"""Atomic file writes: the one way every file of ours is written.

A file is written to a temporary name in its target folder and renamed into place, so a reader
never sees half a file and a failed write leaves the old file as it was; an existing file is
replaced only when the caller says so.
"""

import os
import tempfile
from pathlib import Path

from ._errors import VolumeEVMError


def atomic_target(path, *, overwrite):
    """Check that ``path`` may be written and make its folder; returns it as a ``Path``.

    Raises
    ------
    VolumeEVMError
        If ``path`` names a folder, or exists and ``overwrite`` is False.
    """
    path = Path(path)
    if path.is_dir():
        raise VolumeEVMError(f"{path}: is a folder, not a file name")
    if path.exists() and not overwrite:
        raise VolumeEVMError(f"{path}: exists; choose another name or allow overwriting")
    path.parent.mkdir(parents=True, exist_ok=True)
    return path


def write_atomically(path, write, *, overwrite=False):
    """Call ``write(temporary)`` on a new file beside ``path``, then rename it onto ``path``.

    The temporary file keeps ``path``'s suffix (some writers choose the format by it) and gets
    the usual file mode. Returns ``path`` as a ``Path``.
    """
    path = atomic_target(path, overwrite=overwrite)
    handle, temporary = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=path.suffix, dir=path.parent)
    os.close(handle)
    temporary = Path(temporary)
    try:
        write(temporary)
        mask = os.umask(0o022)
        os.umask(mask)
        os.chmod(temporary, 0o666 & ~mask)  # mkstemp makes 0600
        os.replace(temporary, path)
    except BaseException:
        temporary.unlink(missing_ok=True)
        raise
    return path
