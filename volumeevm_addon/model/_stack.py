"""A non-destructive stack of tool operations on a VolumeEVM.

The volume keeps its base VolumeEVM and an ordered list of operations (tool, what to do, whether
it is enabled). Evaluating the stack applies the enabled operations in order. The result after
each entry is cached, so when one tool moves only that entry and the ones after it are computed
again.

Moving a tool changes the results only where the old and the new tool differ (``old ^ new``),
and the entries after it are voxel-wise operations, so they change only there too. When every
entry from the moved one on is the same cut, keep or add as before, the stack updates its cached
results in place: each entry's result is its previous one with the rows (x, y) crossing
``old ^ new`` made again from dense blocks of those rows, its region XOR where those rows
changed, its densities spliced in by the rows' offsets. The result is the one a full evaluation
gives, voxel for voxel and density for density (``tests/test_stack.py`` checks it on random
moves); only the VolumeEVM of the last entry is made, the others stay arrays.
"""

from dataclasses import KW_ONLY, dataclass

import numpy as np

from .._errors import VolumeEVMError
from ._evm import EVM

OPERATIONS = ("cut", "keep", "add", "largest")


@dataclass(frozen=True)
class ToolOperation:
    """One entry of the stack: a tool and what to do with it.

    A frozen record, compared by value, so :meth:`EditStack.evaluate` can tell which entries
    changed since the last call. ``enabled`` and ``density`` are keyword-only.

    Parameters
    ----------
    tool : EVM or None
        The tool's voxels in the volume's lattice (e.g. ``EVM.from_mask(voxelize_mesh(...))``;
        a clip box is a box's EVM with "keep"). None for "largest".
    operation : {"cut", "keep", "add", "largest"}
        Remove the tool's voxels, keep only them, add them as material, or keep the largest
        face-connected part of the region.
    enabled : bool, optional
        Disabled entries are skipped (default True).
    density : float or None, optional
        Density of added voxels (``"add"`` only); None means the region's largest density.

    Raises
    ------
    VolumeEVMError
        For an unknown operation, a tool given to "largest" or none to another operation.
    TypeError
        If ``tool`` is not an :class:`EVM`.
    """

    tool: EVM = None
    operation: str = "cut"
    _: KW_ONLY
    enabled: bool = True
    density: float = None

    def __post_init__(self):
        if self.operation not in OPERATIONS:
            raise VolumeEVMError(f"operation must be one of {OPERATIONS}, got {self.operation!r}")
        if self.operation == "largest" and self.tool is not None:
            raise VolumeEVMError("operation 'largest' takes no tool")
        if self.operation != "largest" and self.tool is None:
            raise VolumeEVMError(f"operation {self.operation!r} needs a tool")
        if self.tool is not None and not isinstance(self.tool, EVM):
            raise TypeError(f"tool must be an EVM, got {type(self.tool).__name__}")

    def apply(self, region):
        """This entry applied to a VolumeEVM.

        Parameters
        ----------
        region : VolumeEVM
            The region before this entry.

        Returns
        -------
        VolumeEVM
            A new VolumeEVM (:meth:`VolumeEVM.cut`, ``keep``, ``add`` or
            ``largest_component``); ``region`` is not changed.

        Raises
        ------
        VolumeEVMError
            When the result would be empty, or an added tool misses the grid.
        """
        if self.operation == "add":
            return region.add(self.tool, self.density)
        if self.operation == "largest":
            return region.largest_component()
        return getattr(region, self.operation)(self.tool)


_LOCAL_SHARE = 8
"""Update an entry in place only when its dirty blocks hold at most 1/8 of the grid's voxels;
past that, a full evaluation of the entry (its Boolean and table mask) costs less."""


class _Result:
    """The region after one entry: its EVM, its densities table and each row's place in it.

    ``rows[x * Y + y]`` is the table index of row (x, y)'s first voxel and ``rows[-1]`` the
    voxel count: the rows of a block of x are one stretch of the table each. ``density`` is what
    an "add" entry gave its voxels. The VolumeEVM is made when first asked for.
    """

    def __init__(self, evm, table, rows=None, vevm=None, density=None):
        self.evm, self.table, self._rows = evm, table, rows
        self.density = density
        self._vevm = vevm

    @property
    def rows(self):
        """Each row's first table index (made on first use from the EVM's boxes)."""
        if self._rows is None:
            self._rows = _row_starts(self.evm, self._vevm.shape)
        return self._rows

    def volumeevm(self, base):
        """This region as a VolumeEVM with ``base``'s grid, units and interval (made once)."""
        if self._vevm is None:
            self._vevm = base._derived(self.evm, self.table)
        return self._vevm


