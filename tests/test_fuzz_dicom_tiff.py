"""Fuzz the DICOM and TIFF readers: mutate valid files, every case exact or a clear error.

Valid files are written by the reference libraries (pydicom, cloning its real ``CT_small.dcm``;
tifffile as plain, ImageJ and OME-TIFF) from a crop of the real CT head, then mutated with a
seeded generator: truncations, byte flips in headers, tags and descriptions, byte flips in the
pixel data, and crafted values of the fields the readers use. Each case must end in one of:

- ``exact``: the same array (values and dtype), spacing, origin, orientation and units as the
  unmutated file;
- ``error``: a ``VolumeEVMError`` whose message starts with the file (the folder for a DICOM
  series) and, for DICOM, names the mutated slice file;
- ``undetectable``: a change no reader can see, because the file has no checksum: a flipped
  pixel byte (only that slice's voxels change, the geometry does not), or a header value the
  reference library still parses as a valid value of the same field (a rescale, a position, a
  TIFF resolution, a number in an ImageJ/OME description, a strip offset moved onto unused
  bytes). These are counted apart and must show exactly that kind of difference;
- ``spacing lost`` (TIFF header flips only): the tag holding the ImageJ or OME description is
  no longer found, so the same array reads as a plain stack whose spacing is reported unknown
  (``spacing_known`` False), never as a wrong known spacing.

Anything else (another exception type, a different result not explained as above) is a failure.
Crafted values and truncations must be exact or an error. The counts per format and class are
printed (``pytest -s``) and the whole file runs in well under a minute on one core.
"""

import shutil
import struct
import warnings
from collections import Counter

import numpy as np
import pytest

from reader_files import write_series, write_tiff
from volumeevm_addon import VolumeEVMError
from volumeevm_addon.readers import read_volume

SEED = 20261124


@pytest.fixture(scope="module")
def hu(data_dir):
    """A 16 x 12 x 5 crop of the real CT head in HU (int16)."""
    array = np.load(data_dir / "ct_head_invesalius.npy")
    return np.ascontiguousarray(array[100:116, 60:72, 50:55])


# ---------------------------------------------------------------------------------------------
# outcomes


def same_volume(a, b):
    """Whether two volumes are the same: array and dtype, geometry and units."""
    return (a.array.dtype == b.array.dtype and a.array.shape == b.array.shape
            and np.array_equal(a.array, b.array) and a.spacing == b.spacing
            and a.origin == b.origin and np.array_equal(a.orientation, b.orientation)
            and a.units == b.units and a.spacing_known == b.spacing_known)


def outcome(read, reference, source, named):
    """``("exact" | "error" | "unnamed error" | "different", detail)`` of one read.

    An ``error`` is a ``VolumeEVMError`` whose message starts with ``source`` and contains
    ``named``; any other exception propagates and fails the test.
    """
    try:
        vol = read()
    except VolumeEVMError as error:
        message = str(error)
        named_well = message.startswith(str(source)) and named in message
        return ("error" if named_well else "unnamed error"), message
    return ("exact", None) if same_volume(vol, reference) else ("different", vol)


def record(counts, failures, kind, what, result, allowed, explain):
    """Count ``result`` under ``kind``; note a failure (with ``what`` was mutated) when it is
    not an allowed class."""
    name, detail = result
    if name == "different":
        name = explain(detail)
    counts[(kind, name)] += 1
    if name in ("undetectable", "spacing lost") and kind != "flip pixels":
        print(f"  {name} {kind}: {what}")
    if name not in allowed:
        shown = detail if isinstance(detail, str) else f"array {detail.array.ravel()[:6]}, " \
            f"spacing {detail.spacing}, origin {detail.origin}" if detail is not None else ""
        failures.append(f"{kind} ({what}): {name}: {shown}")


def summary(fmt, counts):
    """One line of counts per mutation kind and outcome class."""
    total = sum(counts.values())
    parts = ", ".join(f"{kind} {name} {n}" for (kind, name), n in sorted(counts.items()))
    line = f"fuzz {fmt}: {total} cases: {parts}"
    print(line)
    return line


