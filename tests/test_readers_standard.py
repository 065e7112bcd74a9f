"""Readers against the files scanners and tools write: NRRD kinds, units and Teem/Fiji headers,
DICOM as the standard says (unused bits, padding, one file opening its own series), data units
and the ``units=`` override of ``read_volume``."""

import re
import warnings
from pathlib import Path

import numpy as np
import pytest

from reader_files import assert_same_as_nibabel, write_nrrd
from volumeevm_addon import VolumeEVMError
from volumeevm_addon.readers import read_volume


def raises(path, match):
    """``pytest.raises(VolumeEVMError, match=...)`` that also checks the message names ``path``."""
    return pytest.raises(VolumeEVMError, match=f"(?s)^{re.escape(str(path))}.*{match}")


@pytest.fixture(scope="module")
def ct_crop(data_dir):
    """A non-cubic crop (20 x 16 x 6) of the real CT head in HU, int16."""
    array = np.load(data_dir / "ct_head_invesalius.npy")
    return np.ascontiguousarray(array[110:130, 60:76, 50:56])


def nrrd_file(path, header, array):
    """A NRRD file with the header lines given as text and ``array`` (``[x, y, z]``) raw."""
    path.write_bytes(("NRRD0004\n" + header + "\n\n").encode() + array.T.tobytes())
    return path


# ---------------------------------------------------------------------------------------------
# NRRD


@pytest.mark.parametrize("kinds, sizes", [
    ("RGB-color domain domain", (3, 3, 5)),  # a 3x5 colour image, colour first
    ("RGB-color space space", (3, 4, 2)),
    ("domain domain RGBA-color", (4, 3, 4)),
    ("vector domain domain", (3, 4, 2)),
    ("domain domain time", (3, 4, 2)),
    ("complex domain domain", (2, 4, 2)),
    ("list domain domain", (2, 4, 2)),
])
def test_nrrd_non_spatial_axis_is_refused(tmp_path, kinds, sizes):
    array = np.arange(np.prod(sizes), dtype=np.uint8).reshape(sizes)
    path = tmp_path / "colour.nrrd"
    write_nrrd(path, array, {"kinds": kinds.split(), "encoding": "raw"})
    odd = next(k for k in kinds.split() if k not in ("domain", "space"))
    with raises(path, f"is of kind '{odd}'.*not a spatial axis"):
        read_volume(path)


def test_nrrd_spatial_kinds_read(tmp_path, ct_crop):
    path = tmp_path / "ct.nrrd"
    write_nrrd(path, ct_crop, {"kinds": ["domain", "space", "domain"], "encoding": "raw"})
    np.testing.assert_array_equal(read_volume(path).array, ct_crop)


def test_nrrd_colour_4d_is_refused_for_its_colour(tmp_path):
    path = nrrd_file(tmp_path / "rgb.nrrd", "type: uchar\ndimension: 4\nsizes: 3 2 2 2\n"
                     "kinds: RGB-color domain domain domain\nencoding: raw",
                     np.zeros((3, 2, 2, 2), np.uint8))
    with raises(path, "axis 0 of the NRRD data is of kind 'RGB-color'"):
        read_volume(path)


def test_nrrd_kinds_count_must_match(tmp_path, ct_crop):
    path = nrrd_file(tmp_path / "a.nrrd", "type: short\ndimension: 3\nsizes: 20 16 6\n"
                     "endian: little\nkinds: domain domain\nencoding: raw", ct_crop)
    with raises(path, "'kinds' gives 2 kinds for 3 axes"):
        read_volume(path)


@pytest.mark.parametrize("unit, mm", [("microns", 1e-3), ("micron", 1e-3), ("um", 1e-3),
                                      ("\u00b5m", 1e-3), ("nm", 1e-6), ("m", 1e3),
                                      ("mm", 1.0)])
