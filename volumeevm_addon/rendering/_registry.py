"""The rendering methods: one line per method record, in the order the sidebar lists them.

Each method module ends with its :class:`._method.Method` record; this tuple is the one place
that names them. Blender stores the sidebar's method setting by its position in this order,
so a new method goes last.
"""

from types import MappingProxyType

from .._errors import VolumeEVMError
from ._gpu_inputs import GPU_METHOD
from ._raycast import NAVIGATE_METHOD, RAYCAST_METHOD
from ._reference import REFERENCE_METHOD
from ._shear_warp import SHEAR_WARP_METHOD
from ._splat import SPLAT_METHOD

_RECORDS = (
    RAYCAST_METHOD,
    SHEAR_WARP_METHOD,
    SPLAT_METHOD,
    NAVIGATE_METHOD,
    REFERENCE_METHOD,
    GPU_METHOD,
)

REGISTRY = MappingProxyType({record.name: record for record in _RECORDS})
"""Method name to its record, in the order of :data:`_RECORDS`."""

CPU_METHODS = tuple(name for name, record in REGISTRY.items() if record.render is not None)
"""The methods :func:`~volumeevm_addon.render` runs (the GPU's draws on the Blender side)."""


def methods():
    """Every rendering method's record, by name, in the order the sidebar lists them.

    Returns
    -------
    mapping of str to Method
        Read-only; :data:`CPU_METHODS` (``volumeevm_addon.METHODS``) are those
        :func:`~volumeevm_addon.render` runs, a record with ``gpu=True`` is drawn by the
        Blender side (its ``render`` is None).

    Examples
    --------
    >>> from volumeevm_addon.rendering import methods
    >>> list(methods())
    ['raycast', 'shear_warp', 'splat', 'raycast_navigate', 'reference', 'gpu']
    >>> methods()["splat"].label
    'Splatting'
    """
    return REGISTRY


def method_record(name):
    """The record of the method ``name``.

    Parameters
    ----------
    name : str
        One of the names of :func:`methods`.

    Returns
    -------
    Method

    Raises
    ------
    VolumeEVMError
        When no method has that name.
    """
    if name not in REGISTRY:
        raise VolumeEVMError(f"method: one of {tuple(REGISTRY)}, got {name!r}")
    return REGISTRY[name]