# ---------------------------------------------------------------------------------------------
# DICOM


#: Crafted values of the fields the DICOM reader uses; none is a valid alternative.
DICOM_CRAFTED = [
    ("Rows", v) for v in (0, 1, 11, 13, 65535)] + [
    ("Columns", v) for v in (0, 15, 17, 65535)] + [
    ("BitsAllocated", v) for v in (0, 1, 8, 12, 32, 64)] + [
    ("BitsStored", v) for v in (0, 8, 17)] + [
    ("PixelRepresentation", v) for v in (0, 2)] + [
    ("SamplesPerPixel", v) for v in (0, 3)] + [
    ("NumberOfFrames", v) for v in (0, 2)] + [
    ("RescaleSlope", v) for v in (0, float("nan"), float("inf"), float("-inf"), "")] + [
    ("RescaleIntercept", v) for v in (float("nan"), float("inf"), "")] + [
    ("ImageOrientationPatient", v) for v in (
        [1, 0, 0, 0.5, 0.8660254, 0], [1, 0, 0, 1, 0, 0], [2, 0, 0, 0, 2, 0],
        [0, 0, 0, 0, 0, 0], [1, 0, 0, 0, float("nan"), 0], [1, 0, 0, 0, 1], "")] + [
    ("ImagePositionPatient", v) for v in (
        [0, float("nan"), 42], [0, float("inf"), 42], [0, 1], "", [-16, -20.5, 42.625],
        [-16, -20.5, 43.25])] + [
    ("PixelSpacing", v) for v in (
        [0.75, 0], [-0.75, 0.5], [float("nan"), 0.5], [float("inf"), 0.5], [0.75], "",
        [0.75, 0.5, 1])] + [
    (keyword, None) for keyword in (
        "Rows", "Columns", "BitsAllocated", "SeriesInstanceUID", "ImagePositionPatient",
        "ImageOrientationPatient", "PixelSpacing", "RescaleSlope", "PixelData")]

#: DICOM elements a byte flip may change into another valid value, and what that changes.
DICOM_VALUES = {
    "array": {"RescaleSlope", "RescaleIntercept"},
    "geometry": {"ImagePositionPatient", "ImageOrientationPatient", "PixelSpacing"},
    "units": {"Modality"},
}


def dicom_elements(path):
    """``{tag: (VR, value)}`` of a DICOM file as pydicom parses it, or ``None`` if it fails."""
    import pydicom

    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            ds = pydicom.dcmread(path, force=True)
            return {element.tag: (element.VR, repr(element.value)) for element in ds}
    except Exception:  # the classification only asks whether pydicom still parses it
        return None


def explain_dicom(original, mutated, reference, region, slice_index):
    """Class of a read that succeeded with a different result (see the module notes)."""
    def explain(vol):
        geometry_same = (vol.spacing == reference.spacing and vol.origin == reference.origin
                         and np.array_equal(vol.orientation, reference.orientation))
        if region == "pixels":
            changed = np.argwhere(vol.array != reference.array)
            if (geometry_same and vol.array.shape == reference.array.shape
                    and set(changed[:, 2]) == {slice_index}):
                return "undetectable"
            return "different"
        before, after = dicom_elements(original), dicom_elements(mutated)
        if before is None or after is None or before.keys() != after.keys():
            return "different"
        if any(before[tag][0] != after[tag][0] for tag in before):
            return "different"
        import pydicom

        changed = {pydicom.datadict.keyword_for_tag(tag) for tag in before
                   if before[tag] != after[tag]}
        allowed = set()
        if not np.array_equal(vol.array, reference.array) or vol.array.dtype != (
                reference.array.dtype):
            allowed |= DICOM_VALUES["array"]
        if not geometry_same:
            allowed |= DICOM_VALUES["geometry"]
        if vol.units != reference.units:
            allowed |= DICOM_VALUES["units"]
        return "undetectable" if changed and changed <= allowed else "different"
    return explain


