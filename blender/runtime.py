"""Runtime caches (Python memory, never saved in the .blend).

- Dense volumes between import and build, keyed by the volume object's ``volumeevm.uid``.
  When a volume is missing (the .blend was reopened, Blender restarted), Build re-reads the
  object's ``source_path``.
- Loaded VolumeEVMs keyed by the absolute path of their ``.vevm`` file: a path names one build,
  so undo (which restores an older ``vevm_path``) finds the older VolumeEVM again.
- A status line per volume object for problems found when a .blend is opened (missing or
  corrupt sidecar), shown in the sidebar.
- The tool stack state of each volume object (:class:`StackState`): its ``EditStack`` with the
  cached result after every entry, the voxelized tools keyed by what they were made from, the
  last result and the surface mesh written last, the last refresh's timing and any problem.
  Keyed by ``(uid, object name)`` (a duplicated volume keeps the uid but has its own stack).
  Undo and redo re-sync it from the object's properties (``tool_stack.py``).
"""

import uuid
from collections import OrderedDict
from dataclasses import dataclass, field

_volumes = {}
_vevms = {}
_status = {}
_stacks = {}

#: Voxelized tools kept per volume (the current entries' tools and a few earlier placements,
#: so undoing a move or dragging a tool back finds them again).
TOOL_CACHE_SIZE = 16


@dataclass
class StackState:
    """What a volume's tool stack keeps between refreshes (never saved in the .blend)."""

    base_path: str = ""  # the sidecar the stack's base was loaded from
    base_digest: str = ""  # content digest of the base (part of the surface's signature)
    stack: object = None  # EditStack on the VolumeEVM of base_path
    tools: OrderedDict = field(default_factory=OrderedDict)  # digest -> tool EVM (LRU)
    result: object = None  # the VolumeEVM of the last successful evaluation
    shown: tuple = None  # (signature, co, Faces, BoundaryMesh) last written into the surface
    timing: dict = field(default_factory=dict)  # the last refresh: seconds by part, counts
    problem: str = ""  # why the last evaluation failed ("" if it did not)
    labels: object = None  # a label map's LabelSet (the base of a stack on its label objects)
    labels_shown: dict = field(default_factory=dict)  # label -> (co, Faces) its object shows

    def remember_tool(self, digest, evm):
        self.tools[digest] = evm
        self.tools.move_to_end(digest)
        while len(self.tools) > TOOL_CACHE_SIZE:
            self.tools.popitem(last=False)


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


def stack_state(uid, name):
    """The tool stack state of volume object ``name`` (uid ``uid``), or None."""
    return _stacks.get((uid, name))


def put_stack_state(uid, name, state):
    _stacks[(uid, name)] = state


def forget_stacks_except(keys):
    """Drop the tool stacks of volume objects not in ``keys`` ({(uid, name)})."""
    for key in [k for k in _stacks if k not in keys]:
        del _stacks[key]


def forget_except(uids):
    """Drop cached volumes, statuses and stacks of objects that no longer exist."""
    for store in (_volumes, _status):
        for key in [k for k in store if k not in uids]:
            del store[key]
    for key in [k for k in _stacks if k[0] not in uids]:
        del _stacks[key]


def clear():
    """Forget everything (a different .blend was opened)."""
    _volumes.clear()
    _vevms.clear()
    _status.clear()
    _stacks.clear()
