"""Helpers shared by the reader tests and the reader fuzzers: files written as their formats'
own tools write them, and NIfTI headers patched without repair."""

import io
import warnings
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]


def write_nrrd(path, array, header, **kwargs):
    """pynrrd's writer, silencing its own ``datetime.utcnow`` deprecation (Python 3.12+)."""
    import nrrd

    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", "datetime.datetime.utcnow", DeprecationWarning)
        nrrd.write(str(path), array, header, **kwargs)


def write_den(path, array, byte_order):
    """A VolPack .den file of ``uint8`` ``array`` (``[x, y, z]``) with brainsmall's header."""
    map_len = np.array(array.shape)
    orig_len = np.array([256, 256, 109])
    fields = np.concatenate([[1], np.zeros(3), orig_len - 1, orig_len, np.zeros(3), orig_len - 1,
                             orig_len, np.zeros(3), map_len - 1, map_len, [3]])
    header = fields.astype(f"{byte_order}i2").tobytes()
    header += np.array([array.size], f"{byte_order}i4").tobytes()
    assert len(header) == 62
    path.write_bytes(header + array.T.tobytes())


def patch_nifti(data, **fields):
    """A NIfTI-1 file's bytes with header ``fields`` set, nothing repaired (as on disk)."""
    import nibabel as nib

    header = nib.Nifti1Header.from_fileobj(io.BytesIO(data[:348]), check=False)
    for name, value in fields.items():
        header[name] = value
    return header.binaryblock + data[348:]