#: Elements the reader uses, (group, element, VR) as written (explicit VR little endian).
DICOM_USED = [
    (0x0008, 0x0060, "CS"), (0x0020, 0x000E, "UI"), (0x0020, 0x0032, "DS"),
    (0x0020, 0x0037, "DS"), (0x0028, 0x0002, "US"), (0x0028, 0x0010, "US"),
    (0x0028, 0x0011, "US"), (0x0028, 0x0030, "DS"), (0x0028, 0x0100, "US"),
    (0x0028, 0x0101, "US"), (0x0028, 0x0103, "US"), (0x0028, 0x1052, "DS"),
    (0x0028, 0x1053, "DS"), (0x0002, 0x0010, "UI"),
]


def element_span(raw, group, element, vr):
    """``(start, end)`` of a short-VR element (tag, VR, length and value) in a file's bytes."""
    start = raw.index(struct.pack("<HH", group, element) + vr.encode())
    (length,) = struct.unpack_from("<H", raw, start + 6)
    return start, start + 8 + length


def pixel_range(raw, pixels):
    """``(start, end)`` of the pixel bytes ``pixels`` in a file's bytes."""
    start = raw.rindex(pixels)
    return start, start + len(pixels)


def test_fuzz_dicom_series(tmp_path, hu):
    import pydicom

    original = tmp_path / "original"
    write_series(original, hu)
    reference = read_volume(original)
    np.testing.assert_array_equal(reference.array, hu)
    work = tmp_path / "work"
    rng = np.random.default_rng(SEED)
    counts, failures = Counter(), []
    plan = (["truncate"] * 40 + ["flip header"] * 120 + ["flip element"] * 120
            + ["flip pixels"] * 30
            + [("craft", item) for item in DICOM_CRAFTED])
    for case, kind in enumerate(plan):
        shutil.rmtree(work, ignore_errors=True)
        shutil.copytree(original, work)
        k = int(rng.choice([0, hu.shape[2] - 1, int(rng.integers(hu.shape[2]))]))
        target = work / f"IM{k:04d}.dcm"
        raw = target.read_bytes()
        pixels = np.ascontiguousarray(hu[:, :, k].T + 1024, dtype="<i2").tobytes()
        start, end = pixel_range(raw, pixels)
        region = "header"
        if kind == "truncate":
            cut = int(rng.integers(len(raw)))
            target.write_bytes(raw[:cut])
            what = f"{target.name} cut at {cut}"
        elif kind in ("flip header", "flip element", "flip pixels"):
            if kind == "flip element":
                used = DICOM_USED[int(rng.integers(len(DICOM_USED)))]
                where = int(rng.integers(*element_span(raw, *used)))
            else:
                where = (int(rng.integers(start, end)) if kind == "flip pixels"
                         else int(rng.integers(start - 8)))
            region = "pixels" if kind == "flip pixels" else "header"
            mutated = bytearray(raw)
            mutated[where] ^= int(rng.integers(1, 256))
            target.write_bytes(bytes(mutated))
            what = f"{target.name} byte {where} {raw[where]:#x} -> {mutated[where]:#x}"
        else:
            keyword, value = kind[1]
            every = bool(rng.integers(2))
            for path in sorted(work.iterdir()) if every else [target]:
                ds = pydicom.dcmread(path)
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")
                    if value is None:
                        delattr(ds, keyword)
                    else:
                        setattr(ds, keyword, value)
                    ds.save_as(path)
            what = f"{keyword}={value!r} in {'every slice' if every else target.name}"
            kind = f"craft {'all' if every else 'one'}"
        named = "IM" if kind == "craft all" else target.name
        result = outcome(lambda: read_volume(work), reference, work, named)
        allowed = {"exact", "error"} | ({"undetectable"} if kind.startswith("flip") else set())
        record(counts, failures, kind, what, result, allowed,
               explain_dicom(original / target.name, target, reference, region, k))
    line = summary("DICOM series", counts)
    assert not failures, f"{len(failures)} failures ({line}):\n" + "\n".join(failures[:20])
    assert counts[("flip pixels", "undetectable")] == 30


