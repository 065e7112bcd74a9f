"""Where VolumeEVM sidecar files live, and the handlers that keep them with the .blend.

- Build writes every new VolumeEVM to a fresh file in this session's temporary folder
  (``<tmp>/volumeevm-XXXX/<uid>-<n>.vevm``) and stores that absolute path on the volume object.
  Earlier files stay until Blender exits, so undo (which restores an older path) still finds its
  VolumeEVM, and a cancelled or failed build leaves the previous file untouched.
- On save (``save_pre``) each volume object's VolumeEVM is copied atomically to
  ``<blend folder>/<blend name>_volumeevm/<object name>.vevm`` and its path rewritten to the
  ``//``-relative form before Blender writes the file, so the saved .blend names the sidecar
  beside it. "Save As" to another folder copies it again; "Save Copy" puts the paths back
  afterwards (``save_post``). Only ``.vevm`` files in that folder are ever replaced; a foreign
  file of the same name is left alone and the sidecar gets another name.
- On open (``load_post``) every volume object's sidecar is resolved and loaded into the runtime
  cache; a missing or corrupt one is reported in the sidebar (build again to fix it).

Nothing is ever written into the add-on's folder.
"""

import atexit
import itertools
import os
import shutil
import tempfile
import zipfile
from pathlib import Path

import bpy

from ..volumeevm_addon import VolumeEVM, VolumeEVMError
from ..volumeevm_addon.system import write_atomically
from . import runtime

_session_dir = None
_counter = itertools.count(1)
_pending = {}  # object name -> (old vevm_path) while a "save copy" is written


def session_dir():
    """This session's temporary folder for sidecars of unsaved builds (made on first use)."""
    global _session_dir
    if _session_dir is None or not _session_dir.is_dir():
        if _session_dir is None:
            atexit.register(_remove_session_dir)  # the session's temporary sidecars go at exit
        _session_dir = Path(tempfile.mkdtemp(prefix="volumeevm-"))
    return _session_dir


def _remove_session_dir():
    if _session_dir is not None:
        shutil.rmtree(_session_dir, ignore_errors=True)


def new_temp_path(uid):
    """A path for a new sidecar in the session folder (never an existing file)."""
    return session_dir() / f"{uid}-{next(_counter)}.vevm"


def sidecar_dir(blend_path):
    """``<folder>/<blend name>_volumeevm`` for a .blend path."""
    blend = Path(blend_path)
    return blend.parent / f"{blend.stem}_volumeevm"


def sidecar_target(obj_name, blend_path):
    """Where the sidecar of object ``obj_name`` belongs for a .blend saved at ``blend_path``."""
    return sidecar_dir(blend_path) / f"{bpy.path.clean_name(obj_name)}.vevm"


def is_vevm_file(path):
    """True if ``path`` is a VolumeEVM file (cheap check of the archive's members)."""
    try:
        with zipfile.ZipFile(path) as archive:
            return {"format.npy", "vertices.npy", "table.npy"} <= set(archive.namelist())
    except (OSError, zipfile.BadZipFile):
        return False


def resolve(obj):
    """The existing sidecar file of a volume object, or None.

    The stored path is tried first (``//`` = the .blend's folder); then the default place beside
    the current .blend, for files whose path was lost (e.g. undo past a save).
    """
    stored = obj.volumeevm.vevm_path
    if not stored:
        return None
    path = Path(bpy.path.abspath(stored, library=obj.library))
    if path.is_file():
        return path
    if bpy.data.filepath:
        fallback = sidecar_target(obj.name, bpy.data.filepath)
        if fallback.is_file():
            return fallback
    return None


def load_vevm(obj):
    """The VolumeEVM of a volume object (runtime cache, else its sidecar file).

    Raises
    ------
    VolumeEVMError
        If the object has no VolumeEVM yet or its sidecar is missing or corrupt.
    """
    settings = obj.volumeevm
    if not settings.vevm_path:
        raise VolumeEVMError(f"{obj.name}: no VolumeEVM built yet; build one first")
    path = resolve(obj)
    if path is None:
        raise VolumeEVMError(
            f"{obj.name}: VolumeEVM file {settings.vevm_path!r} not found; build it again")
    cached = runtime.vevm(path)
    if cached is None:
        cached = VolumeEVM.load(path)
        runtime.put_vevm(path, cached)
    return cached


def save_new(uid, vevm):
    """Write a new VolumeEVM to a fresh session file and cache it; returns the path."""
    path = new_temp_path(uid)
    vevm.save(path)
    runtime.put_vevm(path, vevm)
    return path


def _copy_atomic(src, dst):
    write_atomically(dst, lambda temporary: shutil.copyfile(src, temporary), overwrite=True)


def _free_target(obj, blend_path):
    """The sidecar path for ``obj``; another name if a foreign file holds the default one."""
    target = sidecar_target(obj.name, blend_path)
    if target.exists() and not is_vevm_file(target):
        target = target.with_name(f"{target.stem}-{obj.volumeevm.uid[:8]}.vevm")
    return target


def _volume_objects():
    return [o for o in bpy.data.objects
            if o.library is None and o.volumeevm.role == "VOLUME" and o.volumeevm.vevm_path]


@bpy.app.handlers.persistent
def on_save_pre(filepath, *_args):
    """Copy each VolumeEVM beside the .blend being written and store ``//``-relative paths."""
    filepath = filepath or bpy.data.filepath
    if not filepath:
        return
    _pending.clear()
    start = str(Path(filepath).parent)
    for obj in _volume_objects():
        settings = obj.volumeevm
        source = resolve(obj)
        if source is None:
            runtime.set_status(settings.uid, f"VolumeEVM file {settings.vevm_path!r} not found "
                                             f"when saving; build it again")
            continue
        target = _free_target(obj, filepath)
        try:
            if not (target.exists() and os.path.samefile(source, target)):
                _copy_atomic(source, target)
        except OSError as error:
            runtime.set_status(settings.uid, f"could not write the VolumeEVM beside the .blend: "
                                             f"{error}")
            print(f"[volumeevm] {obj.name}: could not write {target}: {error}")
            continue
        cached = runtime.vevm(source)
        if cached is not None:
            runtime.put_vevm(target, cached)
        _pending[obj.name] = settings.vevm_path
        settings.vevm_path = bpy.path.relpath(str(target), start=start)
        runtime.set_status(settings.uid, "")


@bpy.app.handlers.persistent
def on_save_post(filepath, *_args):
    """After "Save Copy" the open file keeps its old sidecar paths."""
    filepath = filepath or bpy.data.filepath
    current = bpy.data.filepath
    is_copy = not current or os.path.normpath(current) != os.path.normpath(filepath)
    if is_copy:
        for name, old in _pending.items():
            obj = bpy.data.objects.get(name)
            if obj is not None:
                obj.volumeevm.vevm_path = old
    _pending.clear()


@bpy.app.handlers.persistent
def on_load_post(*_args):
    """Find every volume object's VolumeEVM again after a .blend is opened."""
    runtime.clear()
    for obj in bpy.data.objects:
        settings = obj.volumeevm
        if settings.role != "VOLUME" or not settings.vevm_path:
            continue
        try:
            load_vevm(obj)
        except VolumeEVMError as error:
            runtime.set_status(settings.uid, str(error))
            print(f"[volumeevm] {error}")


HANDLERS = (("save_pre", on_save_pre), ("save_post", on_save_post), ("load_post", on_load_post))