def _row_starts(evm, shape):
    """The table index of each row's first voxel (see :class:`_Result`), from the boxes."""
    nx, ny, _ = shape
    lo, hi = evm.boxes()
    # Each box adds its run length to the rows of its x, y rectangle: a 2-D difference grid.
    corners = ((lo[:, 0], lo[:, 1], 1), (hi[:, 0], lo[:, 1], -1), (lo[:, 0], hi[:, 1], -1),
               (hi[:, 0], hi[:, 1], 1))
    length = (hi[:, 2] - lo[:, 2]).astype(np.float64)
    grid = sum(sign * np.bincount(x * (ny + 1) + y, length, (nx + 1) * (ny + 1))
               for x, y, sign in corners)
    counts = grid.reshape(nx + 1, ny + 1).cumsum(axis=0).cumsum(axis=1)[:nx, :ny]
    rows = np.zeros(nx * ny + 1, np.int64)
    np.cumsum(counts.astype(np.int64).ravel(), out=rows[1:])
    return rows


def _dirty_blocks(changes, shape):
    """Blocks of whole rows covering the voxels of the EVMs ``changes``.

    Consecutive x slices with changed voxels form a block's x range; over it, the y ranges of
    their changes, joined where they are less than :data:`_GAP` rows apart (each block costs a
    clip of the region, each row a dense column). Returns ``(x0, x1, [(y0, y1), ...])`` in
    ascending x, the y ranges ascending, or None when they would hold more than
    ``1 / _LOCAL_SHARE`` of the grid (a full evaluation is cheaper then).
    """
    nx, ny, nz = shape
    # Changed rows (x, y): every box adds 1 on its x, y rectangle (a 2-D difference grid).
    marks = np.zeros((nx + 1) * (ny + 1))
    for change in changes:
        lo, hi = change.clip((0, 0, 0), shape).boxes()
        for x, y, sign in ((lo[:, 0], lo[:, 1], 1), (hi[:, 0], lo[:, 1], -1),
                           (lo[:, 0], hi[:, 1], -1), (hi[:, 0], hi[:, 1], 1)):
            marks += sign * np.bincount(x * (ny + 1) + y, minlength=len(marks))
    dirty = marks.reshape(nx + 1, ny + 1).cumsum(axis=0).cumsum(axis=1)[:nx, :ny] > 0
    blocks, voxels = [], 0
    for x0, x1 in _runs(dirty.any(axis=1)):
        spans = []
        for y0, y1 in _runs(dirty[x0:x1].any(axis=0)):
            if spans and y0 - spans[-1][1] < _GAP:
                y0 = spans.pop()[0]
            spans.append((y0, y1))
        blocks.append((x0, x1, spans))
        voxels += (x1 - x0) * sum(y1 - y0 for y0, y1 in spans) * nz
    return None if voxels * _LOCAL_SHARE > nx * ny * nz else blocks


_GAP = 16
"""Rows between two changed y ranges of a block below which they are made one range."""


def _runs(flags):
    """The maximal runs ``(start, stop)`` of True in a 1-D boolean array."""
    edges = np.flatnonzero(np.diff(np.r_[0, flags.astype(np.int8), 0]))
    return [(int(a), int(b)) for a, b in zip(edges[::2], edges[1::2])]


def _update_in_place(previous, old, operation, blocks, shape):
    """The result of ``operation`` after ``previous``, from ``old`` (its result before the
    change) outside ``blocks`` and made again inside them; None when a full evaluation must
    decide (an empty result or tool, whose error it raises, or an add whose density moved).

    In each block the voxels before the entry, the tool's and the old result's come as dense
    masks (from the regions clipped to the block's x range); the result's voxels there are
    the operation on the first two, its EVM the old one XOR where they differ from the old
    result's (``EVM(P xor Q) = EVM(P) xor EVM(Q)``), and its table the old one with the
    blocks' rows made again from the densities before the entry.
    """
    tool = operation.tool
    density = None
    if operation.operation == "add":
        tool = tool.clip((0, 0, 0), shape)
        if tool.is_empty():
            return None
        density = previous.table.max() if operation.density is None else operation.density
        if density != old.density:
            return None
    nx, ny, nz = shape
    pieces, done = [], 0
    delta = np.zeros(nx * ny, np.int64)
    change = EVM()
    for x0, x1, spans in blocks:
        lo, hi = (x0, spans[0][0], 0), (x1, spans[-1][1], nz)
        region, inside_tool, was = (evm.clip(lo, hi) for evm in (previous.evm, tool, old.evm))
        firsts = np.arange(x0, x1) * ny
        made = []
        for y0, y1 in spans:
            lo, size = (x0, y0, 0), (x1 - x0, y1 - y0, nz)
            before, inside = region.to_mask(size, lo), inside_tool.to_mask(size, lo)
            dense = np.empty(size, previous.table.dtype)
            dense[before] = np.concatenate(
                [previous.table[previous.rows[f + y0]:previous.rows[f + y1]] for f in firsts])
            if operation.operation == "add":
                after = before | inside
                dense[inside] = density
            elif operation.operation == "cut":
                after = before & ~inside
            else:
                after = before & inside
            change = change ^ EVM.from_mask(after ^ was.to_mask(size, lo), offset=lo)
            counts = after.sum(axis=2)
            made.append(np.split(dense[after], np.cumsum(counts.sum(axis=1))[:-1]))
            rows = (firsts[:, None] + np.arange(y0, y1)).ravel()
            delta[rows] = counts.ravel() - (old.rows[rows + 1] - old.rows[rows])
        # The table is spliced row by row: x by x, each y range of it in turn.
        for i, f in enumerate(firsts):
            for (y0, y1), values in zip(spans, made):
                pieces += [old.table[done:old.rows[f + y0]], values[i]]
                done = old.rows[f + y1]
    evm = old.evm ^ change
    if evm.is_empty():
        return None
    pieces.append(old.table[done:])
    rows = old.rows.copy()
    rows[1:] += np.cumsum(delta)
    return _Result(evm, np.concatenate(pieces), rows, density=density)