def test_nrrd_fiji_space_units(tmp_path, data_dir, unit, mm):
    """Fiji's Nrrd_Writer: quoted ``space units`` in its own spelling ("microns")."""
    array = np.load(data_dir / "micro_nuclei3d_stardist.npy")
    path = tmp_path / "fiji.nrrd"
    header = ("# Created by Nrrd_Writer\ntype: uint16\nencoding: raw\nendian: little\n"
              "dimension: 3\nsizes: 57 61 31\nspace dimension: 3\n"
              "space directions: (0.25,0,0) (0,0.25,0) (0,0,1.5)\n"
              f'space units: "{unit}" "{unit}" "{unit}"\nspace origin: (2,4,6)')
    path.write_bytes(("NRRD0004\n" + header + "\n\n").encode("utf-8") + array.T.tobytes())
    if not unit.isascii():  # a NRRD header is ASCII (Teem refuses anything else)
        with raises(path, "not ASCII"):
            read_volume(path)
        return
    vol = read_volume(path)
    np.testing.assert_array_equal(vol.array, array)
    np.testing.assert_allclose(vol.spacing, np.array([0.25, 0.25, 1.5]) * mm, rtol=1e-12)
    np.testing.assert_allclose(vol.origin, np.array([2, 4, 6]) * mm, rtol=1e-12)
    assert vol.spacing_known


@pytest.mark.parametrize("units", ['"pixel" "pixel" "pixel"', '"furlong" "mm" "mm"'])
def test_nrrd_pixel_units_mean_unknown_spacing(tmp_path, ct_crop, units):
    """Fiji writes "pixel" for an uncalibrated image: spacing unknown, not an error; a unit
    that is neither a length nor "pixel" is still refused."""
    path = nrrd_file(tmp_path / "fiji.nrrd", "type: int16\nencoding: raw\nendian: little\n"
                     "dimension: 3\nsizes: 20 16 6\nspace dimension: 3\n"
                     f"space directions: (1,0,0) (0,1,0) (0,0,1)\nspace units: {units}", ct_crop)
    if "furlong" in units:
        with raises(path, "unknown length unit 'furlong' in 'space units'"):
            read_volume(path)
        return
    vol = read_volume(path)
    np.testing.assert_array_equal(vol.array, ct_crop)
    assert vol.spacing_known is False and vol.spacing == (1.0, 1.0, 1.0)


def test_nrrd_teem_spacings_with_axis_units(tmp_path, ct_crop):
    """Teem's header for a file without a space: ``spacings``, per-axis ``units``, old names."""
    path = nrrd_file(tmp_path / "teem.nrrd", "content: crop\ntype: short\ndimension: 3\n"
                     "sizes: 20 16 6\nspacings: 0.5 0.25 2\naxismins: 0 0 0\n"
                     "centers: cell cell cell\nunits: \"um\" \"um\" \"um\"\n"
                     "endian: little\nencoding: raw", ct_crop)
    vol = read_volume(path)
    np.testing.assert_array_equal(vol.array, ct_crop)
    np.testing.assert_allclose(vol.spacing, (5e-4, 2.5e-4, 2e-3), rtol=1e-12)
    assert vol.spacing_known and np.array_equal(vol.orientation, np.eye(3))


def test_nhdr_bad_byte_skip_names_the_header(tmp_path, ct_crop):
    data = tmp_path / "ct.raw"
    data.write_bytes(ct_crop.T.tobytes())
    header = tmp_path / "ct.nhdr"
    header.write_text("NRRD0004\ntype: short\ndimension: 3\nsizes: 20 16 6\nendian: little\n"
                      "encoding: raw\nbyte skip: 100\ndata file: ct.raw\n")
    with raises(header, rf": data file {re.escape(str(data))}: corrupt NRRD file \(the data "
                        r"holds 3740 bytes"):
        read_volume(header)
    header.write_text(header.read_text().replace("byte skip: 100", "byte skip: -7"))
    with raises(header, r"data file .*byte skip -7"):
        read_volume(header)
    header.write_text(header.read_text().replace("byte skip: -7", "byte skip: 0"))
    np.testing.assert_array_equal(read_volume(header).array, ct_crop)


@pytest.mark.parametrize("written, units", [("HU", "HU"), ("Hounsfield units", "HU"),
                                            ('"mg/cc"', "mg/cc")])
def test_nrrd_sample_units(tmp_path, ct_crop, written, units):
    path = nrrd_file(tmp_path / "a.nrrd", "type: short\ndimension: 3\nsizes: 20 16 6\n"
                     f"endian: little\nencoding: raw\nsample units: {written}", ct_crop)
    assert read_volume(path).units == units


