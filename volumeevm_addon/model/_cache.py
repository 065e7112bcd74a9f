"""What is derived from a VolumeEVM on first use and kept for the next use, counted and bounded.

The renderers derive tables from a VolumeEVM that depend on it alone (or on it and a transfer
function): ray casting's padded sampling tables and space-leaping blocks, splatting's sheets
and culled voxels, shear-warp's slice layouts, gradients and per-transfer-function classes;
the VolumeEVM's coarser levels (:meth:`VolumeEVM.level`) are derived too. Making them costs
more than a frame, so they are kept, in the VolumeEVM's own :class:`DerivedCache`
(``vevm.cache``) rather than out of sight in the renderers' modules: the bytes it holds are
counted (``vevm.size_report()["cache_bytes"]``), bounded by a budget (the least recently used
entries go first) and can be dropped at any time (``vevm.cache.clear()``). Whatever is dropped
is made again, identically, when next needed: the cache trades memory for speed, never results.
"""

import math
import threading
import types
from collections import OrderedDict

import numpy as np

from .._errors import VolumeEVMError

__all__ = ["DerivedCache", "default_budget", "held_bytes"]

BUDGET_PER_VOXEL = 96
"""Default budget per voxel of the grid padded by one voxel on each side (bytes), 24 times a
float32 dense grid: room for the largest set of tables one method derives, so that views with
one method never make a table twice. Measured: ray casting with shading keeps 20 bytes per
padded voxel (a complex64 sampling table and float32 gradients) beside its blocks; shear-warp's
three principal axes, for a region that fills the grid (brainsmall), 31 (pre-classification)
or 15 (post), and 65 or 83 with shading (per-axis gradients). The CT head at 300 HU
(256 x 256 x 108, 6 % of it region) keeps 29 MiB with shear-warp (three axes), 25 MiB with
splatting and 141 MiB with shaded ray casting: its default, 670 MiB, holds all three at once."""
MIN_BUDGET = 256 << 20
"""The default budget is never below this (256 MiB): small volumes keep every method's tables."""


def default_budget(shape):
    """The default budget (bytes) of the cache of a VolumeEVM whose grid is ``shape``:
    :data:`BUDGET_PER_VOXEL` per padded grid voxel, at least :data:`MIN_BUDGET`."""
    return max(MIN_BUDGET, BUDGET_PER_VOXEL * math.prod(int(n) + 2 for n in shape))


