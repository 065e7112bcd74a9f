"""Runtime caches (Python memory, never saved in the .blend).

- Dense volumes between import and build, keyed by the volume object's ``volumeevm.uid``.
  When a volume is missing (the .blend was reopened, Blender restarted), Build re-reads the
  object's ``source_path``.
- Loaded VolumeEVMs keyed by the absolute path of their ``.vevm`` file: a path names one build,
  so undo (which restores an older ``vevm_path``) finds the older VolumeEVM again.
- A status line per volume object for problems found when a .blend is opened (missing or
  corrupt sidecar), shown in the sidebar.
"""

import uuid

_volumes = {}
_vevms = {}
_status = {}


def new_uid():
    """A fresh key for a volume object."""
    return uuid.uuid4().hex


def volume(uid):
    """The cached dense :class:`Volume` of a volume object, or None."""
    return _volumes.get(uid)


def put_volume(uid, vol):
    _volumes[uid] = vol


def vevm(path):
    """The cached VolumeEVM of a sidecar (absolute path string), or None."""
    return _vevms.get(str(path))


def put_vevm(path, vevm_):
    _vevms[str(path)] = vevm_


def status(uid):
    """A problem found with a volume object's sidecar ("" if none)."""
    return _status.get(uid, "")


def set_status(uid, text):
    if text:
        _status[uid] = text
    else:
        _status.pop(uid, None)


def forget_except(uids):
    """Drop cached volumes and statuses of objects that no longer exist."""
    for store in (_volumes, _status):
        for key in [k for k in store if k not in uids]:
            del store[key]


def clear():
    """Forget everything (a different .blend was opened)."""
    _volumes.clear()
    _vevms.clear()
    _status.clear()