def test_slicer_ct_states_no_data_units(data_dir):
    """Slicer's CT NRRD has no field for its HU: the reader reports none, the user sets it."""
    import nrrd

    path = data_dir / "slicer" / "CTChest4.nrrd"
    header = nrrd.read_header(str(path))
    assert "sample units" not in header and not any("unit" in key for key in header)
    vol = read_volume(path)
    assert vol.units == ""
    assert read_volume(path, units="HU").units == "HU"


# ---------------------------------------------------------------------------------------------
# units= of read_volume


def test_units_override_every_format(tmp_path, ct_crop):
    import nibabel as nib

    nifti = tmp_path / "ct.nii"
    nib.save(nib.Nifti1Image(ct_crop, np.eye(4)), nifti)
    stated = nrrd_file(tmp_path / "stated.nrrd", "type: short\ndimension: 3\nsizes: 20 16 6\n"
                       "endian: little\nencoding: raw\nsample units: mg/cc", ct_crop)
    for path in (nifti, stated):
        plain = read_volume(path)
        vol = read_volume(path, units="HU")
        assert vol.units == "HU" and plain.units in ("", "mg/cc")
        np.testing.assert_array_equal(vol.array, plain.array)
        assert (vol.spacing, vol.origin, vol.source) == (plain.spacing, plain.origin,
                                                         plain.source)
    assert read_volume(nifti).units == ""  # NIfTI has no field for the data's units
    assert read_volume(stated, units=" a.u. ").units == "a.u."


@pytest.mark.parametrize("units", [1, b"HU", ["HU"]])
def test_units_must_be_a_str(tmp_path, ct_crop, units):
    path = nrrd_file(tmp_path / "a.nrrd", "type: short\ndimension: 3\nsizes: 20 16 6\n"
                     "endian: little\nencoding: raw", ct_crop)
    with pytest.raises(VolumeEVMError, match=r"^units: .* is a (int|bytes|list); the data's"):
        read_volume(path, units=units)


# ---------------------------------------------------------------------------------------------
# DICOM


def write_mr_series(folder, stored, edit=None):
    """``stored`` (``(X, Y, Z)`` uint16 words, as they are in the file) as an MR series cloned
    from pydicom's real ``MR_small.dcm``, 2 mm apart along z; ``edit(k, ds)`` may change a
    slice. Returns the files in slice order."""
    import copy

    import pydicom
    from pydicom.data import get_testdata_file
    from pydicom.uid import generate_uid

    folder.mkdir(exist_ok=True)
    template = pydicom.dcmread(get_testdata_file("MR_small.dcm"))
    del template.DataSetTrailingPadding  # so that the pixel data ends the file
    uid = generate_uid()
    files = []
    for k in range(stored.shape[2]):
        ds = copy.deepcopy(template)
        ds.SeriesInstanceUID, ds.SOPInstanceUID = uid, generate_uid()
        ds.file_meta.MediaStorageSOPInstanceUID = ds.SOPInstanceUID
        ds.Rows, ds.Columns = stored.shape[1], stored.shape[0]
        ds.ImagePositionPatient = [-83.9063, -91.2, 6.6406 + 2.0 * k]
        ds.PixelData = np.ascontiguousarray(stored[:, :, k].T, dtype="<u2").tobytes()
        if edit is not None:
            edit(k, ds)
        files.append(folder / f"MR{k:03d}.dcm")
        ds.save_as(files[-1], enforce_file_format=True)
    return files


def bits(stored_bits, signed):
    def edit(k, ds):
        ds.BitsStored, ds.HighBit, ds.PixelRepresentation = stored_bits, stored_bits - 1, signed
    return edit


@pytest.mark.parametrize("signed", [0, 1])
def test_dicom_unused_high_bits_masked_or_sign_extended(tmp_path, signed):
    """dcm2niix's QA pattern: 0x0F0F words with BitsStored 12, in both signednesses."""
    rng = np.random.default_rng(20)
    words = rng.integers(0, 0x1000, (16, 12, 5)).astype(np.uint16)
    words[3, 4, :] = 0x0F0F
    words[5, 6, 2] = 0xFFFF  # Siemens XA: a few pixels with every unused bit set
    words[7, 1, 0] = 0xF800
    files = write_mr_series(tmp_path / "s", words, edit=bits(12, signed))
    value = words.astype(np.int32) & 0x0FFF  # PS3.5 8.1.1: bits above HighBit are not the value
    if signed:
        value = np.where(value & 0x800, value - 0x1000, value)
    vol = read_volume(files[2])
    assert vol.array.dtype == (np.int16 if signed else np.uint16)
    np.testing.assert_array_equal(vol.array, value)
    assert vol.array[3, 4, 0] == (-241 if signed else 0x0F0F)
    assert vol.array[5, 6, 2] == (-1 if signed else 0x0FFF)
    assert vol.units == ""  # MR values have no unit


