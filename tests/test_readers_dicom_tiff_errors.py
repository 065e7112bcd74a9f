"""Bad DICOM series and TIFF stacks: each class of defect ends in a ``VolumeEVMError`` that
names the file (the slice file for DICOM), never in silently different data, another exception
type, a hang or an allocation the file cannot justify.

Files are written by the reference libraries (pydicom from its real ``CT_small.dcm``, tifffile)
from a crop of the real CT head, then damaged in one precise way.
"""

import os
import re
import struct
import tracemalloc
import warnings

import numpy as np
import pytest

from reader_files import ORIGIN, SPACING, write_series, write_tiff
from volumeevm_addon import VolumeEVMError, _memory
from volumeevm_addon.readers import _dicom, _tiff, read_volume


@pytest.fixture(scope="module")
def ct_crop(data_dir):
    """A 24 x 16 x 6 crop of the real CT head in HU (int16): skull, brain and air."""
    array = np.load(data_dir / "ct_head_invesalius.npy")
    return np.ascontiguousarray(array[100:124, 60:76, 50:56])


def raises(path, match):
    """``pytest.raises(VolumeEVMError)`` whose message starts with ``path`` and matches."""
    return pytest.raises(VolumeEVMError, match=f"(?s)^{re.escape(str(path))}.*(?:{match})")


# ---------------------------------------------------------------------------------------------
# writers


def edit_slices(slices, **changes):
    """An ``edit`` for :func:`write_series` setting attributes on the slices ``slices``."""
    def edit(k, ds):
        if k in slices:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                for key, value in changes.items():
                    setattr(ds, key, value)
    return edit


def tag_value_offset(path, name, page=0):
    """Byte offset of the value (or inline value field) of tag ``name`` on ``page``."""
    import tifffile

    with tifffile.TiffFile(path) as tif:
        tif.pages.useframes = False
        return tif.pages[page].tags[name].valueoffset


def patch(path, offset, data):
    """Overwrite ``data`` at ``offset`` in the file."""
    raw = bytearray(path.read_bytes())
    raw[offset:offset + len(data)] = data
    path.write_bytes(bytes(raw))


def replace_text(path, old, new):
    """Replace ``old`` by ``new`` (same length) in the file, once."""
    raw = path.read_bytes()
    assert len(old) == len(new) and raw.count(old) == 1
    path.write_bytes(raw.replace(old, new))


# ---------------------------------------------------------------------------------------------
# DICOM: every file of the series accounted for


def test_dicom_series_reads_exactly(tmp_path, ct_crop):
    write_series(tmp_path / "s", ct_crop)
    vol = read_volume(tmp_path / "s")
    assert vol.array.dtype == np.int16
    np.testing.assert_array_equal(vol.array, ct_crop)
    assert vol.spacing == pytest.approx(SPACING)
    np.testing.assert_allclose(vol.origin, ORIGIN)


@pytest.mark.parametrize("which", [0, -1])
@pytest.mark.parametrize("damage, match", [
    ("header cut", "has no SeriesInstanceUID"),  # pydicom reads up to the cut without a word
    ("pixels cut", "cannot decode the pixel data"),
    ("marker lost", "not a readable DICOM file"),
])
def test_dicom_unreadable_first_or_last_slice_is_named(tmp_path, ct_crop, which, damage, match):
    files = write_series(tmp_path / "s", ct_crop)
    bad = files[which]
    raw = bad.read_bytes()
    if damage == "header cut":
        bad.write_bytes(raw[:700])
    elif damage == "pixels cut":
        pixels = np.ascontiguousarray(ct_crop[:, :, which].T + 1024, dtype="<i2").tobytes()
        bad.write_bytes(raw[:raw.rindex(pixels) + 300])
    else:
        bad.write_bytes(raw[:128] + b"DICX" + raw[132:])
    with raises(bad, match):
        read_volume(tmp_path / "s")


def test_dicom_folder_skips_files_that_are_not_dicom(tmp_path, ct_crop):
    import pydicom
    from pydicom.dataset import FileMetaDataset

    folder = tmp_path / "s"
    write_series(folder, ct_crop)
    (folder / "README").write_text("CT head, exported for tests\n")
    np.save(folder / "mask.npy", np.zeros((2, 2, 2)))
    os.mkfifo(folder / "pipe")  # never opened: reading it would block forever
    (folder / "sub").mkdir()
    directory = pydicom.Dataset()  # a DICOMDIR: DICOM, but no series
    directory.file_meta = FileMetaDataset()
    directory.file_meta.MediaStorageSOPClassUID = "1.2.840.10008.1.3.10"
    directory.file_meta.MediaStorageSOPInstanceUID = pydicom.uid.generate_uid()
    directory.file_meta.TransferSyntaxUID = pydicom.uid.ExplicitVRLittleEndian
    directory.FileSetID = "TEST"
    directory.save_as(folder / "DICOMDIR", enforce_file_format=True)
    vol = read_volume(folder)
    np.testing.assert_array_equal(vol.array, ct_crop)
    np.testing.assert_allclose(vol.origin, ORIGIN)


