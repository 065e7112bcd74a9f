"""A non-destructive stack of tool operations on a VolumeEVM.

The volume keeps its base VolumeEVM and an ordered list of operations (tool, what to do, whether
it is enabled). Evaluating the stack applies the enabled operations in order. The result after
each entry is cached, so when one tool moves only that entry and the ones after it are computed
again: dragging the last tool of a stack costs one Boolean, not the whole stack.
"""

from dataclasses import dataclass

from ._evm import EVM

OPERATIONS = ("cut", "keep", "add", "largest")


@dataclass(frozen=True)
class ToolOperation:
    """One entry of the stack.

    Parameters
    ----------
    tool : EVM or None
        The tool's voxels in the volume's lattice (e.g. ``EVM.from_mask(voxelize_mesh(...))``;
        a clip box is a box's EVM with "keep"). None for "largest".
    operation : {"cut", "keep", "add", "largest"}
        Remove the tool's voxels, keep only them, add them as material, or keep the largest
        face-connected part of the region.
    enabled : bool
        Disabled entries are skipped.
    density : float or None
        Density of added voxels (``"add"`` only); None means the region's largest density.
    """

    tool: EVM = None
    operation: str = "cut"
    enabled: bool = True
    density: float = None

    def __post_init__(self):
        if self.operation not in OPERATIONS:
            raise ValueError(f"operation must be one of {OPERATIONS}, got {self.operation!r}")
        if self.operation == "largest" and self.tool is not None:
            raise ValueError("operation 'largest' takes no tool")
        if self.operation != "largest" and self.tool is None:
            raise ValueError(f"operation {self.operation!r} needs a tool")
        if self.tool is not None and not isinstance(self.tool, EVM):
            raise TypeError(f"tool must be an EVM, got {type(self.tool).__name__}")

    def apply(self, region):
        """This entry applied to a VolumeEVM (a new VolumeEVM)."""
        if self.operation == "add":
            return region.add(self.tool, self.density)
        if self.operation == "largest":
            return region.largest_component()
        return getattr(region, self.operation)(self.tool)


class EditStack:
    """Evaluates a list of :class:`ToolOperation` on a base VolumeEVM, reusing earlier results.

    Examples
    --------
    >>> stack = EditStack(region)                                    # doctest: +SKIP
    >>> result = stack.evaluate([ToolOperation(drill, "cut")])       # doctest: +SKIP
    """

    def __init__(self, base):
        self.base = base
        self._entries = []  # (operation, result after it), for the last evaluated list
        self.last_recomputed = 0

    def evaluate(self, operations):
        """The base with every enabled operation applied in order.

        Entries equal to those of the previous call (same tool voxels, operation, flag and
        density) reuse their cached results up to the first one that differs.
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
