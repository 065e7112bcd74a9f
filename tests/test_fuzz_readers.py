"""Fuzzing the volume readers (.npy, raw, .nii, .nii.gz, .nrrd, .nhdr, .den): each mutated file
reads as exactly the original data or is refused with a VolumeEVMError naming the file; never
another exception type, a hang or silently different data.

The seeds are valid files written by each format's reference library (numpy.save, nibabel,
pynrrd; raw bytes; VolPack's .den layout as in test_readers) from a crop of the real CT head.
Each is mutated by truncation, by single-bit flips at seeded random offsets, by appended bytes
and by crafted header fields (dimensions, datatype, vox_offset, pixdim, scl_slope, sizes,
encoding, endian, a garbled space origin, compressed streams with wrong checksums or sizes).

Outcome classes:

- ``exact``: the read gives the original array (values and dtype), spacing, origin,
  orientation, units and ``spacing_known``;
- ``refused``: a VolumeEVMError whose message starts with the mutated file's path;
- ``as announced``: a crafted header that validly means something else (``endian: big``, a
  same-size datatype, Fortran order, no scaling) reads as exactly what it announces;
- ``undetectable data change``: a bit flip inside the voxel data of an uncompressed format,
  which has no checksum: the read must differ from the original in exactly the flipped voxel;
- ``undetectable header value``: a bit flip inside a header field that holds a free number
  (spacing, origin, axis directions, scaling, NIfTI codes and units, the .npy dtype string)
  and still parses: the format cannot tell the new value from a real one.

Truncations, flips in the structure of a header (sizes, types, offsets, magic numbers, field
names) and in compressed streams must end ``exact`` or ``refused``. Anything else, another
exception type or a case slower than :data:`SLOWEST` seconds fails the test. Run with
``pytest -s`` to see a summary line per format: cases by outcome class.
"""

import collections
import gzip
import io
import re
import signal
import typing

import numpy as np
import pytest

from reader_files import patch_nifti, write_den, write_nrrd
from volumeevm_addon import VolumeEVMError
from volumeevm_addon.readers import read_volume

SEED = 20261124
TRUNCATIONS = 40
FLIPS = 300
SLOWEST = 5.0  # seconds one case may take: far above any real read of these small files
SPACING = (0.5, 0.6, 0.7)

#: NIfTI-1 header fields holding free numbers (geometry, scaling, their codes and units).
NIFTI_VALUE_FIELDS = ("pixdim", "scl_slope", "scl_inter", "qform_code", "sform_code",
                      "quatern_b", "quatern_c", "quatern_d", "qoffset_x", "qoffset_y",
                      "qoffset_z", "srow_x", "srow_y", "srow_z", "xyzt_units")

#: NRRD fields whose values are free numbers.
NRRD_VALUE_FIELDS = ("space directions", "space origin", "spacings")


@pytest.fixture(scope="module")
def crop(data_dir):
    """A 24 x 16 x 6 crop of the real CT head (int16 HU): skull, brain and air."""
    array = np.load(data_dir / "ct_head_invesalius.npy")
    return np.ascontiguousarray(array[100:124, 60:76, 50:56])


class Case(typing.NamedTuple):
    """One mutated file set.

    ``files`` maps file names to bytes (the first is the one read); ``kind`` is "structure"
    (exact or refused), "data" (may change exactly the flipped voxel), "value" (may change a
    header value) or "crafted"; ``expect`` is None (exact or refused), "refused", or the
    ``(array, changes)`` a valid crafted header announces (``changes``: geometry that differs
    from the original read).
    """

    label: str
    kind: str
    files: dict
    expect: object = None


# ---------------------------------------------------------------------------------------------
# seeds: valid files written by the reference libraries


def npy_seed(crop):
    buffer = io.BytesIO()
    np.save(buffer, crop)
    return {"ct.npy": buffer.getvalue()}


def raw_seed(crop):
    return {"ct.raw": crop.T.tobytes()}