def test_dicom_named_fifo_or_folder_is_refused(tmp_path, ct_crop):
    files = write_series(tmp_path / "s", ct_crop)
    fifo = tmp_path / "slice.dcm"
    os.mkfifo(fifo)
    with raises(fifo, "not a regular file"):
        read_volume([*files, fifo])
    with raises(fifo, "not a regular file"):
        _dicom.read_dicom(fifo)
    with raises(tmp_path / "s", "not a regular file"):
        read_volume([tmp_path / "s"])


def test_path_too_long_is_named(tmp_path):
    long = tmp_path / ("x" * 5000 + ".dcm")
    with raises(long, "cannot read the file .*File name too long"):
        read_volume([long])
    with raises(long.with_suffix(".tif"), "cannot read the file .*File name too long"):
        _tiff.read_tiff(long.with_suffix(".tif"))


def test_dicom_file_without_series_uid_is_an_error(tmp_path, ct_crop):
    def drop_uid(k, ds):
        if k == 5:
            del ds.SeriesInstanceUID

    files = write_series(tmp_path / "s", ct_crop, edit=drop_uid)
    with raises(files[5], "has no SeriesInstanceUID"):
        read_volume(tmp_path / "s")


def test_dicom_slice_of_the_series_that_is_not_an_image(tmp_path, ct_crop):
    def drop_rows(k, ds):
        if k == 0:
            del ds.Rows

    write_series(tmp_path / "s", ct_crop, edit=drop_rows)
    with raises(tmp_path / "s", r"IM0000.dcm is not an image \(no Rows\)"):
        read_volume(tmp_path / "s")


def test_dicom_series_uid_swallowing_the_header_is_named(tmp_path, ct_crop):
    # A corrupt length makes SeriesInstanceUID swallow Rows and the rest: without the UID check
    # the slice would form a series of its own without image, and be left out silently.
    files = write_series(tmp_path / "s", ct_crop)
    raw = bytearray(files[0].read_bytes())
    length = raw.index(b"\x20\x00\x0e\x00UI") + 6
    raw[length:length + 2] = struct.pack("<H", 0x0800)
    files[0].write_bytes(bytes(raw))
    with raises(files[0], "SeriesInstanceUID .* is not a valid UID"):
        read_volume(tmp_path / "s")


def test_dicom_stray_series_names_its_file(tmp_path, ct_crop):
    def other_uid(k, ds):
        if k == 5:
            ds.SeriesInstanceUID = "1.2.3.4"

    write_series(tmp_path / "s", ct_crop, edit=other_uid)
    with raises(tmp_path / "s", r"holds 2 DICOM series.*1\.2\.3\.4: CT .*1 file\(s\): IM0005.dcm"):
        read_volume(tmp_path / "s")


# ---------------------------------------------------------------------------------------------
# DICOM: header values that would give silently wrong data


@pytest.mark.parametrize("keyword, value", [
    ("RescaleSlope", 0), ("RescaleSlope", float("nan")), ("RescaleSlope", float("inf")),
    ("RescaleSlope", ""), ("RescaleIntercept", float("nan")), ("RescaleIntercept", float("-inf")),
])
def test_dicom_bad_rescale_is_named(tmp_path, ct_crop, keyword, value):
    write_series(tmp_path / "s", ct_crop, edit=edit_slices({3}, **{keyword: value}))
    with raises(tmp_path / "s", f"IM0003.dcm has {keyword}"):
        read_volume(tmp_path / "s")


def test_dicom_rescale_in_some_slices_only(tmp_path, ct_crop):
    def drop_intercept(k, ds):
        if k == 0:
            del ds.RescaleIntercept

    write_series(tmp_path / "s", ct_crop, edit=drop_intercept)
    with raises(tmp_path / "s", "IM0000.dcm has no RescaleIntercept but IM0001.dcm has one"):
        read_volume(tmp_path / "s")


