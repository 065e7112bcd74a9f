"""Readers against the files scanners and tools write: NRRD kinds, units and Teem/Fiji headers,
DICOM as the standard says (unused bits, padding, one file opening its own series), data units
and the ``units=`` override of ``read_volume``."""

import re

import numpy as np
import pytest

from volumeevm_addon import VolumeEVMError
from volumeevm_addon.readers import read_volume
from reader_files import write_nrrd


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


def test_nrrd_fiji_uncalibrated_pixel_units(tmp_path, ct_crop):
    """Fiji writes "pixel" for an uncalibrated image: spacing unknown, not an error."""
    path = nrrd_file(tmp_path / "fiji.nrrd", "type: int16\nencoding: raw\nendian: little\n"
                     "dimension: 3\nsizes: 20 16 6\nspace dimension: 3\n"
                     "space directions: (1,0,0) (0,1,0) (0,0,1)\n"
                     'space units: "pixel" "pixel" "pixel"', ct_crop)
    vol = read_volume(path)
    np.testing.assert_array_equal(vol.array, ct_crop)
    assert vol.spacing_known is False and vol.spacing == (1.0, 1.0, 1.0)


def test_nrrd_unknown_unit_is_still_refused(tmp_path, ct_crop):
    path = nrrd_file(tmp_path / "a.nrrd", "type: int16\nencoding: raw\nendian: little\n"
                     "dimension: 3\nsizes: 20 16 6\nspace dimension: 3\n"
                     "space directions: (1,0,0) (0,1,0) (0,0,1)\n"
                     'space units: "furlong" "mm" "mm"', ct_crop)
    with raises(path, "unknown length unit 'furlong' in 'space units'"):
        read_volume(path)


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
    with raises(header, rf"\(data file {re.escape(str(data))}\): corrupt NRRD file \(the data "
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
