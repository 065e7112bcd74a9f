"""Atomic file writes: the one way every file of ours is written (``.vevm``, EXR, PNG).

A file is written to a temporary name in its target folder and only then published under its
name, so a reader never sees half a file and a failed write leaves the old file as it was; no
temporary is left behind.

An existing file is replaced only when the caller says so (``overwrite=True``: an atomic
``os.replace``). Otherwise the name is checked before the (possibly slow) write, and the
publication itself refuses to replace a file: the temporary gets a hard link under the final name
(``os.link`` fails when the name exists, atomically), so of two saves racing to one new name
exactly one wins and the other gets an error, never a silently replaced file. On a file system
without hard links (FAT, exFAT, some network shares) the name is claimed with an exclusive
create (``O_EXCL``) and the temporary renamed onto the claimed, still empty, file: as safe
against racing saves, though for that instant a reader could see an empty file.

Any ``OSError`` of the file system (disk full, permission denied, read-only file system, a
path under a file) becomes a :class:`~volumeevm_addon.VolumeEVMError` naming the path.
"""

import contextlib
import errno
import os
import tempfile
from pathlib import Path

from ._errors import VolumeEVMError

#: What the user can do about the common write failures, by ``errno``.
_ADVICE = {
    errno.ENOSPC: "the disk is full; free some space or choose another disk",
    errno.EDQUOT: "the disk quota is exhausted; free some space or choose another disk",
    errno.EACCES: "choose a folder you may write to",
    errno.EPERM: "choose a folder you may write to",
    errno.EROFS: "the file system is read-only; choose another folder",
}


def atomic_target(path, *, overwrite):
    """Check that ``path`` may be written and make its folder.

    Writers call it before slow work (a render, an encoding), so a name that exists fails
    at once rather than after the work; :func:`write_atomically` calls it too.

    Parameters
    ----------
    path : str or path-like
        The file to write.
    overwrite : bool
        Whether an existing file may be replaced (keyword-only, required).

    Returns
    -------
    Path
        ``path`` as a :class:`pathlib.Path`.

    Raises
    ------
    VolumeEVMError
        If ``path`` names a folder, exists and ``overwrite`` is False, or its folder cannot be
        made (a file of that name, no permission).
    """
    path = Path(os.fsdecode(path))
    if path.is_dir():
        raise VolumeEVMError(f"{path}: is a folder, not a file name")
    if path.exists() and not overwrite:
        raise _exists(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
    except OSError as error:
        raise _write_error(path, error, f"cannot make its folder {path.parent}") from error
    return path


def write_atomically(path, write, *, overwrite=False):
    """Call ``write(temporary)`` on a new file beside ``path``, then publish it as ``path``.

    Parameters
    ----------
    path : str or path-like
        The file to write.
    write : callable
        Writes the whole content to the ``Path`` it is given (some writers choose the format by
        the suffix, which the temporary keeps).
    overwrite : bool
        Replace an existing file. When False, a file at ``path`` (even one that appears while
        ``write`` runs) is never replaced.

    Returns
    -------
    Path
        ``path``, with the usual file mode (``0666`` less the umask).

    Raises
    ------
    VolumeEVMError
        If the file exists and ``overwrite`` is False, or the file system refuses the write; the
        old file (if any) is then as it was and no temporary is left.
    """
    path = atomic_target(path, overwrite=overwrite)
    try:
        # A short prefix: a long file name plus the random part must still fit the name limit.
        handle, temporary = tempfile.mkstemp(prefix=f".{path.stem[:64]}.", suffix=path.suffix,
                                             dir=path.parent)
    except OSError as error:
        raise _write_error(path, error, "cannot create a file in its folder") from error
    os.close(handle)
    temporary = Path(temporary)
    try:
        write(temporary)
        mask = os.umask(0o022)
        os.umask(mask)
        os.chmod(temporary, 0o666 & ~mask)  # mkstemp makes 0600
        if overwrite:
            os.replace(temporary, path)
        else:
            _publish_new(temporary, path)
    except FileExistsError as error:
        raise _exists(path) from error
    except OSError as error:
        raise _write_error(path, error, "could not write the file") from error
    finally:
        with contextlib.suppress(OSError):
            temporary.unlink(missing_ok=True)
    return path


def _publish_new(temporary, path):
    """Give ``temporary`` the name ``path`` unless ``path`` exists (``FileExistsError``)."""
    try:
        os.link(temporary, path)
        return
    except FileExistsError:
        raise
    except OSError:
        pass  # no hard links on this file system: claim the name instead
    os.close(os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600))
    try:
        os.replace(temporary, path)
    except OSError:
        path.unlink(missing_ok=True)  # the empty file we claimed
        raise


def _exists(path):
    return VolumeEVMError(f"{path}: exists; choose another name or allow overwriting")


def _write_error(path, error, what):
    reason = error.strerror or str(error)
    advice = _ADVICE.get(error.errno)
    return VolumeEVMError(f"{path}: {what} ({reason}){'; ' + advice if advice else ''}")