def test_dicom_pydicom_padded_file_reads(tmp_path):
    import pydicom
    from pydicom.data import get_testdata_file

    path = tmp_path / "padded.dcm"
    path.write_bytes(Path(get_testdata_file("MR_small_padded.dcm")).read_bytes())
    padded = read_volume(path)
    reference = pydicom.dcmread(get_testdata_file("MR_small.dcm")).pixel_array
    np.testing.assert_array_equal(padded.array[:, :, 0], reference.T)


def foreign_files(folder):
    """Files of other projects' test folders that block a folder scan: a big-endian file
    without preamble (pydicom), one without SeriesInstanceUID, text named .dcm."""
    import shutil

    import pydicom
    from pydicom.data import get_testdata_file

    shutil.copy(get_testdata_file("ExplVR_BigEndNoMeta.dcm"), folder / "bigend.dcm")
    ds = pydicom.dcmread(get_testdata_file("CT_small.dcm"))
    del ds.SeriesInstanceUID
    ds.save_as(folder / "noseries.dcm")
    (folder / "notes.dcm").write_text("not DICOM\n")
    return ["bigend.dcm", "noseries.dcm", "notes.dcm"]


def test_dicom_one_file_opens_its_series_past_foreign_files(tmp_path):
    words = np.random.default_rng(1).integers(0, 4000, (16, 12, 5)).astype(np.uint16)
    files = write_mr_series(tmp_path / "s", words)
    other = write_mr_series(tmp_path / "t", words[:, :, :2])
    for path in other:  # another series in the same folder: ignored
        path.rename(tmp_path / "s" / f"other_{path.name}")
    bigend, *skipped = foreign_files(tmp_path / "s")
    with pytest.raises(VolumeEVMError, match="bigend.dcm: not a readable DICOM file"):
        read_volume(tmp_path / "s")  # a folder: every DICOM file must read
    # The big-endian file's series UID (read alone) is another series': it is not read further.
    with pytest.warns(UserWarning, match="2 other file.*skipped") as record:
        vol = read_volume(files[3])
    message = str(record[0].message)
    assert message.startswith(str(files[3])) and all(name in message for name in skipped)
    assert bigend not in message
    np.testing.assert_array_equal(vol.array, words.astype(np.int16))
    np.testing.assert_allclose(vol.origin, (-83.9063, -91.2, 6.6406))
    np.testing.assert_allclose(vol.spacing, (0.3125, 0.3125, 2.0))


def test_dicom_one_file_broken_slice_of_its_series_is_an_error(tmp_path):
    import pydicom

    words = np.random.default_rng(2).integers(0, 4000, (16, 12, 5)).astype(np.uint16)
    files = write_mr_series(tmp_path / "s", words)
    foreign_files(tmp_path / "s")
    raw = files[4].read_bytes()
    files[4].write_bytes(raw[:-100])  # the header keeps its series UID
    with pytest.warns(UserWarning), raises(files[4], "cannot decode the pixel data"):
        read_volume(files[0])
    ds = pydicom.dcmread(files[4])  # the slice as an old file without preamble: unreadable
    ds.preamble, ds.file_meta = None, pydicom.dataset.FileMetaDataset()
    pydicom.dcmwrite(files[4], ds, enforce_file_format=False, implicit_vr=False,
                     little_endian=True)
    assert files[4].read_bytes()[128:132] != b"DICM"
    with raises(files[4], "not a readable DICOM file"):  # before the warning
        read_volume(files[0])
    # Cut before its series UID, a slice cannot be placed: pydicom reads the rest silently, so
    # it is skipped, and the warning is all that shows it (here the last slice: 4 are left).
    files[4].write_bytes(raw[:600])
    with pytest.warns(UserWarning, match="MR004.dcm \\(this DICOM file has no SeriesInstance"):
        assert read_volume(files[0]).array.shape == (16, 12, 4)
    files[4].unlink()
    files[2].unlink()  # a missing slice in the middle: found from the positions
    with pytest.warns(UserWarning), raises(files[0], "not evenly spaced"):
        read_volume(files[0])