def nifti_seed(tmp_path, crop, name):
    """The crop saved by nibabel as ``name`` (``.nii`` or ``.nii.gz``), with an sform."""
    import nibabel as nib

    img = nib.Nifti1Image(crop, np.diag([*SPACING, 1.0]) @ np.array(
        [[1, 0, 0, -20.0], [0, 1, 0, 30.0], [0, 0, 1, 5.0], [0, 0, 0, 1]]))
    img.header.set_xyzt_units("mm")
    nib.save(img, tmp_path / name)
    return {name: (tmp_path / name).read_bytes()}


def nrrd_seed(tmp_path, crop, name, **kwargs):
    path = tmp_path / "seed" / name
    path.parent.mkdir(exist_ok=True)
    write_nrrd(path, crop, {"space": "left-posterior-superior",
                            "space directions": np.diag(SPACING),
                            "space origin": np.array([-20.0, 30.0, 5.0]),
                            "encoding": kwargs.pop("encoding")}, **kwargs)
    files = {name: path.read_bytes()}  # the header first: it is the file read
    files.update({p.name: p.read_bytes() for p in path.parent.iterdir() if p != path})
    return files


def den_array(crop):
    """The crop as the 8-bit densities a .den file holds."""
    return np.clip(crop // 16 + 64, 0, 255).astype(np.uint8)


def den_seed(tmp_path, crop):
    path = tmp_path / "seed.den"
    write_den(path, den_array(crop), "<")
    return {"ct.den": path.read_bytes()}


# ---------------------------------------------------------------------------------------------
# mutations


def generic_cases(files, rng, header_end, region_of):
    """Truncations, single-bit flips and appended bytes of the first file of ``files``.

    ``header_end`` is where the data starts (flips before it are header flips);
    ``region_of(offset)`` classifies a flip as "structure", "data" or "value".
    """
    name, data = next(iter(files.items()))
    cases = []
    cuts = {0, 1, header_end - 1, header_end, header_end + 1, len(data) - 1}
    cuts |= {int(c) for c in rng.integers(1, len(data), TRUNCATIONS)}
    for cut in sorted(c for c in cuts if 0 <= c < len(data)):
        cases.append(Case(f"truncated at {cut}", "structure", {**files, name: data[:cut]}))
    in_header = FLIPS if header_end >= len(data) else FLIPS // 2 if header_end > 0 else 0
    offsets = list(rng.integers(0, header_end, in_header)) if in_header else []
    offsets += list(rng.integers(header_end, len(data), FLIPS - in_header))
    for offset in offsets:
        bit = int(rng.integers(8))
        changed = bytearray(data)
        changed[offset] ^= 1 << bit
        cases.append(Case(f"bit {bit} of byte {offset} flipped", region_of(int(offset)),
                          {**files, name: bytes(changed)}))
    for extra in (b"\0", b"\0" * 16, b"\x01"):
        cases.append(Case(f"{len(extra)} bytes appended", "structure",
                          {**files, name: data + extra}))
    return cases


def npy_cases(files, rng, crop):
    data = files["ct.npy"]
    header_end = data.index(b"\n") + 1
    descr = data.index(b"'descr': '") + len(b"'descr': '")
    cases = generic_cases(files, rng, header_end, lambda o: "data" if o >= header_end else
                          "value" if descr <= o < descr + 3 else "structure")

    def edit(old, new):
        """The header with ``old`` replaced, its padding adjusted to keep its length."""
        assert old in data[:header_end]
        header = data[:header_end - 1].replace(old, new, 1).rstrip(b" ").ljust(header_end - 1)
        assert len(header) == header_end - 1
        return {"ct.npy": header + data[header_end - 1:]}

    cases += [
        Case("shape shrunk", "crafted", edit(b"(24, 16, 6)", b"(24, 16, 5)"), "refused"),
        Case("shape grown", "crafted", edit(b"(24, 16, 6)", b"(24, 16, 7)"), "refused"),
        Case("shape huge", "crafted", edit(b"(24, 16, 6)", b"(2400000, 1600000, 600000)"),
             "refused"),
        Case("shape negative", "crafted", edit(b"(24, 16, 6)", b"(24, -16, 6)"), "refused"),
        Case("shape 2-D", "crafted", edit(b"(24, 16, 6)", b"(384, 6)"), "refused"),
        Case("dtype wider", "crafted", edit(b"'<i2'", b"'<i4'"), "refused"),
        Case("dtype object", "crafted", edit(b"'<i2'", b"'|O'"), "refused"),
        Case("dtype bytes", "crafted", edit(b"'<i2'", b"'|S2'"), "refused"),
        Case("dtype big-endian", "crafted", edit(b"'<i2'", b"'>i2'"),
             (crop.byteswap(), {})),
        Case("dtype unsigned", "crafted", edit(b"'<i2'", b"'<u2'"),
             (crop.view(np.uint16), {})),
        Case("Fortran order", "crafted", edit(b"False", b"True"), (fortran_reread(crop), {})),
        Case("header length huge", "crafted",
             {"ct.npy": data[:8] + b"\xff\xff" + data[10:]}, "refused"),
        Case("version 3.0", "crafted", {"ct.npy": data[:6] + b"\x03\x00" + data[8:]},
             "refused"),
        Case("not closed", "crafted", edit(b"6), }", b"6), '''"), "refused"),
        Case("npz archive", "crafted", {"ct.npy": b"PK\x03\x04" + data[4:]}, "refused"),
    ]
    return cases


def fortran_reread(crop):
    """The crop's C-order bytes read as a Fortran-order array of the same shape."""
    return np.frombuffer(crop.tobytes(), crop.dtype).reshape(crop.shape, order="F")


def raw_cases(files, rng, crop):
    return generic_cases(files, rng, 0, lambda o: "data")


def nifti_regions(data):
    """``region_of`` for a NIfTI-1 file: value fields, data, or structure."""
    import nibabel as nib

    fields = nib.Nifti1Header.template_dtype.fields
    values = [(fields[n][1], fields[n][1] + fields[n][0].itemsize) for n in NIFTI_VALUE_FIELDS]
    return lambda o: ("data" if o >= 352 else
                      "value" if any(a <= o < b for a, b in values) else "structure")


def nifti_crafted(data, crop):
    """Crafted NIfTI-1 headers: ``(label, bytes, expect)``."""
    scaled = crop.astype(np.float64) * 2.0 - 5.0
    return [
        ("dims shrunk", patch_nifti(data, dim=[3, 24, 16, 5, 1, 1, 1, 1]), "refused"),
        ("dims grown", patch_nifti(data, dim=[3, 24, 16, 7, 1, 1, 1, 1]), "refused"),
        ("dims huge", patch_nifti(data, dim=[3, 32767, 32767, 32767, 1, 1, 1, 1]), "refused"),
        ("dims 4-D", patch_nifti(data, dim=[4, 24, 16, 3, 2, 1, 1, 1]), "refused"),
        ("dims 0-D", patch_nifti(data, dim=[0, 24, 16, 6, 1, 1, 1, 1]), "refused"),
        ("dims negative", patch_nifti(data, dim=[3, 24, -16, 6, 1, 1, 1, 1]), "refused"),
        ("dims with unit 4th axis", patch_nifti(data, dim=[4, 24, 16, 6, 1, 1, 1, 1]),
         (crop, {})),
        ("datatype float32", patch_nifti(data, datatype=16), "refused"),
        ("datatype float32 bitpix 32", patch_nifti(data, datatype=16, bitpix=32), "refused"),
        ("datatype uint8 bitpix 8", patch_nifti(data, datatype=2, bitpix=8), "refused"),
        ("datatype unknown", patch_nifti(data, datatype=99), "refused"),
        ("datatype complex", patch_nifti(data, datatype=32, bitpix=64), "refused"),
        ("datatype uint16", patch_nifti(data, datatype=512), (crop.view(np.uint16), {})),
        ("bitpix 8", patch_nifti(data, bitpix=8), "refused"),
        ("vox_offset 0", patch_nifti(data, vox_offset=0), "refused"),
        ("vox_offset 348", patch_nifti(data, vox_offset=348), "refused"),
        ("vox_offset 352.5", patch_nifti(data, vox_offset=352.5), "refused"),
        ("vox_offset 368", patch_nifti(data, vox_offset=368), "refused"),
        ("magic ni1", patch_nifti(data, magic=b"ni1"), "refused"),
        ("magic garbage", patch_nifti(data, magic=b"xyz"), "refused"),
        ("sizeof_hdr 349", patch_nifti(data, sizeof_hdr=349), "refused"),
        ("pixdim 0 under sform", patch_nifti(data, pixdim=[1, 0, 0, 0, 1, 1, 1, 1]), (crop, {})),
        ("pixdim 0 without sform", patch_nifti(data, sform_code=0, qform_code=0,
                                               pixdim=[1, 0, 0, 0, 1, 1, 1, 1]),
         (crop, {"spacing": (1.0, 1.0, 1.0), "spacing_known": False, **base_geometry(crop)})),
        ("pixdim one 0 without sform", patch_nifti(data, sform_code=0,
                                                   pixdim=[1, 0.5, 0, 0.7, 1, 1, 1, 1]),
         "refused"),
        ("pixdim NaN without sform", patch_nifti(data, sform_code=0,
                                                 pixdim=[1, 0.5, np.nan, 0.7, 1, 1, 1, 1]),
         "refused"),
        ("pixdim negative without sform", patch_nifti(data, sform_code=0,
                                                      pixdim=[1, -0.5, 0.6, 0.7, 1, 1, 1, 1]),
         "refused"),
        ("scl_slope NaN", patch_nifti(data, scl_slope=np.nan, scl_inter=7.0), (crop, {})),
        ("scl_slope 0", patch_nifti(data, scl_slope=0.0, scl_inter=7.0), (crop, {})),
        ("scl_slope 2 inter -5", patch_nifti(data, scl_slope=2.0, scl_inter=-5.0), (scaled, {})),
        ("scl_inter inf", patch_nifti(data, scl_slope=2.0, scl_inter=np.inf), "refused"),
        ("scl_slope inf", patch_nifti(data, scl_slope=np.inf), (crop, {})),
        ("xyzt_units unknown", patch_nifti(data, xyzt_units=7), "refused"),
        ("srow NaN", patch_nifti(data, srow_x=[np.nan, 0, 0, 0]), "refused"),
        ("srow zero column", patch_nifti(data, srow_x=[0.5, 0, 0, -10], srow_y=[0, 0, 0, 18],
                                         srow_z=[0, 0, 0.7, 3.5]), "refused"),
    ]


def base_geometry(crop):
    """Origin and orientation (LPS) nibabel gives a header without sform or qform, 1 mm voxels."""
    import nibabel as nib

    header = nib.Nifti1Header()
    header.set_data_shape(crop.shape)
    affine = np.diag([-1.0, -1.0, 1.0, 1.0]) @ header.get_base_affine()
    return {"origin": tuple(affine[:3, 3]), "orientation": affine[:3, :3]}


def nii_cases(files, rng, crop):
    data = files["ct.nii"]
    cases = generic_cases(files, rng, 352, nifti_regions(data))
    return cases + [Case(label, "crafted", {"ct.nii": bytes_}, expect)
                    for label, bytes_, expect in nifti_crafted(data, crop)]


def nii_gz_cases(files, rng, crop):
    data = files["ct.nii.gz"]
    plain = gzip.decompress(data)
    # Every byte is gzip header or deflate stream behind the CRC-32: all "structure".
    cases = generic_cases(files, rng, len(data) // 2, lambda o: "structure")

    def trailer(crc=None, size=None):
        body = bytearray(data)
        if crc is not None:
            body[-8:-4] = crc.to_bytes(4, "little")
        if size is not None:
            body[-4:] = size.to_bytes(4, "little")
        return bytes(body)

    crc = int.from_bytes(data[-8:-4], "little")
    cases += [
        Case("CRC wrong", "crafted", {"ct.nii.gz": trailer(crc=crc ^ 0x80000000)}, "refused"),
        Case("length wrong", "crafted", {"ct.nii.gz": trailer(size=len(plain) + 1)}, "refused"),
        Case("inflates past the header", "crafted",
             {"ct.nii.gz": gzip.compress(plain + bytes(1 << 20))}, "refused"),
        Case("inflates short", "crafted", {"ct.nii.gz": gzip.compress(plain[:-1])}, "refused"),
        Case("deflate bomb", "crafted",
             {"ct.nii.gz": gzip.compress(patch_nifti(plain, dim=[3, 16384, 16384, 16384, 1, 1,
                                                                  1, 1]) + bytes(8 << 20))},
             "refused"),
        Case("two gzip members", "crafted",
             {"ct.nii.gz": gzip.compress(plain[:1000]) + gzip.compress(plain[1000:])},
             (crop, {})),
        Case("not gzip", "crafted", {"ct.nii.gz": plain}, "refused"),
        Case("gzip mtime changed", "crafted", {"ct.nii.gz": data[:4] + b"\x01\x02\x03\x04"
                                                + data[8:]}, (crop, {})),
        Case("gzip FHCRC flag set", "crafted", {"ct.nii.gz": data[:3] + bytes([data[3] | 2])
                                                 + data[4:]}, "refused"),
        Case("gzip FNAME flag set", "crafted", {"ct.nii.gz": data[:3] + bytes([data[3] | 8])
                                                 + data[4:]}, "refused"),
        Case("gzip method not deflate", "crafted", {"ct.nii.gz": data[:2] + b"\x07"
                                                     + data[3:]}, "refused"),
        Case("trailing garbage", "crafted", {"ct.nii.gz": data + b"garbage"}, "refused"),
    ]
    cases += [Case(label, "crafted", {"ct.nii.gz": gzip.compress(bytes_)}, expect)
              for label, bytes_, expect in nifti_crafted(plain, crop)]
    return cases


def nrrd_regions(data, header_end, compressed):
    """``region_of`` for a NRRD file: value fields, data, or structure."""
    header = data[:header_end]
    values = []
    start = 0
    for line in header.split(b"\n"):
        name, colon, _ = line.partition(b":")
        if colon and name.decode("ascii") in NRRD_VALUE_FIELDS:
            values.append((start + len(name) + 1, start + len(line)))
        start += len(line) + 1
    return lambda o: ("structure" if o >= header_end and compressed else
                      "data" if o >= header_end else
                      "value" if any(a <= o < b for a, b in values) else "structure")


def nrrd_crafted(name, files, crop):
    """Crafted NRRD headers (``name`` holds the header): ``Case`` list."""
    data = files[name]

    def edit(old, new):
        assert old in data, old
        return {**files, name: data.replace(old, new, 1)}

    return [
        Case("sizes shrunk", "crafted", edit(b"sizes: 24 16 6", b"sizes: 24 16 5"), "refused"),
        Case("sizes grown", "crafted", edit(b"sizes: 24 16 6", b"sizes: 24 16 7"), "refused"),
        Case("sizes huge", "crafted", edit(b"sizes: 24 16 6", b"sizes: 240000 160000 60000"),
             "refused"),
        Case("sizes 4-D", "crafted", edit(b"sizes: 24 16 6", b"sizes: 24 16 3 2"), "refused"),
        Case("dimension 2", "crafted", edit(b"dimension: 3", b"dimension: 2"), "refused"),
        Case("type int8", "crafted", edit(b"type: int16", b"type: int8"), "refused"),
        Case("type float", "crafted", edit(b"type: int16", b"type: float"), "refused"),
        Case("type unknown", "crafted", edit(b"type: int16", b"type: int12"), "refused"),
        Case("type uint16", "crafted", edit(b"type: int16", b"type: uint16"),
             (crop.view(np.uint16), {})),
        Case("endian big", "crafted", edit(b"endian: little", b"endian: big"),
             (crop.byteswap(), {})),
        Case("endian missing", "crafted", edit(b"endian: little\n", b""), "refused"),
        Case("endian garbled", "crafted", edit(b"endian: little", b"endian: lottle"), "refused"),
        Case("encoding garbled", "crafted", edit(b"encoding: ", b"encoding: x"), "refused"),
        Case("encoding bzip2", "crafted", edit(b"encoding: ", b"encoding: bzip2\n#"),
             "refused"),
        Case("space origin misspelt", "crafted", edit(b"space origin:", b"space orgin:"),
             "refused"),
        Case("space origin garbled name", "crafted", edit(b"space origin:", b"spaceorigin:"),
             "refused"),
        Case("space origin non-ASCII", "crafted", edit(b"space origin: (", b"space origin: (\xad"),
             "refused"),
        Case("space origin 2-D", "crafted", edit(b"space origin: (-20,30,5)",
                                                 b"space origin: (-20,30)"), "refused"),
        Case("space origin unclosed", "crafted", edit(b"space origin: (-20,30,5)",
                                                      b"space origin: (-20,30,5"), "refused"),
        Case("space origin NaN", "crafted", edit(b"space origin: (-20,30,5)",
                                                 b"space origin: (nan,30,5)"), "refused"),
        Case("space unknown", "crafted", edit(b"space: left-posterior-superior",
                                              b"space: left-posterior-inferior"), "refused"),
        Case("space directions 2", "crafted", edit(b"space directions: (0.5,0,0) ",
                                                   b"space directions: "), "refused"),
        Case("space directions zero", "crafted", edit(b"space directions: (0.5,0,0)",
                                                      b"space directions: (0,0,0)"), "refused"),
        Case("space units unknown", "crafted", edit(b"encoding:", b"space units: \"furlong\" "
                                                    b"\"mm\" \"mm\"\nencoding:"), "refused"),
        Case("field duplicated", "crafted",
             edit(b"dimension: 3\n", b"dimension: 3\ndimension: 3\n"), "refused"),
        Case("unknown field", "crafted",
             edit(b"dimension: 3\n", b"dimension: 3\nsapcings: 1 1 1\n"), "refused"),
        Case("key/value pair", "crafted", edit(b"dimension: 3\n", b"dimension: 3\nnote:=hello\n"),
             (crop, {})),
        Case("byte skip 1", "crafted", edit(b"dimension: 3\n", b"dimension: 3\nbyte skip: 1\n"),
             "refused"),
        Case("byte skip -2", "crafted", edit(b"dimension: 3\n", b"dimension: 3\nbyte skip: -2\n"),
             "refused"),
        Case("line skip 1", "crafted", edit(b"dimension: 3\n", b"dimension: 3\nline skip: 1\n"),
             "refused"),
        Case("magic garbled", "crafted", edit(b"NRRD0005", b"NRRD0009"), "refused"),
        Case("no magic", "crafted", edit(b"NRRD0005", b"MRRD0005"), "refused"),
    ]


def nrrd_cases(files, rng, crop):
    name = next(iter(files))
    data = files[name]
    header_end = data.index(b"\n\n") + 2 if name.endswith(".nrrd") else len(data)
    compressed = b"encoding: gzip" in data
    cases = generic_cases(files, rng, header_end, nrrd_regions(data, header_end, compressed))
    if name.endswith(".nhdr"):  # the detached data file: truncated, flipped, padded
        data_name = next(n for n in files if n != name)
        cases += [Case(f"data file {c.label}", c.kind, {name: data, data_name: c.files[name]})
                  for c in generic_cases({name: files[data_name]}, rng, 0, lambda o: "data")]
        cases += [Case("data file missing", "crafted", {name: data}, "refused"),
                  Case("data file renamed", "crafted",
                       {name: data.replace(data_name.encode(), b"elsewhere.raw"),
                        data_name: files[data_name]}, "refused")]
    if compressed:
        cut = data.index(b"\n\n") + 2
        body = bytearray(data)
        body[-8] ^= 0x01
        cases += [Case("gzip CRC wrong", "crafted", {name: bytes(body)}, "refused"),
                  Case("gzip replaced by raw", "crafted",
                       {name: data[:cut] + crop.T.tobytes()}, "refused"),
                  Case("gzip inflates past the sizes", "crafted",
                       {name: data[:cut] + gzip.compress(crop.T.tobytes() + bytes(1 << 20))},
                       "refused"),
                  Case("gzip two members", "crafted",
                       {name: data[:cut] + gzip.compress(crop.T.tobytes()[:500])
                        + gzip.compress(crop.T.tobytes()[500:])}, (crop, {}))]
    return cases + nrrd_crafted(name, files, crop)


def den_cases(files, rng, crop):
    data = files["ct.den"]
    cases = generic_cases(files, rng, 62, lambda o: "data" if o >= 62 else "structure")
    swapped = np.frombuffer(data[:58], "<i2").astype(">i2").tobytes()
    swapped += np.frombuffer(data[58:62], "<i4").astype(">i4").tobytes()

    def fields(**changes):
        header = np.frombuffer(data[:58], "<i2").copy()
        for index, value in changes.items():
            header[int(index[1:])] = value
        return {"ct.den": header.tobytes() + data[58:]}

    return cases + [
        Case("big-endian header", "crafted", {"ct.den": swapped + data[62:]},
             (den_array(crop), {})),
        Case("version 2", "crafted", fields(f0=2), "refused"),
        Case("map_len shrunk", "crafted", fields(f27=5), "refused"),
        Case("map_len negative", "crafted", fields(f26=-16), "refused"),
        Case("map_len huge", "crafted", fields(f25=32767, f26=32767, f27=32767), "refused"),
        Case("map_length huge", "crafted",
             {"ct.den": data[:58] + (2**31 - 1).to_bytes(4, "little") + data[62:]}, "refused"),
    ]


# ---------------------------------------------------------------------------------------------
# running a case


class Timeout(BaseException):
    """A read that took longer than :data:`SLOWEST` (not an Exception: no reader may catch it)."""


def _alarm(signum, frame):
    raise Timeout


def outcome(case, folder, options, reference, violations):
    """Write ``case``, read it, classify the result; append any violation of the rules.

    A refusal must name a file of the case's folder first: the file read, or the data file its
    header names.
    """
    for old in folder.iterdir():
        old.unlink()
    for name, content in case.files.items():
        (folder / name).write_bytes(content)
    path = folder / next(iter(case.files))
    signal.setitimer(signal.ITIMER_REAL, SLOWEST)
    try:
        vol = read_volume(path, **options)
    except VolumeEVMError as exc:
        signal.setitimer(signal.ITIMER_REAL, 0)
        named = re.match(f"{re.escape(str(folder))}/[^/]+: ", str(exc))
        if not named:
            violations.append(f"{case.label}: message does not start with the path: {exc}")
        if isinstance(case.expect, tuple):
            violations.append(f"{case.label}: refused a valid header ({exc})")
        return "refused"
    except Timeout:
        violations.append(f"{case.label}: took more than {SLOWEST} s")
        return "hang"
    except Exception as exc:  # noqa: BLE001 - the very thing the fuzz looks for
        signal.setitimer(signal.ITIMER_REAL, 0)
        violations.append(f"{case.label}: {type(exc).__name__}: {exc}")
        return "other exception"
    signal.setitimer(signal.ITIMER_REAL, 0)
    if isinstance(case.expect, tuple):
        array, changes = case.expect
        expected = {**reference, "array": array, **changes}
        if not same(vol, expected):
            violations.append(f"{case.label}: does not read as its header announces")
        return "as announced"
    if same(vol, reference):
        if case.expect == "refused":
            violations.append(f"{case.label}: accepted")
        return "exact"
    if case.kind == "data" and same_geometry(vol, reference):
        differs = np.count_nonzero(vol.array != reference["array"])
        if vol.array.dtype == reference["array"].dtype and differs == 1:
            return "undetectable data change"
    if case.kind == "value":
        return "undetectable header value"
    violations.append(f"{case.label} ({case.kind}): read as different data")
    return "different"


def same_geometry(vol, expected):
    return (vol.spacing == expected["spacing"] and vol.origin == expected["origin"]
            and np.array_equal(vol.orientation, expected["orientation"])
            and vol.units == expected["units"]
            and vol.spacing_known == expected["spacing_known"])


def same(vol, expected):
    return (vol.array.dtype == expected["array"].dtype
            and vol.array.shape == expected["array"].shape
            and np.array_equal(vol.array, expected["array"]) and same_geometry(vol, expected))


FORMATS = {
    "npy": (lambda tmp, crop: npy_seed(crop), npy_cases, {}),
    "raw": (lambda tmp, crop: raw_seed(crop), raw_cases,
            {"shape": (24, 16, 6), "dtype": "int16", "spacing": SPACING}),
    "nii": (lambda tmp, crop: nifti_seed(tmp, crop, "ct.nii"), nii_cases, {}),
    "nii.gz": (lambda tmp, crop: nifti_seed(tmp, crop, "ct.nii.gz"), nii_gz_cases, {}),
    "nrrd raw": (lambda tmp, crop: nrrd_seed(tmp, crop, "ct.nrrd", encoding="raw"),
                 nrrd_cases, {}),
    "nrrd gzip": (lambda tmp, crop: nrrd_seed(tmp, crop, "ct.nrrd", encoding="gzip"),
                  nrrd_cases, {}),
    "nhdr": (lambda tmp, crop: nrrd_seed(tmp, crop, "ct.nhdr", encoding="raw",
                                         detached_header=True), nrrd_cases, {}),
    "den": (den_seed, den_cases, {}),
}


@pytest.mark.parametrize("fmt", list(FORMATS))
def test_fuzz_reader(tmp_path, crop, fmt):
    seed, make_cases, options = FORMATS[fmt]
    files = seed(tmp_path, crop)
    folder = tmp_path / "case"
    folder.mkdir()
    for name, content in files.items():
        (folder / name).write_bytes(content)
    vol = read_volume(folder / next(iter(files)), **options)
    reference = {"array": vol.array, "spacing": vol.spacing, "origin": vol.origin,
                 "orientation": vol.orientation, "units": vol.units,
                 "spacing_known": vol.spacing_known}
    reference["array"] = den_array(crop) if fmt == "den" else crop
    assert same(vol, reference)  # the seed itself reads exactly
    rng = np.random.default_rng([SEED, list(FORMATS).index(fmt)])
    previous = signal.signal(signal.SIGALRM, _alarm)
    violations = []
    counts = collections.defaultdict(collections.Counter)
    try:
        for case in make_cases(files, rng, crop):
            counts[group(case)][outcome(case, folder, options, reference, violations)] += 1
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, previous)
    total = sum(sum(c.values()) for c in counts.values())
    summary = " | ".join(f"{g}: " + ", ".join(f"{k} {v}" for k, v in sorted(c.items()))
                         for g, c in sorted(counts.items()))
    print(f"\nfuzz {fmt}: {total} cases | {summary}")
    assert not violations, "\n".join(violations[:20])
    assert sum(c["refused"] for c in counts.values()) > 0


def group(case):
    """The mutation's group for the summary: truncation, flip, appended bytes or crafted."""
    if "truncated" in case.label:
        return "truncation"
    if "flipped" in case.label:
        return {"data": "flip in data", "value": "flip in header value"}.get(
            case.kind, "flip in structure")
    return "appended bytes" if "appended" in case.label else "crafted"
