""".vevm test helpers shared by ``test_vevm_file.py`` and ``test_fuzz_vevm.py``: volumes to save,
archives written by hand (members with crafted headers, lying sizes, deflate bombs), good files
rewritten with changed members and re-computed checksums so that a semantic check is reached
instead of the checksum, and the checks that a file loads exactly or is refused.
"""

import hashlib
import io
import json
import struct
import zipfile
import zlib

import numpy as np
import pytest
from numpy.lib import format as npy_format

from volumeevm_addon import EVM, VolumeEVM, VolumeEVMError


def synthetic():
    """A small VolumeEVM with every field set: float32 densities, a rotated frame, an interval."""
    rng = np.random.default_rng(9)
    array = rng.normal(100.0, 40.0, (7, 6, 5)).astype(np.float32)
    turn = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    return VolumeEVM.from_array(array, 90.0, 180.0, spacing=(0.5, 0.75, 2.0),
                                origin=(-3.0, 4.5, 10.0), orientation=turn, units="HU",
                                source="synthetic")


def ct_crop(data_dir):
    """The CT head cropped to a 64 x 64 x 32 block around the skull, thresholded at 300 HU."""
    head = np.load(data_dir / "ct_head_invesalius.npy")
    return VolumeEVM.from_array(head[64:128, 96:160, 40:72], 300, spacing=(0.957, 0.957, 1.5),
                                origin=(-120.0, -130.0, 10.0), units="HU", source="ct crop")


def sha(array):
    """SHA-256 of an array's C-order bytes, computed here independently of the reader."""
    return hashlib.sha256(np.ascontiguousarray(array).tobytes()).hexdigest()


def members_of(path):
    """The arrays of a good ``.vevm`` file (read with NumPy, pickles refused) and its metadata."""
    with np.load(path, allow_pickle=False) as archive:
        arrays = {name: archive[name] for name in archive.files}
    return arrays, json.loads(str(arrays["meta"]))


def npy_bytes(array):
    """The ``.npy`` bytes of an array (object arrays pickled: to test that they are refused)."""
    buffer = io.BytesIO()
    npy_format.write_array(buffer, np.asanyarray(array), allow_pickle=True)
    return buffer.getvalue()


def crafted_npy(descr, shape, data=b""):
    """A ``.npy`` whose header declares ``descr`` and ``shape`` whatever ``data`` follows."""
    buffer = io.BytesIO()
    npy_format.write_array_header_1_0(buffer, {"descr": descr, "fortran_order": False,
                                               "shape": shape})
    return buffer.getvalue() + data


def write_zip(path, members, compression=zipfile.ZIP_STORED):
    """Write ``members`` ({name: bytes}, ``.npy`` added to the names) with :mod:`zipfile`."""
    with zipfile.ZipFile(path, "w", compression) as archive:
        for name, data in members.items():
            archive.writestr(f"{name}.npy", data)


def write_vevm_members(path, arrays, meta=None, *, recompute=True, compression=zipfile.ZIP_STORED):
    """Write ``arrays`` as a ``.vevm`` archive; ``meta`` (dict) replaces the meta member, with
    checksums of the arrays written re-computed unless ``recompute`` is False."""
    arrays = dict(arrays)
    if meta is not None:
        meta = dict(meta)
        if recompute:
            meta["vertices_sha256"] = sha(arrays["vertices"])
            meta["table_sha256"] = sha(arrays["table"])
        arrays["meta"] = np.array(json.dumps(meta))
    write_zip(path, {name: npy_bytes(array) for name, array in arrays.items()}, compression)