def test_dicom_chosen_file_without_series_reads_alone(tmp_path):
    import pydicom
    from pydicom.data import get_testdata_file

    names = foreign_files(tmp_path)
    vol = read_volume(tmp_path / names[1])
    reference = pydicom.dcmread(get_testdata_file("CT_small.dcm"))
    expected = reference.pixel_array.T.astype(np.int32) * int(reference.RescaleSlope) + int(
        reference.RescaleIntercept)
    np.testing.assert_array_equal(vol.array[:, :, 0], expected)
    assert vol.units == "HU"


@pytest.mark.parametrize("modality, rescale, rescale_type, units", [
    ("CT", True, None, "HU"), ("CT", True, "HU", "HU"), ("CT", True, "US", "HU"),
    ("CT", False, None, ""), ("PT", True, "BQML", "BQML"), ("MR", False, None, ""),
    ("OT", True, "OD", "OD"),
])
def test_dicom_data_units(tmp_path, modality, rescale, rescale_type, units):
    words = np.full((4, 4, 2), 100, np.uint16)

    def edit(k, ds):
        ds.Modality = modality
        if rescale:
            ds.RescaleSlope, ds.RescaleIntercept = 1, -1024
        if rescale_type is not None:
            ds.RescaleType = rescale_type

    files = write_mr_series(tmp_path / "s", words, edit=edit)
    vol = read_volume(files[0])
    assert vol.units == units
    assert read_volume(files[0], units="mm/s").units == "mm/s"
    np.testing.assert_array_equal(vol.array, 100 - 1024 if rescale else 100)


# ---------------------------------------------------------------------------------------------
# DICOM: enhanced multi-frame and Siemens mosaic, against nibabel's DICOM wrappers


def nicom_file(tmp_path, name, pixels=None):
    """A real scanner file of nibabel's ``nicom/tests/data`` (shipped gzipped), unzipped into
    ``tmp_path``; ``pixels(ds)`` may give new pixel words (the shipped files' are all zero)."""
    import gzip

    import nibabel
    import pydicom

    source = Path(nibabel.__file__).parent / "nicom" / "tests" / "data" / f"{name}.dcm.gz"
    path = tmp_path / f"{name}.dcm"
    path.write_bytes(gzip.decompress(source.read_bytes()))
    if pixels is not None:
        ds = pydicom.dcmread(path)
        ds.PixelData = pixels(ds).astype("<u2").tobytes()
        ds.save_as(path)
    return path


def test_dicom_enhanced_multiframe_philips(tmp_path):
    """A Philips enhanced MR export: 176 frames in one file, each placed by its own
    PlanePositionSequence; the per-frame rescale (2.1079...) applied."""
    frames = np.random.default_rng(4).integers(0, 4096, (176, 256, 256), dtype=np.uint16)
    path = nicom_file(tmp_path, "philips_mprage", lambda ds: frames)
    vol = read_volume(path)
    assert vol.array.shape == (256, 256, 176) and vol.array.dtype == np.float32
    slope = np.float32(2.10793650793650)  # frames 1 to 176 lie along the stacking direction
    np.testing.assert_array_equal(vol.array, frames.T.astype(np.float32) * slope)
    np.testing.assert_allclose(vol.spacing, (1, 1, 1), rtol=1e-5)
    np.testing.assert_allclose(vol.origin, (92.7090416119899, -125.12766968458,
                                            136.495256863534))  # frame 1's position
    data = assert_same_as_nibabel(vol, path, scale=2.10793650793650)
    assert np.ptp(data) > 4000


