"""NumPy ``.npy`` volumes, with an optional JSON sidecar for spacing and units.

The array is taken as already indexed ``[x, y, z]`` (the convention of the project's real data
in ``../shared/data``). ``np.load`` runs with ``allow_pickle=False``: a ``.npy`` holding Python
objects would execute code when unpickled, so it is refused instead.

The sidecar is ``NAME.json`` beside ``NAME.npy`` (the schema of ``../shared/data/*.json``). The
keys used are ``spacing_mm`` (x, y, z in mm), ``spacing_known``, ``units``, and, as consistency
checks against the array, ``shape``, ``dtype`` and ``axis_order`` (must be "xyz"). Other keys
are ignored.
"""

import json
from pathlib import Path

import numpy as np

from .._errors import VolumeEVMError
from ._checks import checked_volume

#: Sidecar spellings of data units mapped to the short names the core uses.
_UNIT_ALIASES = {"hounsfield units": "HU", "hounsfield unit": "HU", "hu": "HU"}


def read_npy(path):
    """Read a ``.npy`` volume indexed ``[x, y, z]`` and its optional JSON sidecar.

    Parameters
    ----------
    path : str or Path
        The ``.npy`` file.

    Returns
    -------
    Volume
        Identity orientation and zero origin (a ``.npy`` has no patient frame); spacing from
        the sidecar, else 1 mm with ``spacing_known=False``.

    Raises
    ------
    VolumeEVMError
        If the file is not a readable ``.npy`` (corrupt, truncated, pickled objects), the array
        is not a valid volume, or the sidecar is unreadable or disagrees with the array.
    """
    path = Path(path)
    try:
        array = np.load(path, allow_pickle=False)
    except (ValueError, OSError, EOFError) as exc:
        raise VolumeEVMError(f"{path}: not a readable .npy array ({exc})") from exc
    if not isinstance(array, np.ndarray):
        raise VolumeEVMError(f"{path}: holds an archive of several arrays, not one volume")
    spacing, units = _read_sidecar(path.with_suffix(".json"), array)
    return checked_volume(array, path, spacing=spacing, units=units)


def _read_sidecar(sidecar, array):
    """Spacing (mm, or ``None``) and units from ``sidecar`` if it exists, checked on ``array``."""
    if not sidecar.is_file():
        return None, ""
    try:
        meta = json.loads(sidecar.read_text(encoding="utf-8"))
    except (ValueError, OSError) as exc:
        raise VolumeEVMError(f"{sidecar}: corrupt JSON sidecar ({exc})") from exc
    if not isinstance(meta, dict):
        raise VolumeEVMError(f"{sidecar}: corrupt JSON sidecar (not a JSON object)")
    if meta.get("axis_order", "xyz") != "xyz":
        raise VolumeEVMError(
            f"{sidecar}: axis_order is {meta['axis_order']!r}; only 'xyz' arrays are supported"
        )
    if "shape" in meta and tuple(meta["shape"]) != array.shape:
        raise VolumeEVMError(
            f"{sidecar}: shape {meta['shape']} does not match the array's shape {array.shape}"
        )
    if "dtype" in meta and str(meta["dtype"]) != str(array.dtype):
        raise VolumeEVMError(
            f"{sidecar}: dtype {meta['dtype']} does not match the array's dtype {array.dtype}"
        )
    units = str(meta.get("units", ""))
    units = _UNIT_ALIASES.get(units.lower(), units)
    if "spacing_mm" not in meta or not meta.get("spacing_known", True):
        return None, units
    spacing = meta["spacing_mm"]
    if (
        not isinstance(spacing, list)
        or len(spacing) != 3
        or not all(isinstance(s, (int, float)) for s in spacing)
    ):
        raise VolumeEVMError(f"{sidecar}: spacing_mm {spacing!r} is not a list of 3 numbers")
    return spacing, units