class DerivedCache:
    """Keyed entries made on first use, bounded by a budget in bytes, least recently used
    dropped first.

    Each :class:`VolumeEVM` owns one, ``vevm.cache``; renderers keep there what they derive
    from the VolumeEVM (module docstring). An entry is whatever ``make()`` returned: an array,
    or a container or small object holding arrays; its size is the bytes of the arrays it
    holds (:func:`held_bytes`), measured whenever the cache is used, so entries that fill in as
    they are used count what they hold now.

    Parameters
    ----------
    budget : int
        Most bytes the entries may hold (keyword-only; see :attr:`budget`).

    Raises
    ------
    VolumeEVMError
        For a budget that is not an integer >= 0.

    Examples
    --------
    >>> cache = DerivedCache(budget=1000)
    >>> table = cache.get(("ones", 100), lambda: np.ones(100))  # made: 800 bytes
    >>> cache.get(("ones", 100), lambda: np.zeros(100)) is table  # kept: not made again
    True
    >>> cache.nbytes, ("ones", 100) in cache
    (800, True)
    >>> _ = cache.get(("ones", 50), lambda: np.ones(50))  # 1200 bytes > budget: the oldest goes
    >>> cache.keys(), cache.nbytes
    ([('ones', 50)], 400)
    >>> cache.clear()
    >>> cache.nbytes
    0
    """

    def __init__(self, *, budget):
        self._entries = OrderedDict()  # least recently used first
        self._lock = threading.RLock()  # guards the entries: a render job and the viewport
        self._making = {}  # key -> the lock of the one thread making that entry
        self.budget = budget

    @property
    def budget(self):
        """Most bytes the entries may hold (int). After every :meth:`get` (and on setting it)
        the least recently used entries are dropped until the rest fit, so an entry larger
        than the whole budget is returned but not kept; 0 keeps nothing."""
        return self._budget

    @budget.setter
    def budget(self, value):
        if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)) \
                or value < 0:
            raise VolumeEVMError(f"budget: an integer number of bytes >= 0, got {value!r}")
        with self._lock:
            self._budget = int(value)
            self._evict()

    def get(self, key, make):
        """The entry under ``key``, made by ``make()`` when it is not kept.

        The entry becomes the most recently used; then the budget is enforced (:attr:`budget`).

        Parameters
        ----------
        key : hashable
            Names the entry: a tuple starting with the name of what derives it (``"raycast"``,
            ``"splat"``, ``"shear_warp"``, ``"level"``), then whatever the entry depends on.
        make : callable
            Called without arguments when the entry is not kept; returns it.

        Returns
        -------
        object
            The entry, kept or just made.

        Notes
        -----
        Thread-safe: threads asking for the same missing key wait for the one that makes it
        (a table is never made twice at once, which would double its memory); other keys are
        made meanwhile.
        """
        with self._lock:
            if key in self._entries:
                return self._use(key)
            making = self._making.setdefault(key, threading.RLock())
        with making:
            with self._lock:
                if key in self._entries:  # made by another thread while this one waited
                    return self._use(key)
            try:
                value = make()
            finally:
                with self._lock:
                    self._making.pop(key, None)
            with self._lock:
                self._entries[key] = value
                self._evict()
            return value

    def _use(self, key):
        """The entry under ``key``, now the most recently used (the lock held)."""
        self._entries.move_to_end(key)
        value = self._entries[key]
        self._evict()
        return value

    def discard(self, key):
        """Drop the entry under ``key``, if there is one.

        Parameters
        ----------
        key : hashable
            As given to :meth:`get`.
        """
        with self._lock:
            self._entries.pop(key, None)

    def clear(self):
        """Drop every entry (they are made again when next needed)."""
        with self._lock:
            self._entries.clear()

    def keys(self):
        """The keys of the entries kept.

        Returns
        -------
        list
            The keys, least recently used first (a new list).
        """
        with self._lock:
            return list(self._entries)

    def __contains__(self, key):
        """Whether an entry is kept under ``key`` (not a use: the order of use stays)."""
        return key in self._entries

    def __len__(self):
        return len(self._entries)

    @property
    def nbytes(self):
        """Bytes of the arrays the entries hold now (:func:`held_bytes`; an array two entries
        share counts once)."""
        seen = set()
        with self._lock:
            values = list(self._entries.values())
        return sum(held_bytes(value, seen) for value in values)

    def _evict(self):
        """Drop the least recently used entries until the rest fit the budget (the lock
        held)."""
        while self._entries and self.nbytes > self._budget:
            self._entries.popitem(last=False)

    def __repr__(self):
        return (f"DerivedCache({len(self._entries)} entries, {self.nbytes} bytes, "
                f"budget {self._budget})")


def held_bytes(value, seen=None):
    """Bytes of the NumPy arrays ``value`` holds: an object with an integer ``nbytes`` (an
    array, a nested :class:`DerivedCache`) counts that; tuples, lists, sets and dict values
    count their items and other objects their attributes (``__dict__`` and ``__slots__``),
    recursively; anything else (numbers, strings, functions, classes, modules) counts 0.
    ``seen`` (a set of ids) makes each object count once across several calls."""
    seen = set() if seen is None else seen
    if id(value) in seen:
        return 0
    seen.add(id(value))
    size = getattr(value, "nbytes", None)
    if isinstance(size, (int, np.integer)) and not isinstance(size, bool):
        return int(size)
    if isinstance(value, dict):
        return sum(held_bytes(item, seen) for item in list(value.values()))
    if isinstance(value, (tuple, list, set, frozenset)):
        return sum(held_bytes(item, seen) for item in list(value))
    if isinstance(value, (type, types.ModuleType, types.FunctionType, types.MethodType)):
        return 0
    attributes = list(getattr(value, "__dict__", {}).values())
    for cls in type(value).__mro__:  # and the attributes of classes with __slots__
        slots = vars(cls).get("__slots__", ())
        attributes += [getattr(value, name, None)
                       for name in ((slots,) if isinstance(slots, str) else slots)
                       if name not in ("__dict__", "__weakref__")]
    return sum(held_bytes(item, seen) for item in attributes)