@pytest.mark.parametrize("orientation, match", [
    ([1, 0, 0, 0.5, 0.8660254, 0], r"right angles \(lengths \[1.0, 1.0\], cosine 0.5\)"),
    ([1, 0, 0, 1, 0, 0], "right angles"),
    ([2, 0, 0, 0, 2, 0], r"unit vectors.*lengths \[2.0, 2.0\]"),
    ([0, 0, 0, 0, 1, 0], "unit vectors"),
    ([1, 0, 0, 0, float("nan"), 0], "ImageOrientationPatient.*finite"),
    ([1, 0, 0, 0, 1], "ImageOrientationPatient.*6 finite"),
])
def test_dicom_orientation_must_be_orthonormal(tmp_path, ct_crop, orientation, match):
    write_series(tmp_path / "s", ct_crop,
                 edit=edit_slices(range(6), ImageOrientationPatient=orientation))
    with raises(tmp_path / "s", f"IM0000.dcm.*{match}"):
        read_volume(tmp_path / "s")


def test_dicom_orientation_rounded_in_the_file_is_normalised(tmp_path, ct_crop):
    # Decimal strings of limited precision: lengths 1 +- 1e-6 are accepted and normalised.
    rounded = [0.999999, 0.0, 0.0, 0.0, 1.000001, 0.0]
    write_series(tmp_path / "s", ct_crop,
                 edit=edit_slices(range(6), ImageOrientationPatient=rounded))
    vol = read_volume(tmp_path / "s")
    np.testing.assert_array_equal(vol.array, ct_crop)
    np.testing.assert_allclose(np.linalg.norm(vol.orientation, axis=0), 1.0, rtol=1e-12)
    np.testing.assert_allclose(vol.orientation, np.eye(3), atol=1e-12)


@pytest.mark.parametrize("keyword, value, match", [
    ("PixelSpacing", [0.75, 0.0], "PixelSpacing.*positive"),
    ("PixelSpacing", [-0.75, 0.5], "PixelSpacing.*positive"),
    ("PixelSpacing", [float("nan"), 0.5], "PixelSpacing.*2 finite"),
    ("PixelSpacing", [0.75], "PixelSpacing.*2 finite"),
    ("ImagePositionPatient", [0.0, float("inf"), 42.0], "ImagePositionPatient.*3 finite"),
    ("ImagePositionPatient", [0.0, 1.0], "ImagePositionPatient.*3 finite"),
])
def test_dicom_bad_geometry_values_are_named(tmp_path, ct_crop, keyword, value, match):
    write_series(tmp_path / "s", ct_crop, edit=edit_slices({5}, **{keyword: value}))
    with raises(tmp_path / "s", f"IM0005.dcm has {match}"):
        read_volume(tmp_path / "s")


def test_dicom_lone_slice_needs_a_positive_thickness(tmp_path, ct_crop):
    files = write_series(tmp_path / "s", ct_crop[:, :, :1],
                         edit=edit_slices({0}, SpacingBetweenSlices=0.0))
    with raises(files[0], "slice spacing of 0.0 mm"):
        read_volume(files[0])


@pytest.mark.parametrize("changes, match", [
    ({"BitsAllocated": 12}, "BitsAllocated 12 and BitsStored 16"),
    ({"NumberOfFrames": 2}, r"has NumberOfFrames 2; single-frame slices or an enhanced"),
    ({"NumberOfFrames": 0}, r"has NumberOfFrames 0; single-frame slices or an enhanced"),
    ({"PixelRepresentation": 0}, "mixes pixel formats"),
    ({"BitsStored": 12, "HighBit": 11}, "mixes pixel formats"),
])
def test_dicom_pixel_format_problems(tmp_path, ct_crop, changes, match):
    write_series(tmp_path / "s", ct_crop, edit=edit_slices({2}, **changes))
    with raises(tmp_path / "s", f"IM0002.dcm.*{match}|{match}.*IM0002.dcm"):
        read_volume(tmp_path / "s")


def test_dicom_bits_above_bits_stored_follow_the_standard(tmp_path, ct_crop):
    # PS3.5 8.1.1: the bits above HighBit are not part of the value; signed values are
    # sign-extended from HighBit. A HighBit that disagrees with BitsStored is a corrupt header.
    write_series(tmp_path / "s", ct_crop,
                 edit=edit_slices(range(6), BitsStored=8, HighBit=7))
    stored = (ct_crop.astype(np.int32) + 1024) & 0xFF
    expected = np.where(stored >= 0x80, stored - 0x100, stored) - 1024
    vol = read_volume(tmp_path / "s")
    np.testing.assert_array_equal(vol.array, expected)
    write_series(tmp_path / "t", ct_crop, edit=edit_slices(range(6), BitsStored=8))
    with raises(tmp_path / "t", "IM0000.dcm has HighBit 15 with BitsStored 8"):
        read_volume(tmp_path / "t")