class EditStack:
    """Evaluates a list of :class:`ToolOperation` on a base VolumeEVM, reusing earlier results.

    Entries equal to those of the previous call are reused up to the first one that differs;
    from there, an entry that differs from its previous version only by its tool (and every
    entry after it that is the same cut, keep or add as before) is updated in place, where the
    old and the new tool differ (see the module docstring); any other entry is evaluated in
    full, and so are the ones after it.

    Parameters
    ----------
    base : VolumeEVM
        The region before any operation; never changed.

    Attributes
    ----------
    last_recomputed : int
        How many entries the last :meth:`evaluate` computed again (the others were reused).
    last_updated : int
        How many of those it updated in place rather than evaluated in full.

    Examples
    --------
    >>> import numpy as np
    >>> from volumeevm_addon import VolumeEVM
    >>> from volumeevm_addon.model import box_evm
    >>> region = VolumeEVM.from_array(np.ones((16, 4, 4)), 1.0)
    >>> drill = box_evm((0, 0, 0), (2, 4, 4), region.shape)
    >>> stack = EditStack(region)
    >>> stack.evaluate([ToolOperation(drill, "cut")]).voxel_count
    224
    >>> largest = ToolOperation(operation="largest")
    >>> stack.evaluate([ToolOperation(drill, "cut"), largest]).voxel_count
    224
    >>> stack.last_recomputed  # the cut was reused
    1
    >>> moved = box_evm((0, 0, 0), (1, 4, 4), region.shape)  # the drill moved off x = 1
    >>> stack.evaluate([ToolOperation(moved, "cut"), largest]).voxel_count
    240
    >>> stack.last_recomputed, stack.last_updated  # the cut in place, "largest" in full
    (2, 1)
    """

    def __init__(self, base):
        self.base = base
        self._entries = []  # (operation, _Result after it), for the last evaluated list
        self._start = None  # the base's _Result, made on first use
        self.last_recomputed = 0
        self.last_updated = 0

    def evaluate(self, operations):
        """The base with every enabled operation applied in order.

        Entries equal to those of the previous call (same tool voxels, operation, flag and
        density) reuse their cached results up to the first one that differs.

        Parameters
        ----------
        operations : iterable of ToolOperation
            The stack, first entry first.

        Returns
        -------
        VolumeEVM
            The base itself when no entry is enabled.

        Raises
        ------
        VolumeEVMError
            As :meth:`ToolOperation.apply`, for the first entry that fails; the cached results
            stay those of the previous call.
        """
        operations = list(operations)
        same = 0
        while (same < min(len(operations), len(self._entries))
               and operations[same] == self._entries[same][0]):
            same += 1
        if self._start is None:
            self._start = _Result(self.base.evm, self.base.table(0), vevm=self.base)
        entries = self._entries[:same]
        region = entries[-1][1] if entries else self._start
        changes, blocks = [], []  # where the tools moved; None once anything may have changed
        updated = 0
        for index in range(same, len(operations)):
            operation = operations[index]
            old_operation, old = (self._entries[index] if index < len(self._entries)
                                  else (None, None))
            if old_operation is None or not _same_but_tool(operation, old_operation):
                changes = None
            elif changes is not None and operation.tool != old_operation.tool:
                changes.append(operation.tool ^ old_operation.tool)
                blocks = _dirty_blocks(changes, self.base.shape)
            if operation.enabled:
                result = None
                if changes is not None and blocks is not None and operation.operation != "largest":
                    result = _update_in_place(region, old, operation, blocks, self.base.shape)
                if result is None:
                    result = self._apply(operation, region)
                    changes = None
                else:
                    updated += 1
                region = result
            entries.append((operation, region))
        self._entries = entries
        self.last_recomputed = len(operations) - same
        self.last_updated = updated
        return region.volumeevm(self.base)

    def _apply(self, operation, region):
        """``operation`` applied to ``region`` in full (:meth:`ToolOperation.apply`)."""
        density = None
        if operation.operation == "add":
            density = region.table.max() if operation.density is None else operation.density
        result = operation.apply(region.volumeevm(self.base))
        return _Result(result.evm, result.table(0), vevm=result, density=density)


def _same_but_tool(a, b):
    """True when two entries differ at most by their tools."""
    return (a.operation, a.enabled, a.density) == (b.operation, b.enabled, b.density)