# ---------------------------------------------------------------------------------------------
# TIFF


def tiff_layout(path):
    """Per page: ``{tag name: (dtype, count, value offset, value)}`` and its strips' ranges."""
    import tifffile

    pages = []
    with tifffile.TiffFile(path) as tif:
        tif.pages.useframes = False
        for page in tif.pages:
            tags = {tag.name: (tag.dtype, tag.count, tag.valueoffset, repr(tag.value))
                    for tag in page.tags.values()}
            strips = [(int(o), int(o) + int(c)) for o, c in zip(page.dataoffsets,
                                                                 page.databytecounts)]
            pages.append((tags, strips, page.offset))
    return pages


def tiff_tags(path):
    """tifffile's tags of every page, or ``None`` if tifffile cannot parse the file."""
    try:
        return [tags for tags, _, _ in tiff_layout(path)]
    except Exception:  # the classification only asks whether tifffile still parses it
        return None


#: Tags a byte flip may change into another valid value, and what that changes.
TIFF_VALUES = {"array": {"StripOffsets"},
               "spacing": {"XResolution", "YResolution", "ImageDescription"}}


def explain_tiff(original, mutated, reference, region):
    """Class of a read that succeeded with a different result (see the module notes)."""
    def explain(vol):
        if region == "pixels":
            same_rest = (vol.spacing == reference.spacing and vol.array.shape
                         == reference.array.shape and vol.array.dtype == reference.array.dtype)
            return "undetectable" if same_rest else "different"
        if (np.array_equal(vol.array, reference.array) and reference.spacing_known
                and not vol.spacing_known):
            return "spacing lost"  # the metadata tag itself is gone: spacing reported unknown
        before, after = tiff_tags(original), tiff_tags(mutated)
        if before is None or after is None or len(before) != len(after):
            return "different"
        changed = set()
        for old, new in zip(before, after):
            if old.keys() != new.keys():
                return "different"
            for name in old:
                if old[name][:3] != new[name][:3]:
                    return "different"
                if old[name] != new[name]:
                    changed.add(name)
        allowed = set()
        if not np.array_equal(vol.array, reference.array):
            allowed |= TIFF_VALUES["array"]
        if vol.spacing != reference.spacing:
            allowed |= TIFF_VALUES["spacing"]
        return "undetectable" if changed and changed <= allowed else "different"
    return explain


def pack(dtype, value):
    """A TIFF field value in the file's (little-endian) encoding."""
    if dtype == 3:
        return struct.pack("<H", min(value, 0xFFFF))
    if dtype == 5:
        return struct.pack("<II", *value)
    return struct.pack("<I", value)


#: Crafted tag values (any page); ``"+"`` adds to the current value (offsets).
TIFF_CRAFTED = [
    ("ImageWidth", v) for v in (0, 1, 15, 17, 0xFFFF, 0xFFFFFFF0)] + [
    ("ImageLength", v) for v in (0, 1, 11, 13, 0xFFFFFFF0)] + [
    ("StripOffsets", ("+", d)) for d in (1, 2, -1, -2, 384, -384)] + [
    ("StripOffsets", v) for v in (0, 10**9)] + [
    ("StripByteCounts", v) for v in (0, 382, 386, 0xFFFFFFF0)] + [
    ("BitsPerSample", v) for v in (1, 8, 12, 32, 64)] + [
    ("SampleFormat", v) for v in (1, 3, 7)] + [
    ("Compression", v) for v in (5, 8, 65000)] + [
    ("SamplesPerPixel", v) for v in (0, 3)] + [
    ("PhotometricInterpretation", v) for v in (2, 3)] + [
    ("XResolution", v) for v in ((1, 0), (0, 1), (0, 0))]

