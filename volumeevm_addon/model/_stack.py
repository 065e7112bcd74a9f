"""A non-destructive stack of tool operations on a VolumeEVM.

The volume keeps its base VolumeEVM and an ordered list of operations (tool, what to do, whether
it is enabled). Evaluating the stack applies the enabled operations in order. The result after
each entry is cached, so when one tool moves only that entry and the ones after it are computed
again: dragging the last tool of a stack costs one Boolean, not the whole stack.
"""

from dataclasses import KW_ONLY, dataclass

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


class EditStack:
    """Evaluates a list of :class:`ToolOperation` on a base VolumeEVM, reusing earlier results.

    Parameters
    ----------
    base : VolumeEVM
        The region before any operation; never changed.

    Attributes
    ----------
    last_recomputed : int
        How many entries the last :meth:`evaluate` computed again (the others were reused).

    Examples
    --------
    >>> import numpy as np
    >>> from volumeevm_addon import VolumeEVM, box_evm
    >>> region = VolumeEVM.from_array(np.ones((4, 4, 4)), 1.0)
    >>> drill = box_evm((0, 0, 0), (2, 4, 4), region.shape)
    >>> stack = EditStack(region)
    >>> stack.evaluate([ToolOperation(drill, "cut")]).voxel_count
    32
    >>> largest = ToolOperation(operation="largest")
    >>> stack.evaluate([ToolOperation(drill, "cut"), largest]).voxel_count
    32
    >>> stack.last_recomputed  # the cut was reused
    1
    """

    def __init__(self, base):
        self.base = base
        self._entries = []  # (operation, result after it), for the last evaluated list
        self.last_recomputed = 0

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
            As :meth:`ToolOperation.apply`, for the first entry that fails.
        """
        operations = list(operations)
        same = 0
        while (same < min(len(operations), len(self._entries))
               and operations[same] == self._entries[same][0]):
            same += 1
        entries = self._entries[:same]
        region = entries[-1][1] if entries else self.base
        for operation in operations[same:]:
            if operation.enabled:
                region = operation.apply(region)
            entries.append((operation, region))
        self._entries = entries
        self.last_recomputed = len(operations) - same
        return region