def test_dicom_pixel_data_longer_than_the_header_says(tmp_path, ct_crop):
    def padded(k, ds):
        if k == 4:
            ds.PixelData += b"\0\0" * 16

    def longer(k, ds):
        if k == 4:
            ds.PixelData += b"\1\0" * 16

    write_series(tmp_path / "p", ct_crop, edit=padded)  # zero padding: read
    np.testing.assert_array_equal(read_volume(tmp_path / "p").array, ct_crop)
    files = write_series(tmp_path / "s", ct_crop, edit=longer)
    with raises(files[4], "need 768, and the 32 bytes after them are not zero padding"):
        read_volume(tmp_path / "s")


def test_dicom_codec_missing_is_a_clear_error(tmp_path, ct_crop):
    from pydicom.encaps import encapsulate

    def jpeg2000(k, ds):
        if k == 1:  # JPEG 2000 needs a decoder plug-in (pylibjpeg, GDCM): none is installed
            ds.file_meta.TransferSyntaxUID = "1.2.840.10008.1.2.4.90"
            ds.PixelData = encapsulate([b"\xff\x4f\xff\x51" + b"\0" * 60])

    files = write_series(tmp_path / "s", ct_crop, edit=jpeg2000)
    with raises(files[1], "cannot decode the pixel data") as info:
        read_volume(tmp_path / "s")
    assert info.value.__cause__ is not None


def test_dicom_third_party_error_is_chained(tmp_path, ct_crop):
    files = write_series(tmp_path / "s", ct_crop)
    raw = files[3].read_bytes()
    files[3].write_bytes(raw[:142])  # cut inside the file meta: a pydicom exception
    with raises(files[3], "not a readable DICOM file") as info:
        read_volume(tmp_path / "s")
    assert info.value.__cause__ is not None
    assert not isinstance(info.value.__cause__, VolumeEVMError)


# ---------------------------------------------------------------------------------------------
# DICOM: sizes checked before allocating


def test_dicom_rows_and_columns_beyond_the_file_are_refused(tmp_path, ct_crop):
    files = write_series(tmp_path / "s", ct_crop,
                         edit=edit_slices(range(6), Rows=65535, Columns=65535))
    with raises(files[0], r"65535x65535 pixels of 16 bits need, 8589672450, is more than the "
                          r"whole file holds"):
        read_volume(tmp_path / "s")


def test_dicom_series_beyond_the_memory_budget(tmp_path, ct_crop, monkeypatch):
    write_series(tmp_path / "s", ct_crop)
    monkeypatch.setenv("VOLUMEEVM_MEMORY_LIMIT", "8K")
    with raises(tmp_path / "s", r"reading 6 slices of 24x16 pixels needs about .* of memory but "
                                r"only 8.0 KiB is available; read fewer slices"):
        read_volume(tmp_path / "s")


def peak_against_estimate(monkeypatch, module, read):
    """(tracemalloc peak of ``read()``, the estimate the reader passed to ``check_memory``)."""
    estimates = []

    def record(needed, what, **kwargs):
        estimates.append(needed)
        return _memory.check_memory(needed, what, **kwargs)

    monkeypatch.setattr(module, "check_memory", record)
    tracemalloc.start()
    try:
        read()
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert len(estimates) == 1
    return peak, estimates[0]


def test_dicom_memory_estimate_bounds_the_peak(tmp_path, monkeypatch, data_dir):
    hu = np.load(data_dir / "ct_head_invesalius.npy")[:, :, 40:72]  # 256 x 256 x 32, 4 MiB
    write_series(tmp_path / "s", hu)
    peak, estimate = peak_against_estimate(monkeypatch, _dicom, lambda: read_volume(tmp_path / "s"))
    assert peak <= estimate <= 2 * peak, (peak, estimate)


# ---------------------------------------------------------------------------------------------
# TIFF


@pytest.mark.parametrize("kind", ["plain", "imagej", "ome"])
def test_tiff_reads_exactly(tmp_path, ct_crop, kind):
    vol = read_volume(write_tiff(tmp_path / "v.tif", ct_crop, kind))
    np.testing.assert_array_equal(vol.array, ct_crop)
    assert vol.spacing_known is (kind != "plain")