def test_dicom_enhanced_multiframe_refusals(tmp_path):
    import pydicom

    path = nicom_file(tmp_path, "philips_mprage")
    ds = pydicom.dcmread(path)  # its first 8 frames, for speed
    ds.NumberOfFrames = 8
    ds.PixelData = ds.PixelData[:8 * 256 * 256 * 2]
    ds.PerFrameFunctionalGroupsSequence = ds.PerFrameFunctionalGroupsSequence[:8]
    ds.save_as(path)
    assert read_volume(path).array.shape == (256, 256, 8)
    ds.PerFrameFunctionalGroupsSequence = ds.PerFrameFunctionalGroupsSequence[:7]
    ds.save_as(path)
    with raises(path, "NumberOfFrames 8 but 7 per-frame functional groups"):
        read_volume(path)
    ds = pydicom.dcmread(path)
    ds.PerFrameFunctionalGroupsSequence.append(ds.PerFrameFunctionalGroupsSequence[6])
    position = ds.PerFrameFunctionalGroupsSequence[1].PlanePositionSequence[0]
    position.ImagePositionPatient = ds.PerFrameFunctionalGroupsSequence[0].PlanePositionSequence[
        0].ImagePositionPatient  # two frames at one place: a second echo or time point
    ds.save_as(path)
    with raises(path, "share one position.*frame 1 and .*frame 2"):
        read_volume(path)
    ds.NumberOfFrames = 2
    del ds.PerFrameFunctionalGroupsSequence  # a multi-frame image without its frames' places
    ds.PixelData = ds.PixelData[:2 * 256 * 256 * 2]
    ds.save_as(path)
    with raises(path, "NumberOfFrames 2; single-frame slices or an enhanced multi-frame"):
        read_volume(path)


def mosaic_words(ds):
    """A volume of 48 slices of 128 x 128 with distinct values, tiled 7 x 7 as Siemens does."""
    words = np.zeros((ds.Rows, ds.Columns), np.uint16)
    values = np.arange(128 * 128 * 48).reshape(48, 128, 128) % 4093 + 1
    for k in range(48):
        r, c = divmod(k, 7)
        words[r * 128:(r + 1) * 128, c * 128:(c + 1) * 128] = values[k]
    return words


def test_dicom_siemens_mosaic(tmp_path):
    """A Siemens DWI mosaic: 48 slices tiled in one 896 x 896 image, the count and the normal's
    sign in the CSA header; one file of the series is one volume."""
    path = nicom_file(tmp_path, "siemens_dwi_1000", mosaic_words)
    nicom_file(tmp_path, "siemens_dwi_0", mosaic_words)  # same series, same place: b=0
    vol = read_volume(path)
    assert vol.array.shape == (128, 128, 48) and vol.array.dtype == np.uint16
    expected = np.arange(128 * 128 * 48).reshape(48, 128, 128) % 4093 + 1
    np.testing.assert_array_equal(vol.array, expected.transpose(2, 1, 0))
    np.testing.assert_allclose(vol.spacing, (1.796875, 1.796875, 3.0), rtol=1e-5)
    assert_same_as_nibabel(vol, path)
    with raises(tmp_path, "share one position"):
        read_volume(tmp_path)  # the folder: two volumes at one place


def test_dicom_mosaic_without_csa_header(tmp_path):
    import pydicom

    path = nicom_file(tmp_path, "siemens_dwi_0")
    ds = pydicom.dcmread(path)
    del ds[0x0029, 0x1010]
    ds.save_as(path)
    with raises(path, "is a mosaic .*without the Siemens CSA image header"):
        read_volume(path)


@pytest.mark.parametrize("count", [0, 26, 90, 4097, 896 * 896])
def test_dicom_mosaic_slice_count_must_fit(tmp_path, count):
    """A CSA slice count the mosaic cannot hold in a square grid (or absurdly many) is refused."""
    import pydicom

    with warnings.catch_warnings():  # nibabel: "The DICOM readers are highly experimental"
        warnings.simplefilter("ignore")
        from nibabel.nicom import csareader

    path = nicom_file(tmp_path, "siemens_dwi_0")
    ds = pydicom.dcmread(path)
    raw = ds[0x0029, 0x1010].value
    csa = csareader.read(raw)
    assert csareader.get_n_mosaic(csa) == 48
    # The count is text in its CSA item, "48" padded with spaces: rewrite it at that length.
    old = b"48      "
    start = raw.index(old, raw.index(b"NumberOfImagesInMosaic"))
    new = f"{count:<8}".encode()
    ds[0x0029, 0x1010].value = raw[:start] + new + raw[start + len(old):]
    assert csareader.get_n_mosaic(csareader.read(ds[0x0029, 0x1010].value)) == count
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        ds.save_as(path)
    with raises(path, f"cannot hold {count} slices in a square grid"):
        read_volume(path)