def raw_zip(path, entries):
    """Write a ZIP by hand for what :mod:`zipfile` will not write: lying sizes, deflate bombs,
    repeated names, flags. ``entries`` holds dicts with ``name`` and ``payload`` (the bytes as
    stored) and optional ``method`` (0 stored, 8 deflate), ``size`` (declared uncompressed size),
    ``crc`` and ``flags``."""
    out, central = io.BytesIO(), io.BytesIO()
    for entry in entries:
        name = f"{entry['name']}.npy".encode()
        payload = entry["payload"]
        method, flags = entry.get("method", 0), entry.get("flags", 0)
        size = entry.get("size", len(payload))
        crc = entry.get("crc", zlib.crc32(payload) if method == 0 else 0)
        offset = out.tell()
        out.write(struct.pack("<4s2B4HL2L2H", b"PK\x03\x04", 20, 0, flags, method, 0, 33,
                              crc, len(payload), size, len(name), 0))
        out.write(name + payload)
        central.write(struct.pack("<4s4B4HL2L5H2L", b"PK\x01\x02", 20, 3, 20, 0, flags, method, 0,
                                  33, crc, len(payload), size, len(name), 0, 0, 0, 0, 0, offset))
        central.write(name)
    directory = central.getvalue()
    end = struct.pack("<4s4H2LH", b"PK\x05\x06", 0, 0, len(entries), len(entries), len(directory),
                      out.tell(), 0)
    path.write_bytes(out.getvalue() + directory + end)


def raw_entries(path):
    """The members of a stored ``.vevm`` file as :func:`raw_zip` entries (to change and rewrite)."""
    with zipfile.ZipFile(path) as archive:
        return [{"name": info.filename[:-len(".npy")], "payload": archive.read(info)}
                for info in archive.infolist()]


def deflate_zeros(count):
    """A raw deflate stream of ``count`` zero bytes (a multiple of 1 MiB), made without compressing
    them all: one fully flushed 1 MiB block repeated (a full flush makes blocks independent)."""
    chunk = 1 << 20
    compressor = zlib.compressobj(9, zlib.DEFLATED, -15)
    block = compressor.compress(bytes(chunk)) + compressor.flush(zlib.Z_FULL_FLUSH)
    return block * (count // chunk) + compressor.flush()


def assert_same(loaded, original):
    """``loaded`` holds exactly ``original``'s data: region, table (values and dtype), geometry."""
    assert loaded.evm == original.evm
    np.testing.assert_array_equal(loaded.evm.vertices, original.evm.vertices)
    assert loaded.table(0).dtype == original.table(0).dtype
    np.testing.assert_array_equal(loaded.table(0), original.table(0))
    fields = ("shape", "spacing", "origin", "units", "threshold", "upper")
    assert [getattr(loaded, f) for f in fields] == [getattr(original, f) for f in fields]
    np.testing.assert_array_equal(loaded.orientation, original.orientation)


def refused(path, match):
    """Loading ``path`` raises VolumeEVMError naming the file, matching ``match``; returns it."""
    with pytest.raises(VolumeEVMError, match=match) as info:
        VolumeEVM.load(path)
    assert str(info.value).startswith(f"{path}: ")
    return info.value


def region_change(name):
    """A change of a good file's vertices/table/meta that only a semantic check can see."""
    def outside(arrays, meta):
        vertices = arrays["vertices"].astype(np.int64)
        arrays["vertices"] = vertices + [0, 0, meta["shape"][2] - vertices[:, 2].max() + 1]

    def negative(arrays, meta):
        arrays["vertices"] = arrays["vertices"].astype(np.int64) - [1, 0, 0]

    def odd_line(arrays, meta):
        arrays["vertices"] = arrays["vertices"][1:]

    def duplicate(arrays, meta):
        v = arrays["vertices"]
        arrays["vertices"] = np.concatenate([v, v])  # every line stays even

    def short_table(arrays, meta):
        arrays["table"] = arrays["table"][:-1]
        meta["voxels"] -= 1

    def voxels(arrays, meta):
        meta["voxels"] += 1

    def nan_table(arrays, meta):
        arrays["table"] = arrays["table"].astype(np.float64)  # integer tables hold no NaN
        arrays["table"][2] = np.nan

    def shifted_box(arrays, meta):
        # Another valid region (a box) of a different volume than the table's length.
        mask = np.zeros((7, 6, 5), bool)
        mask[1:3, 1:3, 1:3] = True
        arrays["vertices"] = EVM.from_mask(mask).vertices

    return {"outside": outside, "negative": negative, "odd line": odd_line, "duplicate": duplicate,
            "short table": short_table, "voxels": voxels, "nan table": nan_table,
            "other region": shifted_box}[name]