@pytest.mark.parametrize("old, new, match", [
    (b'SizeZ="6"', b'SizeZ="9"', "missing 3 frames"),
    (b'SizeZ="6"', b'SizeZ="3"', "expected 3 frames, got 6"),
    (b'SizeC="1"', b'SizeC="2"', "damaged or inconsistent"),
    (b'SizeT="1"', b'SizeT="2"', "damaged or inconsistent"),
    (b'SizeX="24"', b'SizeX="25"', "discontiguous storage"),
    (b'Type="int16"', b'Type="int32"', "Type='int32' but the pages hold int16"),
    (b'PhysicalSizeX="0.5"', b'PhysicalSizeX="0.0"', "PhysicalSizeX is '0.0'; it must be a"),
    (b'PhysicalSizeX="0.5"', b'PhysicalSizeX="nan"', "PhysicalSizeX is 'nan'"),
    (b'PhysicalSizeX="0.5"', b'PhysicalSizeX="abc"', "PhysicalSizeX is 'abc', not a number"),
    (b'PhysicalSizeX=', b'PhysicalSizeQ=', "attributes the OME schema does not define "
                                           "\\('PhysicalSizeQ'\\)"),
])
def test_tiff_ome_metadata_disagreeing_with_the_pages(tmp_path, ct_crop, old, new, match):
    path = write_tiff(tmp_path / "v.ome.tif", ct_crop, "ome")
    replace_text(path, old, new)
    with raises(path, match):
        read_volume(path)


def test_tiff_ome_name_without_ome_metadata(tmp_path, ct_crop):
    import tifffile

    path = write_tiff(tmp_path / "v.ome.tif", ct_crop, "ome")
    with tifffile.TiffFile(path) as tif:
        entry = tif.pages[0].tags["ImageDescription"].offset
    patch(path, entry, struct.pack("<H", 0xC10E))  # the tag's code: a private tag now
    with raises(path, "the name says OME-TIFF but the file holds no OME-XML"):
        read_volume(path)


@pytest.mark.parametrize("old, new, match", [
    (b"images=6", b"images=9", "images=9 but the file holds 6 slices"),
    (b"spacing=1.5", b"spacing=nan", "'spacing' is nan"),
    (b"spacing=1.5", b"spacing=0.0", "'spacing' is 0.0"),
    (b"spacing=1.5", b"spacing=-1.", "'spacing' is -1.0"),
    (b"unit=mm", b"unit=zz", "unknown length unit 'zz'"),
    (b"\nspacing=1.5", b"\x84spacing=1.5", "holds a non-ASCII or control character"),
])
def test_tiff_imagej_metadata_invalid(tmp_path, ct_crop, old, new, match):
    path = write_tiff(tmp_path / "v.tif", ct_crop, "imagej")
    replace_text(path, old, new)
    with raises(path, match):
        read_volume(path)


@pytest.mark.parametrize("rational", [(1, 0), (0, 1), (0, 0)])
def test_tiff_imagej_resolution_zero_is_an_error(tmp_path, ct_crop, rational):
    path = write_tiff(tmp_path / "v.tif", ct_crop, "imagej")
    patch(path, tag_value_offset(path, "XResolution"), struct.pack("<II", *rational))
    with raises(path, f"XResolution is {rational[0]}/{rational[1]} pixels per mm"):
        read_volume(path)


def test_tiff_plain_resolution_zero_leaves_spacing_unknown(tmp_path, ct_crop):
    # A plain TIFF's resolution is a print DPI the reader never uses: 1/0 changes nothing.
    path = write_tiff(tmp_path / "v.tif", ct_crop, "plain")
    patch(path, tag_value_offset(path, "XResolution"), struct.pack("<II", 1, 0))
    vol = read_volume(path)
    np.testing.assert_array_equal(vol.array, ct_crop)
    assert vol.spacing_known is False and vol.spacing == (1.0, 1.0, 1.0)


@pytest.mark.parametrize("kind", ["plain", "imagej", "ome"])
@pytest.mark.parametrize("tag, value, match", [
    ("ImageWidth", 0xFFFFFFF0, r"page 0 is \(16, 4294967280\) int16 uncompressed"),
    ("ImageLength", 0xFFFFFFF0, r"page 0 is \(4294967280, 24\) int16 uncompressed"),
    ("ImageLength", 12, r"page 0 is \(12, 24\) int16"),
    ("StripByteCounts", 100, "strips hold 100 bytes"),
    ("StripOffsets", 10**9, "lies beyond the end of the file"),
])
def test_tiff_sizes_that_do_not_fit_the_file(tmp_path, ct_crop, kind, tag, value, match):
    path = write_tiff(tmp_path / "v.tif", ct_crop, kind)
    patch(path, tag_value_offset(path, tag), struct.pack("<I", value))
    with raises(path, match):
        read_volume(path)