#: Crafted description texts (same length as what they replace), by variant.
TIFF_TEXTS = {
    "plain": [],
    "imagej": [(b"images=5", b"images=" + c) for c in (b"9", b"0", b"x", b"-")]
    + [(b"slices=5", b"slices=9")]
    + [(b"spacing=1.5", b"spacing=" + t) for t in (b"nan", b"0.0", b"-1.", b"inf", b"abc")]
    + [(b"unit=mm", b"unit=zz")],
    "ome": [(b'SizeZ="5"', b'SizeZ="' + c + b'"') for c in (b"9", b"0", b"x", b"-", b"4")]
    + [(b'SizeC="1"', b'SizeC="2"'), (b'SizeT="1"', b'SizeT="2"'),
       (b'SizeX="16"', b'SizeX="17"'), (b'SizeY="12"', b'SizeY="99"'),
       (b'Type="int16"', b'Type="int32"'), (b'Type="int16"', b'Type="uint16')]
    + [(b'PhysicalSizeX="0.5"', b'PhysicalSizeX="' + t + b'"')
       for t in (b"0.0", b"nan", b"inf", b"-.5", b"abc")],
}


@pytest.mark.parametrize("variant", ["plain", "imagej", "ome"])
def test_fuzz_tiff_stack(tmp_path, hu, variant):
    suffix = ".ome.tif" if variant == "ome" else ".tif"
    original = tmp_path / f"original{suffix}"
    write_tiff(original, hu, variant)
    reference = read_volume(original)
    np.testing.assert_array_equal(reference.array, hu)
    raw = original.read_bytes()
    layout = tiff_layout(original)
    strips = [r for _, page_strips, _ in layout for r in page_strips]
    in_pixels = np.zeros(len(raw), bool)
    for start, end in strips:
        in_pixels[start:end] = True
    header_bytes = np.flatnonzero(~in_pixels)
    pixel_bytes = np.flatnonzero(in_pixels)
    path = tmp_path / f"mutated{suffix}"
    rng = np.random.default_rng(SEED + len(variant))
    counts, failures = Counter(), []
    plan = (["truncate"] * 30 + ["flip header"] * 120 + ["flip pixels"] * 20
            + [("craft", item) for item in TIFF_CRAFTED]
            + [("text", item) for item in TIFF_TEXTS[variant]])
    for kind in plan:
        mutated, region = bytearray(raw), "header"
        allowed = {"exact", "error"}
        if kind == "truncate":
            cut = int(rng.integers(len(raw)))
            del mutated[cut:]
            what = f"cut at {cut}"
        elif kind in ("flip header", "flip pixels"):
            region = "pixels" if kind == "flip pixels" else "header"
            where = int(rng.choice(pixel_bytes if region == "pixels" else header_bytes))
            mutated[where] ^= int(rng.integers(1, 256))
            what = f"byte {where} {raw[where]:#x} -> {mutated[where]:#x}"
            allowed |= {"undetectable", "spacing lost"}
        elif kind[0] == "craft":
            name, value = kind[1]
            page = int(rng.integers(len(layout)))
            tags, page_strips, _ = layout[page]
            dtype, _, offset, _ = tags[name]
            if isinstance(value, tuple) and value[0] == "+":
                # A strip moved by a few bytes onto unused padding reads as other valid bytes.
                value = page_strips[0][0] + value[1]
                allowed.add("undetectable")
            data = pack(dtype, value)
            mutated[offset:offset + len(data)] = data
            what = f"{name}={value} on page {page}"
            kind = "craft"
        else:
            old, new = kind[1]
            assert len(old) == len(new) and raw.count(old) == 1, old
            start = raw.index(old)
            mutated[start:start + len(old)] = new
            what = f"{old!r} -> {new!r}"
            kind = "text"
        path.write_bytes(bytes(mutated))
        result = outcome(lambda: read_volume(path), reference, path, path.name)
        record(counts, failures, kind, what, result, allowed,
               explain_tiff(original, path, reference, region))
    line = summary(f"TIFF {variant}", counts)
    assert not failures, f"{len(failures)} failures ({line}):\n" + "\n".join(failures[:20])
    assert counts[("flip pixels", "undetectable")] == 20