@pytest.mark.parametrize("kind", ["plain", "imagej", "ome"])
@pytest.mark.parametrize("page", [0, 5])
def test_tiff_strips_moved_onto_other_data_are_refused(tmp_path, ct_crop, kind, page):
    import tifffile

    path = write_tiff(tmp_path / "v.tif", ct_crop, kind)
    with tifffile.TiffFile(path) as tif:
        tif.pages.useframes = False
        offset = tif.pages[page].dataoffsets[0]
    step = 2 if page == 0 else -ct_crop.shape[0] * ct_crop.shape[1] * 2
    patch(path, tag_value_offset(path, "StripOffsets", page), struct.pack("<I", offset + step))
    with raises(path, "overlap in the file"):
        read_volume(path)


@pytest.mark.parametrize("kind", ["plain", "imagej", "ome"])
def test_tiff_broken_page_chain_is_not_a_shorter_stack(tmp_path, ct_crop, kind):
    import tifffile

    path = write_tiff(tmp_path / "v.tif", ct_crop, kind)
    with tifffile.TiffFile(path) as tif:
        last = tif.pages[5].offset
    path.write_bytes(path.read_bytes()[:last])  # the last page's directory is gone
    with raises(path, "damaged or inconsistent|beyond the end of the file"):
        read_volume(path)


def test_tiff_pages_of_another_size_are_refused(tmp_path, ct_crop):
    import tifffile

    path = tmp_path / "v.tif"
    with tifffile.TiffWriter(path) as tif:
        for k in range(4):
            tif.write(ct_crop[:, :, k].T, photometric="minisblack", metadata=None)
        tif.write(ct_crop[:, :8, 4].T.copy(), photometric="minisblack", metadata=None)
    with raises(path, r"page 4 differs from page 0 \(shape \(8, 24\)"):
        read_volume(path)


def test_tiff_missing_codec_is_a_clear_error(tmp_path, ct_crop):
    import tifffile

    path = tmp_path / "v.tif"
    tifffile.imwrite(path, ct_crop.T, photometric="minisblack", metadata=None,
                     compression="zlib")
    for page in range(6):  # declare a compression no decoder here knows
        patch(path, tag_value_offset(path, "Compression", page), struct.pack("<H", 65000))
    with raises(path, "not a readable TIFF file") as info:
        read_volume(path)
    assert info.value.__cause__ is not None


def test_tiff_fifo_is_refused(tmp_path):
    fifo = tmp_path / "stack.tif"
    os.mkfifo(fifo)
    with raises(fifo, "not a regular file"):
        read_volume(fifo)


def test_tiff_third_party_error_is_chained(tmp_path, ct_crop):
    path = write_tiff(tmp_path / "v.tif", ct_crop, "plain")
    path.write_bytes(path.read_bytes()[:100])
    with raises(path, "not a readable TIFF file") as info:
        read_volume(path)
    assert info.value.__cause__ is not None


def test_tiff_beyond_the_memory_budget(tmp_path, ct_crop, monkeypatch):
    path = write_tiff(tmp_path / "v.tif", ct_crop, "plain")
    monkeypatch.setenv("VOLUMEEVM_MEMORY_LIMIT", "4K")
    needed = _memory.format_bytes(2 * ct_crop.nbytes + 2 * 24 * 16 * 2)  # stack, copy, 2 pages
    with raises(path, f"reading a 24x16x6 int16 TIFF stack needs about {needed} of memory but "
                      f"only 4.0 KiB is available; crop the stack"):
        read_volume(path)


@pytest.mark.parametrize("kind", ["plain", "ome"])
def test_tiff_memory_estimate_bounds_the_peak(tmp_path, monkeypatch, data_dir, kind):
    hu = np.load(data_dir / "ct_head_invesalius.npy")[:, :, 40:72]  # 256 x 256 x 32, 4 MiB
    path = write_tiff(tmp_path / "v.tif", hu, kind)
    peak, estimate = peak_against_estimate(monkeypatch, _tiff, lambda: read_volume(path))
    assert peak <= estimate <= 2 * peak, (peak, estimate)
