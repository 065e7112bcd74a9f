"""Tests for ``volumeevm_addon.readers``: real volumes written with each format's reference
library, read back, compared exactly; every bad-input path raises ``VolumeEVMError`` naming the
file and the problem."""

import copy
import errno
import gzip
import json
import os
import re
import shutil
import subprocess
import sys
import tokenize
from pathlib import Path

import numpy as np
import pytest

from reader_files import REPO, patch_nifti, write_den, write_nrrd
from skips import skip_unless_ci
from volumeevm_addon import VolumeEVMError
from volumeevm_addon.readers import SUPPORTED_EXTENSIONS, read_volume

pytestmark = pytest.mark.filterwarnings("error")


# ---------------------------------------------------------------------------------------------
# helpers


def load(data_dir, name):
    """A real volume ``[x, y, z]`` and its JSON metadata from the shared data folder."""
    meta = json.loads((data_dir / f"{name}.json").read_text())
    return np.load(data_dir / f"{name}.npy"), meta


@pytest.fixture(scope="module")
def ct_crop(data_dir):
    """A non-cubic crop (64 x 48 x 12) of the real CT head in HU, int16: skull and air."""
    array = np.load(data_dir / "ct_head_invesalius.npy")
    return np.ascontiguousarray(array[96:160, 40:88, 50:62])


def assert_volume(vol, array, *, spacing, origin, orientation, units, spacing_known, source):
    """Exact array (values and dtype) and geometry of a read volume."""
    assert vol.array.dtype == array.dtype
    np.testing.assert_array_equal(vol.array, array)
    assert vol.array.flags.c_contiguous
    assert vol.array.dtype.isnative
    np.testing.assert_allclose(vol.spacing, spacing, rtol=1e-6)
    np.testing.assert_allclose(vol.origin, origin, rtol=1e-6, atol=1e-9)
    np.testing.assert_allclose(vol.orientation, orientation, atol=1e-6)
    assert vol.units == units
    assert vol.spacing_known is spacing_known
    assert vol.source == str(source)


def raises(path, match):
    """``pytest.raises(VolumeEVMError, match=...)`` that also checks the message names ``path``."""
    return pytest.raises(VolumeEVMError, match=f"(?s)^{re.escape(str(path))}.*{match}")



# ---------------------------------------------------------------------------------------------
# dispatch


def test_supported_extensions_dispatch_case_insensitively(tmp_path, ct_crop):
    assert SUPPORTED_EXTENSIONS == (
        ".npy", ".raw", ".bin", ".nrrd", ".nhdr", ".nii", ".nii.gz", ".dcm", ".tif", ".tiff",
        ".den",
    )
    path = tmp_path / "HEAD.NPY"
    with path.open("wb") as f:  # np.save would append ".npy" to this name
        np.save(f, ct_crop)
    np.testing.assert_array_equal(read_volume(path).array, ct_crop)


def test_missing_file(tmp_path):
    path = tmp_path / "nothing.nrrd"
    with raises(path, "no such file or folder"):
        read_volume(path)


def test_unsupported_extension(tmp_path):
    path = tmp_path / "volume.mha"
    path.write_bytes(b"ObjectType = Image\n")
    with raises(path, r"unsupported file type; supported are \.npy, .*\.den"):
        read_volume(path)


def test_unknown_option_is_a_type_error(tmp_path, ct_crop):
    path = tmp_path / "v.npy"
    np.save(path, ct_crop)
    with pytest.raises(TypeError, match="shape"):
        read_volume(path, shape=(1, 2, 3))


def test_import_needs_numpy_only():
    code = (
        "import sys; import volumeevm_addon.readers; "
        "print([m for m in ('pydicom', 'nibabel', 'nrrd', 'tifffile') if m in sys.modules])"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, check=True
    )
    assert out.stdout.strip() == "[]"


@pytest.mark.parametrize(
    ("module", "pip_name", "name"),
    [("pydicom", "pydicom", "a.dcm"), ("nibabel", "nibabel", "a.nii"),
     ("nrrd", "pynrrd", "a.nrrd"), ("tifffile", "tifffile", "a.tif")],
)
def test_missing_library_names_the_package(tmp_path, monkeypatch, module, pip_name, name):
    path = tmp_path / name
    path.write_bytes(b"\0" * 16)
    monkeypatch.setitem(sys.modules, module, None)  # makes `import module` raise ImportError
    with raises(path, f"needs the Python package '{pip_name}'"):
        read_volume(path)


# ---------------------------------------------------------------------------------------------
# common checks (exercised through .npy, the format with no decoding of its own)


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_non_finite_densities(tmp_path, bad):
    array = np.zeros((4, 5, 6), np.float32)
    array[1, 2, 3] = bad
    path = tmp_path / "v.npy"
    np.save(path, array)
    with raises(path, r"1 densities are NaN or Inf \(first at voxel \(1, 2, 3\)"):
        read_volume(path)


@pytest.mark.parametrize("shape", [(5, 6), (2, 3, 4, 5)])
def test_wrong_number_of_dimensions(tmp_path, shape):
    path = tmp_path / "v.npy"
    np.save(path, np.zeros(shape, np.uint8))
    with raises(path, f"has {len(shape)} dimension"):
        read_volume(path)


def test_empty_volume(tmp_path):
    path = tmp_path / "v.npy"
    np.save(path, np.zeros((4, 0, 3), np.uint8))
    with raises(path, "empty"):
        read_volume(path)


@pytest.mark.parametrize("dtype", [np.complex64, np.bool_, "U3"])
def test_unsupported_dtype(tmp_path, dtype):
    path = tmp_path / "v.npy"
    np.save(path, np.zeros((2, 3, 4), dtype))
    with raises(path, "unsupported data type"):
        read_volume(path)


def test_float_volume_keeps_float32(tmp_path, data_dir):
    array, meta = load(data_dir, "ct_skull_cgal")
    path = tmp_path / "ct_skull_cgal.npy"
    shutil.copy(data_dir / "ct_skull_cgal.npy", path)
    shutil.copy(data_dir / "ct_skull_cgal.json", tmp_path)
    vol = read_volume(path)
    assert_volume(vol, array, spacing=meta["spacing_mm"], origin=(0, 0, 0), orientation=np.eye(3),
                  units="", spacing_known=True, source=path)


# ---------------------------------------------------------------------------------------------
# .npy


def test_npy_real_ct_with_sidecar(data_dir):
    array, meta = load(data_dir, "ct_head_invesalius")
    path = data_dir / "ct_head_invesalius.npy"
    vol = read_volume(path)
    assert_volume(vol, array, spacing=meta["spacing_mm"], origin=(0, 0, 0), orientation=np.eye(3),
                  units="HU", spacing_known=True, source=path)


def test_npy_sidecar_with_unknown_spacing(data_dir):
    array, _ = load(data_dir, "micro_nuclei3d_stardist")
    path = data_dir / "micro_nuclei3d_stardist.npy"
    vol = read_volume(str(path))
    assert_volume(vol, array, spacing=(1, 1, 1), origin=(0, 0, 0), orientation=np.eye(3),
                  units="", spacing_known=False, source=path)


def test_npy_fortran_order_without_sidecar(tmp_path, ct_crop):
    path = tmp_path / "crop.npy"
    np.save(path, np.asfortranarray(ct_crop))
    vol = read_volume(path)
    assert_volume(vol, ct_crop, spacing=(1, 1, 1), origin=(0, 0, 0), orientation=np.eye(3),
                  units="", spacing_known=False, source=path)


def test_npy_refuses_pickled_objects(tmp_path):
    path = tmp_path / "v.npy"
    np.save(path, np.empty((2, 2, 2), dtype=object), allow_pickle=True)
    with raises(path, r"not a readable \.npy array \(Object arrays cannot be loaded"):
        read_volume(path)


@pytest.mark.parametrize("keep", [10, 100, 1000])
def test_npy_truncated(tmp_path, ct_crop, keep):
    path = tmp_path / "v.npy"
    np.save(path, ct_crop)
    path.write_bytes(path.read_bytes()[:keep])
    with raises(path, r"not a readable \.npy array"):
        read_volume(path)


def test_npy_sidecar_shape_mismatch(tmp_path, data_dir):
    array, meta = load(data_dir, "mr_t1_itk_kmeans")
    path = tmp_path / "mr.npy"
    np.save(path, array[:, :, :10])
    sidecar = tmp_path / "mr.json"
    sidecar.write_text(json.dumps(meta))
    with raises(sidecar, r"shape \[128, 128, 62\] does not match the array's shape"):
        read_volume(path)


def test_npy_sidecar_corrupt(tmp_path, ct_crop):
    path = tmp_path / "v.npy"
    np.save(path, ct_crop)
    sidecar = tmp_path / "v.json"
    sidecar.write_text('{"spacing_mm": [1, 2')
    with raises(sidecar, "corrupt JSON sidecar"):
        read_volume(path)
    sidecar.write_text('{"spacing_mm": [1, 2]}')
    with raises(sidecar, "spacing_mm .* is not a list of 3 numbers"):
        read_volume(path)
    sidecar.write_text('{"spacing_mm": [1, 0, 2]}')
    with raises(path, r"corrupt header: voxel spacing \[1.0, 0.0, 2.0\]"):
        read_volume(path)


# ---------------------------------------------------------------------------------------------
# raw


def test_raw_little_endian_with_header(tmp_path, ct_crop):
    path = tmp_path / "ct.raw"
    # x fastest in the file: the (Z, Y, X) C-order bytes of the transposed array.
    path.write_bytes(b"H" * 17 + ct_crop.T.astype("<i2").tobytes())
    vol = read_volume(path, shape=ct_crop.shape, dtype="int16", header_bytes=17,
                      spacing=(0.9570312, 0.9570312, 1.5))
    assert_volume(vol, ct_crop, spacing=(0.9570312, 0.9570312, 1.5), origin=(0, 0, 0),
                  orientation=np.eye(3), units="", spacing_known=True, source=path)


def test_raw_big_endian(tmp_path, data_dir):
    array, _ = load(data_dir, "micro_nuclei3d_stardist")
    path = tmp_path / "nuclei.bin"
    path.write_bytes(array.T.astype(">u2").tobytes())
    vol = read_volume(path, shape=array.shape, dtype=np.uint16, byte_order="big")
    assert_volume(vol, array, spacing=(1, 1, 1), origin=(0, 0, 0), orientation=np.eye(3),
                  units="", spacing_known=False, source=path)


@pytest.mark.parametrize("delta", [-1, 1, -1000])
def test_raw_wrong_size(tmp_path, ct_crop, delta):
    path = tmp_path / "ct.raw"
    data = ct_crop.T.tobytes()
    path.write_bytes(data[:delta] if delta < 0 else data + b"\0" * delta)
    with raises(path, f"file has {len(data) + delta} bytes but shape .* needs exactly {len(data)}"):
        read_volume(path, shape=ct_crop.shape, dtype="int16")


def test_raw_needs_layout(tmp_path):
    path = tmp_path / "v.raw"
    path.write_bytes(b"\0" * 24)
    with raises(path, r"no header; give its layout with shape=\(X, Y, Z\) and dtype="):
        read_volume(path, dtype="uint8")
    with raises(path, r"shape must be 3 positive integers"):
        read_volume(path, shape=(4, 6), dtype="uint8")


@pytest.mark.parametrize(
    ("dtype", "match"),
    [("uint12", "unknown dtype 'uint12'"), ("complex64", "unsupported dtype complex64")],
)
def test_raw_bad_dtype(tmp_path, dtype, match):
    path = tmp_path / "v.raw"
    path.write_bytes(b"\0" * 192)
    with raises(path, match):
        read_volume(path, shape=(2, 3, 4), dtype=dtype)


def test_raw_bad_byte_order_and_header(tmp_path):
    path = tmp_path / "v.raw"
    path.write_bytes(b"\0" * 24)
    with raises(path, "byte_order must be 'little' or 'big'"):
        read_volume(path, shape=(2, 3, 4), dtype="uint8", byte_order="middle")
    with raises(path, "header_bytes must be a non-negative integer"):
        read_volume(path, shape=(2, 3, 4), dtype="uint8", header_bytes=-2)


def test_raw_nan(tmp_path):
    array = np.ones((3, 4, 5), np.float32)
    array[2, 0, 4] = np.nan
    path = tmp_path / "v.raw"
    path.write_bytes(array.T.tobytes())
    with raises(path, r"NaN or Inf \(first at voxel \(2, 0, 4\)"):
        read_volume(path, shape=array.shape, dtype="float32")


# ---------------------------------------------------------------------------------------------
# NRRD


def test_nrrd_lps(tmp_path, ct_crop):
    path = tmp_path / "ct.nrrd"
    spacing = np.array([0.9570312, 0.9570312, 1.5])
    origin = np.array([-120.5, -80.25, 33.0])
    write_nrrd(path, ct_crop, {"space": "left-posterior-superior",
                               "space directions": np.diag(spacing), "space origin": origin})
    vol = read_volume(path)
    assert_volume(vol, ct_crop, spacing=spacing, origin=origin, orientation=np.eye(3),
                  units="", spacing_known=True, source=path)


def test_nrrd_ras_oblique_to_lps(tmp_path, data_dir):
    array, _ = load(data_dir, "mr_t1_itk_kmeans")
    path = tmp_path / "mr.nrrd"
    c, s = 0.8, 0.6  # axis directions rotated about S, then scaled by the spacing
    directions_ras = np.array([[2 * c, 2 * s, 0.0], [-2 * s, 2 * c, 0.0], [0.0, 0.0, 3.0]])
    write_nrrd(path, array, {"space": "RAS", "space directions": directions_ras,
                             "space origin": np.array([10.0, -20.0, 30.0])})
    vol = read_volume(path)
    expected = np.array([[-c, s, 0.0], [-s, -c, 0.0], [0.0, 0.0, 1.0]])  # columns, LPS
    assert_volume(vol, array, spacing=(2, 2, 3), origin=(-10, 20, 30), orientation=expected,
                  units="", spacing_known=True, source=path)


def test_nhdr_detached_in_micrometres(tmp_path, data_dir):
    array, _ = load(data_dir, "micro_nuclei3d_stardist")
    path = tmp_path / "nuclei.nhdr"
    write_nrrd(path, array, {"space": "left-posterior-superior",
                             "space directions": np.diag([0.5, 0.5, 2.0]),
                             "space origin": np.zeros(3), "space units": ["um", "um", "um"]},
               detached_header=True)
    vol = read_volume(path)
    assert_volume(vol, array, spacing=(5e-4, 5e-4, 2e-3), origin=(0, 0, 0),
                  orientation=np.eye(3), units="", spacing_known=True, source=path)


def test_nrrd_spacings_only_and_no_geometry(tmp_path, ct_crop):
    path = tmp_path / "a.nrrd"
    write_nrrd(path, ct_crop, {"spacings": [0.5, 0.7, 2.0]})
    vol = read_volume(path)
    assert_volume(vol, ct_crop, spacing=(0.5, 0.7, 2.0), origin=(0, 0, 0), orientation=np.eye(3),
                  units="", spacing_known=True, source=path)
    write_nrrd(path, ct_crop, {})
    assert read_volume(path).spacing_known is False


def test_nrrd_corrupt_header(tmp_path):
    path = tmp_path / "bad.nrrd"
    path.write_bytes(b"NRRD0004\ntype: quaternion\ndimension: 3\nsizes: 2 2 2\n"
                     b"encoding: raw\n\n" + b"\0" * 8)
    with raises(path, "corrupt NRRD file"):
        read_volume(path)
    path.write_bytes(b"PNG\x89 not a nrrd at all\n")
    with raises(path, "corrupt NRRD file"):
        read_volume(path)


def test_nrrd_truncated(tmp_path, ct_crop):
    path = tmp_path / "ct.nrrd"
    write_nrrd(path, ct_crop, {"encoding": "raw"})
    path.write_bytes(path.read_bytes()[:-100])
    with raises(path, "corrupt NRRD file"):
        read_volume(path)


def test_nrrd_wrong_dimensions(tmp_path):
    path = tmp_path / "slice.nrrd"
    write_nrrd(path, np.zeros((4, 5), np.uint8), {})
    with raises(path, "has 2 dimension"):
        read_volume(path)


def test_nrrd_unsupported_space(tmp_path, ct_crop):
    path = tmp_path / "a.nrrd"
    write_nrrd(path, ct_crop, {"space": "3D-left-handed", "space directions": np.eye(3)})
    with raises(path, "unsupported NRRD space '3D-left-handed'"):
        read_volume(path)


# ---------------------------------------------------------------------------------------------
# NIfTI


def test_nifti_real_mr_affine_to_lps(tmp_path, data_dir):
    import nibabel as nib

    array, meta = load(data_dir, "mr_t1_itk_kmeans")
    path = tmp_path / "mr.nii.gz"
    img = nib.Nifti1Image(array, np.array(meta["affine"]))
    img.header.set_xyzt_units("mm")
    nib.save(img, path)
    vol = read_volume(path)
    # RAS affine columns (-2,0,0), (0,0,2), (0,3,0) -> LPS: +L, +S, -P (anterior): "LSA".
    expected = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])
    assert_volume(vol, array, spacing=(2, 2, 3), origin=(0, 254, 0), orientation=expected,
                  units="", spacing_known=True, source=path)


def test_nifti_scaling_applied(tmp_path, ct_crop):
    import nibabel as nib

    path = tmp_path / "ct.nii"
    img = nib.Nifti1Image(ct_crop, np.diag([0.5, 0.5, 1.5, 1.0]))
    img.header.set_slope_inter(2.5, -10.0)
    img.header.set_xyzt_units("micron")
    nib.save(img, path)
    vol = read_volume(path)
    expected = ct_crop.astype(np.float64) * 2.5 - 10.0
    assert_volume(vol, expected, spacing=(5e-4, 5e-4, 1.5e-3), origin=(0, 0, 0),
                  orientation=np.diag([-1.0, -1.0, 1.0]), units="", spacing_known=True,
                  source=path)


def test_nifti_trailing_unit_axis_dropped(tmp_path, data_dir):
    import nibabel as nib

    array, _ = load(data_dir, "micro_nuclei3d_stardist")
    path = tmp_path / "n.nii"
    nib.save(nib.Nifti1Image(array[..., None], np.eye(4)), path)
    vol = read_volume(path)
    assert vol.array.dtype == np.uint16
    np.testing.assert_array_equal(vol.array, array)


def test_nifti_wrong_dimensions(tmp_path, ct_crop):
    import nibabel as nib

    path = tmp_path / "t.nii"
    nib.save(nib.Nifti1Image(np.stack([ct_crop, ct_crop], axis=3), np.eye(4)), path)
    with raises(path, "has 4 dimension"):
        read_volume(path)


def test_nifti_corrupt_and_truncated(tmp_path, ct_crop):
    import nibabel as nib

    path = tmp_path / "ct.nii"
    nib.save(nib.Nifti1Image(ct_crop, np.eye(4)), path)
    data = path.read_bytes()
    path.write_bytes(data[:-500])
    with raises(path, "not a readable NIfTI image"):
        read_volume(path)
    path.write_bytes(b"\x07" * len(data))
    with raises(path, "not a readable NIfTI image"):
        read_volume(path)


def test_nifti_nan(tmp_path):
    import nibabel as nib

    array = np.zeros((3, 4, 5), np.float32)
    array[0, 3, 1] = np.nan
    path = tmp_path / "f.nii.gz"
    nib.save(nib.Nifti1Image(array, np.eye(4)), path)
    with raises(path, r"NaN or Inf \(first at voxel \(0, 3, 1\)"):
        read_volume(path)


# ---------------------------------------------------------------------------------------------
# DICOM


def ct_small_path():
    from pydicom.data import get_testdata_file

    return Path(get_testdata_file("CT_small.dcm"))


def write_series(folder, stored, *, pixel_spacing, dz, origin, row, col, slope, intercept,
                 seed, modality="CT", prefix="IM", step=None):
    """Write ``stored`` (``(X, Y, Z)`` int16) as a DICOM series, cloned from the real CT_small.

    Slice ``k`` sits at ``origin + k * step`` (default ``step``: ``dz`` along the normal).
    Files get shuffled names and instance numbers, so only the positions give the order.
    Returns the series UID and the files in slice order.
    """
    import pydicom
    from pydicom.uid import generate_uid

    template = pydicom.dcmread(ct_small_path())
    uid = generate_uid()
    step = dz * np.cross(row, col) if step is None else np.asarray(step)
    shuffled = np.random.default_rng(seed).permutation(stored.shape[2])
    files = []
    for k in range(stored.shape[2]):
        ds = copy.deepcopy(template)
        ds.Modality = modality
        ds.SeriesInstanceUID = uid
        ds.SOPInstanceUID = generate_uid()
        ds.file_meta.MediaStorageSOPInstanceUID = ds.SOPInstanceUID
        ds.InstanceNumber = int(shuffled[k]) + 1
        ds.Rows, ds.Columns = stored.shape[1], stored.shape[0]
        ds.PixelSpacing = [pixel_spacing[1], pixel_spacing[0]]  # (between rows, between columns)
        ds.ImageOrientationPatient = [float(v) for v in (*row, *col)]
        ds.ImagePositionPatient = [round(float(v), 6) for v in origin + k * step]
        ds.RescaleSlope, ds.RescaleIntercept = slope, intercept
        ds.BitsAllocated, ds.BitsStored, ds.HighBit, ds.PixelRepresentation = 16, 16, 15, 1
        ds.PixelData = np.ascontiguousarray(stored[:, :, k].T, dtype="<i2").tobytes()
        files.append(folder / f"{prefix}{shuffled[k]:04d}.dcm")
        ds.save_as(files[-1], enforce_file_format=True)
    return uid, files


@pytest.fixture()
def axial_series(tmp_path, ct_crop):
    """The CT crop as an axial series stored as HU + 1024 with intercept -1024."""
    folder = tmp_path / "axial"
    folder.mkdir()
    uid, files = write_series(
        folder, ct_crop + 1024, pixel_spacing=(0.5, 0.75), dz=1.25,
        origin=np.array([-16.0, -20.5, 42.0]), row=(1.0, 0.0, 0.0), col=(0.0, 1.0, 0.0),
        slope=1, intercept=-1024, seed=1,
    )
    return folder, uid, files


def test_dicom_real_ct_small(tmp_path):
    import pydicom

    path = tmp_path / "CT_small.dcm"
    shutil.copy(ct_small_path(), path)
    ds = pydicom.dcmread(path)
    vol = read_volume(path)
    expected = (ds.pixel_array.T.astype(np.int32) * int(ds.RescaleSlope)
                + int(ds.RescaleIntercept)).astype(np.int16)[:, :, None]
    row, col = np.array(ds.ImageOrientationPatient[:3]), np.array(ds.ImageOrientationPatient[3:])
    assert_volume(vol, expected,
                  spacing=(ds.PixelSpacing[1], ds.PixelSpacing[0], ds.SliceThickness),
                  origin=np.array(ds.ImagePositionPatient, dtype=float),
                  orientation=np.column_stack([row, col, np.cross(row, col)]),
                  units="HU", spacing_known=True, source=path)


def test_dicom_axial_series_folder_file_and_list(axial_series, ct_crop):
    folder, _, files = axial_series
    expected = dict(spacing=(0.5, 0.75, 1.25), origin=(-16.0, -20.5, 42.0),
                    orientation=np.eye(3), units="HU", spacing_known=True)
    assert_volume(read_volume(folder), ct_crop, source=folder, **expected)
    assert_volume(read_volume(str(files[5])), ct_crop, source=files[5], **expected)
    listed = read_volume(files[::-1])
    assert_volume(listed, ct_crop, source=listed.source, **expected)
    assert listed.source.startswith(str(files[-1])) and "11 more files" in listed.source


def test_dicom_oblique_shuffled_float_rescale(tmp_path, data_dir):
    array, _ = load(data_dir, "mr_t1_itk_kmeans")
    stored = np.ascontiguousarray(array[30:90, 20:100, 20:34])  # 60 x 80 x 14
    row, col = np.array([0.6, 0.8, 0.0]), np.array([0.0, 0.0, -1.0])
    normal = np.cross(row, col)  # (-0.8, 0.6, 0)
    origin = np.array([12.0, -7.5, 60.0])
    write_series(tmp_path, stored, pixel_spacing=(0.9, 1.1), dz=2.5, origin=origin, row=row,
                 col=col, slope=2.5, intercept=-10, seed=7, modality="MR")
    vol = read_volume(tmp_path)
    expected = stored.astype(np.float32) * np.float32(2.5) + np.float32(-10)
    assert_volume(vol, expected, spacing=(0.9, 1.1, 2.5), origin=origin,
                  orientation=np.column_stack([row, col, normal]), units="",
                  spacing_known=True, source=tmp_path)


def test_dicom_series_stacked_against_the_normal(tmp_path, ct_crop):
    # Positions written with decreasing z: the reader must flip the stack so z grows.
    write_series(tmp_path, ct_crop[:, :, ::-1] + 1024, pixel_spacing=(0.5, 0.5), dz=-2.0,
                 origin=np.array([0.0, 0.0, 100.0]), row=(1.0, 0.0, 0.0), col=(0.0, 1.0, 0.0),
                 slope=1, intercept=-1024, seed=3)
    vol = read_volume(tmp_path)
    assert_volume(vol, ct_crop, spacing=(0.5, 0.5, 2.0),
                  origin=(0.0, 0.0, 100.0 - 2.0 * (ct_crop.shape[2] - 1)), orientation=np.eye(3),
                  units="HU", spacing_known=True, source=tmp_path)


def test_dicom_gantry_tilt_gives_the_stacking_direction(tmp_path, ct_crop):
    # Each slice is axial but shifted 0.5 mm in y (gantry tilt): the grid is sheared, and the
    # third orientation column must follow the real stacking direction, not the normal.
    step = np.array([0.0, 0.5, 2.0])
    write_series(tmp_path, ct_crop + 1024, pixel_spacing=(0.5, 0.5), dz=None, step=step,
                 origin=np.array([1.0, 2.0, 3.0]), row=(1.0, 0.0, 0.0), col=(0.0, 1.0, 0.0),
                 slope=1, intercept=-1024, seed=5)
    vol = read_volume(tmp_path)
    orientation = np.column_stack([(1, 0, 0), (0, 1, 0), step / np.linalg.norm(step)])
    assert_volume(vol, ct_crop, spacing=(0.5, 0.5, np.linalg.norm(step)), origin=(1, 2, 3),
                  orientation=orientation, units="HU", spacing_known=True, source=tmp_path)
    last = vol.index_to_physical() @ np.array([0, 0, ct_crop.shape[2] - 1, 1.0])
    np.testing.assert_allclose(last[:3], (1, 2 + 0.5 * 11, 3 + 2.0 * 11))


def test_dicom_two_series(tmp_path, axial_series, ct_crop):
    folder, uid, _ = axial_series
    other, _ = write_series(folder, ct_crop[:, :, :3] + 1024, pixel_spacing=(1.0, 1.0), dz=3.0,
                            origin=np.zeros(3), row=(1.0, 0.0, 0.0), col=(0.0, 1.0, 0.0),
                            slope=1, intercept=-1024, seed=2, prefix="SE2_")
    with raises(folder, f"holds 2 DICOM series; choose one with series_uid=.*{uid}.*{other}|"
                        f"holds 2 DICOM series; choose one with series_uid=.*{other}.*{uid}"):
        read_volume(folder)
    np.testing.assert_array_equal(read_volume(folder, series_uid=uid).array, ct_crop)
    assert read_volume(folder, series_uid=other).shape == (64, 48, 3)
    with raises(folder, "no series with SeriesInstanceUID '1.2.3'"):
        read_volume(folder, series_uid="1.2.3")


def test_dicom_folder_without_series(tmp_path):
    (tmp_path / "notes.txt").write_text("not DICOM")
    np.save(tmp_path / "v.npy", np.zeros((2, 2, 2)))
    with raises(tmp_path, r"no DICOM image series found among 2 file\(s\)"):
        read_volume(tmp_path)
    empty = tmp_path / "empty"
    empty.mkdir()
    with raises(empty, r"no DICOM image series found among 0 file\(s\)"):
        read_volume(empty)


def test_dicom_explicit_non_dicom_file(tmp_path, axial_series):
    _, _, files = axial_series
    bad = tmp_path / "notes.txt"
    bad.write_text("not DICOM")
    with raises(bad, "not a readable DICOM file"):
        read_volume([*files, bad])


def test_dicom_truncated_and_foreign_file(tmp_path):
    path = tmp_path / "slice.dcm"
    path.write_bytes(ct_small_path().read_bytes()[:20000])  # header intact, pixels cut
    with raises(path, r"cannot decode the pixel data \(The number of bytes of pixel data"):
        read_volume(path)
    path.write_bytes(b"\x89PNG\r\n" + b"\0" * 200)
    with raises(path, "not a readable DICOM file"):
        read_volume(path)


def _edit(path, **changes):
    import pydicom

    ds = pydicom.dcmread(path)
    for key, value in changes.items():
        setattr(ds, key, value)
    ds.save_as(path)


def test_dicom_mixed_sizes(axial_series, ct_crop):
    folder, _, files = axial_series
    _edit(files[4], Rows=24, Columns=64, PixelData=ct_crop[:, :24, 4].T.astype("<i2").tobytes())
    with raises(folder, "mixes image sizes 64x24, 64x48"):
        read_volume(folder)


def test_dicom_mixed_orientations(axial_series):
    folder, _, files = axial_series
    _edit(files[2], ImageOrientationPatient=[1.0, 0.0, 0.0, 0.0, 0.0, -1.0])
    with raises(folder, "mixes slice orientations"):
        read_volume(folder)


def test_dicom_missing_slice(axial_series):
    folder, _, files = axial_series
    files[6].unlink()
    with raises(folder, "not evenly spaced: gaps along the normal range from 1.25 to 2.5 mm"):
        read_volume(folder)


def test_dicom_duplicate_position(axial_series):
    import pydicom

    folder, _, files = axial_series
    position = pydicom.dcmread(files[3]).ImagePositionPatient
    _edit(files[4], ImagePositionPatient=position)
    with raises(folder, "two or more slices share one position"):
        read_volume(folder)


def test_dicom_slice_without_position(axial_series):
    import pydicom

    folder, _, files = axial_series
    ds = pydicom.dcmread(files[0])
    del ds.ImagePositionPatient
    ds.save_as(files[0])
    with raises(folder, f"{files[0].name} has no ImagePositionPatient"):
        read_volume(folder)


# ---------------------------------------------------------------------------------------------
# TIFF


@pytest.mark.parametrize("unit", ["micron", "\\u00B5m", "um"])  # ImageJ escapes the µ
def test_tiff_imagej_spacing(tmp_path, data_dir, unit):
    import tifffile

    array, _ = load(data_dir, "micro_nuclei3d_stardist")
    path = tmp_path / "nuclei.tif"
    tifffile.imwrite(path, array.T, imagej=True, resolution=(1 / 0.25, 1 / 0.5),
                     metadata={"spacing": 2.0, "unit": unit, "axes": "ZYX"})
    with tifffile.TiffFile(path) as tif:
        assert tif.imagej_metadata["unit"] == unit  # as ImageJ and tifffile store it
    vol = read_volume(path)
    assert_volume(vol, array, spacing=(2.5e-4, 5e-4, 2e-3), origin=(0, 0, 0),
                  orientation=np.eye(3), units="", spacing_known=True, source=path)


def test_tiff_ome_spacing(tmp_path, data_dir):
    import tifffile

    array, _ = load(data_dir, "micro_nuclei3d_stardist")
    path = tmp_path / "nuclei.ome.tiff"
    tifffile.imwrite(path, array.T, ome=True, photometric="minisblack",
                     metadata={"axes": "ZYX", "PhysicalSizeX": 0.2, "PhysicalSizeY": 0.3,
                               "PhysicalSizeZ": 0.004, "PhysicalSizeZUnit": "mm"})
    vol = read_volume(path)
    assert_volume(vol, array, spacing=(2e-4, 3e-4, 4e-3), origin=(0, 0, 0),
                  orientation=np.eye(3), units="", spacing_known=True, source=path)


def test_tiff_plain_stack(tmp_path, ct_crop):
    import tifffile

    path = tmp_path / "ct.tiff"
    tifffile.imwrite(path, ct_crop.T, photometric="minisblack", metadata=None)
    vol = read_volume(path)
    assert_volume(vol, ct_crop, spacing=(1, 1, 1), origin=(0, 0, 0), orientation=np.eye(3),
                  units="", spacing_known=False, source=path)


def test_tiff_bad_inputs(tmp_path):
    import tifffile

    path = tmp_path / "slice.tif"
    tifffile.imwrite(path, np.zeros((5, 6), np.uint8))
    with raises(path, "has 2 dimension"):
        read_volume(path)
    path = tmp_path / "rgb.tif"
    tifffile.imwrite(path, np.zeros((4, 5, 6, 3), np.uint8), photometric="rgb")
    with raises(path, "colour samples or channels"):
        read_volume(path)
    path = tmp_path / "junk.tif"
    path.write_bytes(b"II*\0" + b"\xff" * 40)
    with raises(path, "not a readable TIFF file"):
        read_volume(path)


# ---------------------------------------------------------------------------------------------
# VolPack .den


@pytest.mark.parametrize("byte_order", ["<", ">"])
def test_den_brainsmall(tmp_path, data_dir, byte_order):
    array, _ = load(data_dir, "mr_brainsmall_volpack")
    path = tmp_path / "brainsmall.den"
    write_den(path, array, byte_order)
    vol = read_volume(path)
    assert_volume(vol, array, spacing=(1, 1, 1), origin=(0, 0, 0), orientation=np.eye(3),
                  units="", spacing_known=False, source=path)


def test_den_debian_original(tmp_path, data_dir):
    candidates = sorted(Path("/usr/share/doc/libvolpack1-dev/examples").glob("brainsmall.den*"))
    if not candidates:
        skip_unless_ci("Debian's libvolpack1-dev examples are not installed")
    path = candidates[0]
    if path.suffix == ".gz":  # Debian compresses large files under /usr/share/doc
        import gzip

        plain = tmp_path / "brainsmall.den"
        plain.write_bytes(gzip.decompress(path.read_bytes()))
        path = plain
    array, _ = load(data_dir, "mr_brainsmall_volpack")
    np.testing.assert_array_equal(read_volume(path).array, array)


def test_den_bad_files(tmp_path, data_dir):
    array, _ = load(data_dir, "mr_brainsmall_volpack")
    path = tmp_path / "b.den"
    write_den(path, array, "<")
    data = path.read_bytes()
    path.write_bytes(data[:-1])
    with raises(path, r"file has 1376317 bytes but its header announces 62 \+ 1376256"):
        read_volume(path)
    path.write_bytes(data[:40])
    with raises(path, "truncated VolPack .den file: 40 bytes"):
        read_volume(path)
    path.write_bytes(b"\x02\x00" + data[2:])
    with raises(path, "corrupt header: not a VolPack .den file"):
        read_volume(path)
    path.write_bytes(data[:58] + np.array([1000], "<i4").tobytes() + data[62:])
    with raises(path, r"corrupt header: map_len \(128, 128, 84\) and map_length 1000 disagree"):
        read_volume(path)


# ---------------------------------------------------------------------------------------------
# Bad input of every class (issue 9): path-level cases, silent wrong data, third-party errors,
# huge headers and the memory check; .npy, raw, NIfTI, NRRD and .den (DICOM and TIFF have
# tests/test_readers_dicom_tiff_errors.py).


def nifti_bytes(array):
    """``array`` as the bytes of a ``.nii`` file written by nibabel (0.5 x 0.6 x 0.7 mm)."""
    import nibabel as nib

    img = nib.Nifti1Image(array, np.diag([0.5, 0.6, 0.7, 1.0]))
    img.header.set_xyzt_units("mm")
    return img.to_bytes()


def test_read_volume_bytes_path(tmp_path, ct_crop):
    path = tmp_path / "ct.npy"
    np.save(path, ct_crop)
    with pytest.raises(VolumeEVMError, match=re.escape(f"{bytes(path)!r}: a path given as bytes")):
        read_volume(bytes(path))


@pytest.mark.parametrize("name", ["a" * 300 + ".nii", "a/" * 3000 + "v.nii"])
def test_read_volume_path_too_long(tmp_path, name):
    path = tmp_path / name
    with raises(path, r"cannot access this path \(the path or one of its names is too long"):
        read_volume(path)


def test_read_volume_permission_denied(tmp_path, monkeypatch, ct_crop):
    from volumeevm_addon.readers import _checks

    path = tmp_path / "ct.npy"
    np.save(path, ct_crop)
    path.chmod(0)
    if os.access(path, os.R_OK):  # root reads any file: make open() fail as it does for users
        def denied(file, *args, **kwargs):
            raise PermissionError(errno.EACCES, "Permission denied", str(file))

        monkeypatch.setattr(_checks, "open", denied, raising=False)
    with raises(path, r"cannot open the file for reading \(Permission denied\)") as caught:
        read_volume(path)
    assert isinstance(caught.value.__cause__, PermissionError)


def test_read_volume_folder_with_volume_extension(tmp_path):
    path = tmp_path / "head.nii.gz"
    path.mkdir()
    with raises(path, r"is a folder, not a \.nii\.gz file"):
        read_volume(path)


def test_read_volume_broken_symlink(tmp_path):
    path = tmp_path / "head.nrrd"
    path.symlink_to(tmp_path / "moved.nrrd")
    with raises(path, f"broken symbolic link \\(its target {re.escape(str(tmp_path))}/moved"):
        read_volume(path)


def test_read_volume_fifo(tmp_path):
    path = tmp_path / "stream.raw"
    os.mkfifo(path)  # a reader opening it would wait for a writer forever
    with raises(path, r"not a regular file or folder \(a FIFO, socket or device\)"):
        read_volume(path, shape=(2, 2, 2), dtype="uint8")


def test_read_volume_device(tmp_path):
    path = tmp_path / "zero.npy"
    path.symlink_to("/dev/zero")  # endless zeros
    with raises(path, "not a regular file or folder"):
        read_volume(path)


def test_nhdr_data_file_fifo(tmp_path, ct_crop):
    path = tmp_path / "ct.nhdr"
    write_nrrd(path, ct_crop, {"encoding": "raw"}, detached_header=True)
    data = tmp_path / "ct.raw"
    data.unlink()
    os.mkfifo(data)
    with raises(data, r"not a regular file \(a folder, FIFO, socket or device\)"):
        read_volume(path)


@pytest.mark.parametrize(("name", "match"), [
    ("v.npy", r"not a readable \.npy array \(corrupt header: EOF"),
    ("v.raw", r"file has 0 bytes but shape \(2, 2, 2\)"),
    ("v.nii", r"the header size field is not 348 or 540"),
    ("v.nii.gz", r"the header size field is not 348 or 540"),
    ("v.nrrd", r"not a NRRD file: it does not start with 'NRRD000x'"),
    ("v.nhdr", r"not a NRRD file"),
    ("v.den", r"truncated VolPack \.den file: 0 bytes"),
])
def test_empty_file(tmp_path, name, match):
    # Nothing to parse: a clear refusal, not pynrrd's StopIteration or NumPy's EOFError.
    path = tmp_path / name
    path.write_bytes(b"")
    with raises(path, match):
        read_volume(path, **({"shape": (2, 2, 2), "dtype": "uint8"} if name == "v.raw" else {}))


# .npy


@pytest.mark.parametrize(("old", "new", "match", "cause"), [
    (b"(64, 48, 12)", b"(64, 48, 11)", r"the file has 73856 bytes but its header announces 128 "
                                       r"\+ 67584", None),
    (b"'<i2'", b"'<i4'", r"header announces 128 \+ 147456", None),
    (b"(64, 48, 12)", b"(64, 48, -1)", r"corrupt header: shape \(64, 48, -1\) has a negative",
     None),
    (b"'<i2'", b"'<i3'", r"corrupt header: descr is not a valid dtype descriptor", ValueError),
    (b"False", b"Falsx", r"corrupt header: malformed node", ValueError),
    (b"12), }", b'12), """', r"corrupt header: \('EOF in multi-line string'",
     tokenize.TokenError),
])
def test_npy_header_mismatch(tmp_path, ct_crop, old, new, match, cause):
    path = tmp_path / "ct.npy"
    np.save(path, ct_crop)
    data = path.read_bytes()
    assert old in data[:128]
    path.write_bytes(data.replace(old, new, 1))
    with raises(path, r"not a readable \.npy array \(.*" + match) as caught:
        read_volume(path)
    assert type(caught.value.__cause__) is (type(None) if cause is None else cause)


def test_npy_trailing_bytes(tmp_path, ct_crop):
    path = tmp_path / "ct.npy"
    np.save(path, ct_crop)
    path.write_bytes(path.read_bytes() + b"\0\0")
    with raises(path, r"the file has 73858 bytes but its header announces 128 \+ 73728"):
        read_volume(path)


def test_npy_huge_header(tmp_path, monkeypatch, ct_crop):
    # A header claiming 2.4 TB: refused by the file length, before any allocation.
    path = tmp_path / "ct.npy"
    np.save(path, ct_crop)
    path.write_bytes(path.read_bytes().replace(b"(64, 48, 12)", b"(64000, 48000, 400)", 1))
    with raises(path, r"header announces 128 \+ 2457600000000 for shape"):
        read_volume(path)


# raw


def test_raw_shape_product_overflows(tmp_path):
    path = tmp_path / "v.raw"
    path.write_bytes(b"\0" * 64)
    shape = (2**40, 2**40, 2**40)  # 2**121 samples: int64 products would wrap around
    with raises(path, f"file has 64 bytes but shape .* needs exactly {2 * 2**120}"):
        read_volume(path, shape=shape, dtype="int16")


@pytest.mark.parametrize("shape", [7, (2, 2, 2.0), (2, 2, True, 1)])
def test_raw_bad_shape_type(tmp_path, shape):
    path = tmp_path / "v.raw"
    path.write_bytes(b"\0" * 8)
    with raises(path, "shape must be 3 positive integers"):
        read_volume(path, shape=shape, dtype="uint8")


# NIfTI


@pytest.fixture()
def nii_gz(tmp_path, ct_crop):
    """The CT crop saved by nibabel as ``.nii.gz`` (its bytes and path)."""
    import nibabel as nib

    path = tmp_path / "ct.nii.gz"
    nib.save(nib.Nifti1Image(ct_crop, np.diag([0.5, 0.6, 0.7, 1.0])), path)
    return path, path.read_bytes()


@pytest.mark.parametrize(("where", "match"), [
    (-8, r"CRC check failed"),  # the stored CRC-32
    (-1, r"Incorrect length of data produced"),  # the stored length (ISIZE)
])
def test_nifti_gzip_crc_corrupt(nii_gz, where, match):
    path, data = nii_gz
    changed = bytearray(data)
    changed[where] ^= 0x01
    path.write_bytes(bytes(changed))
    with raises(path, r"the gzip-compressed NIfTI data is corrupt or truncated \(BadGzipFile: "
                + match) as caught:
        read_volume(path)
    assert isinstance(caught.value.__cause__, OSError)


def test_nifti_gzip_corrupt_deflate_and_truncated(nii_gz):
    path, data = nii_gz
    path.write_bytes(data[:-8])  # the trailer cut off: CRC never checked
    with raises(path, r"corrupt or truncated \(EOFError: Compressed file ended"):
        read_volume(path)
    changed = bytearray(data)
    changed[len(data) // 2] ^= 0x10  # inside the deflate stream
    path.write_bytes(bytes(changed))
    with raises(path, r"the gzip-compressed NIfTI data (is corrupt or truncated|ends after|"
                      r"holds more than)"):
        read_volume(path)


def test_nifti_gzip_inflates_past_the_header(nii_gz):
    path, data = nii_gz
    plain = gzip.decompress(data)
    path.write_bytes(gzip.compress(plain + bytes(1 << 20)))  # 1 MiB of zeros nobody announced
    with raises(path, r"the gzip-compressed NIfTI data holds more than the 74080 bytes"):
        read_volume(path)
    path.write_bytes(gzip.compress(plain[:-2]))
    with raises(path, r"the gzip-compressed NIfTI data ends after 74078 bytes but the header "
                      r"announces 74080"):
        read_volume(path)


def test_nifti_gzip_huge_header(nii_gz, monkeypatch):
    # 19 bytes of header change claim 4 GiB: refused by the memory check before inflating.
    path, data = nii_gz
    plain = patch_nifti(gzip.decompress(data), dim=[3, 2048, 1024, 1024, 1, 1, 1, 1])
    path.write_bytes(gzip.compress(plain))
    monkeypatch.setenv("VOLUMEEVM_MEMORY_LIMIT", "1G")
    with raises(path, r"reading a 2048x1024x1024 int16 volume needs about 8\.0 GiB of memory but "
                      r"only 1\.0 GiB is available; crop"):
        read_volume(path)


def test_nifti_vox_offset_zero(tmp_path, ct_crop):
    path = tmp_path / "ct.nii"
    data = nifti_bytes(ct_crop)
    for offset in (0, 100, 351.5):  # inside the header, or not a whole byte
        path.write_bytes(patch_nifti(data, vox_offset=offset))
        with raises(path, f"corrupt header: vox_offset {offset:g} is not a whole number of bytes "
                          f"past the 352-byte header"):
            read_volume(path)


def test_nifti_pixdim_zero(tmp_path, ct_crop):
    path = tmp_path / "ct.nii"
    data = patch_nifti(nifti_bytes(ct_crop), sform_code=0, qform_code=1)
    path.write_bytes(data)
    assert read_volume(path).spacing == pytest.approx((0.5, 0.6, 0.7))
    path.write_bytes(patch_nifti(data, pixdim=[1, 0, 0, 0, 1, 1, 1, 1]))  # sizes not given
    vol = read_volume(path)
    assert_volume(vol, ct_crop, spacing=(1, 1, 1), origin=(0, 0, 0),
                  orientation=np.diag([-1.0, -1.0, 1.0]), units="", spacing_known=False,
                  source=path)
    for bad in (0.0, -0.6, np.nan, np.inf):  # one size 0 or invalid: corrupt, not 1 mm
        path.write_bytes(patch_nifti(data, pixdim=[1, 0.5, bad, 0.7, 1, 1, 1, 1]))
        with raises(path, r"corrupt header: voxel sizes pixdim\[1:4\] = \[0\.5, "
                          f"{re.escape(repr(float(np.float32(bad))))}"):
            read_volume(path)


def test_nifti_trailing_bytes(tmp_path, ct_crop):
    path = tmp_path / "ct.nii"
    data = nifti_bytes(ct_crop)
    path.write_bytes(data + b"\0" * 4)
    with raises(path, r"the file has 74084 bytes but its header announces 352 \+ 73728 for "
                      r"64x48x12 voxels of int16\); the file is truncated"):
        read_volume(path)
    path.write_bytes(patch_nifti(data, dim=[3, 64, 48, 11, 1, 1, 1, 1]))  # shrunk dimensions
    with raises(path, r"the file has 74080 bytes but its header announces 352 \+ 67584"):
        read_volume(path)


def test_nifti_huge_header(tmp_path, ct_crop):
    # 70 TB announced by a 74 kB file: refused by the file length, before any allocation.
    path = tmp_path / "ct.nii"
    path.write_bytes(patch_nifti(nifti_bytes(ct_crop), dim=[3, 32767, 32767, 32767, 1, 1, 1, 1]))
    with raises(path, f"the file has 74080 bytes but its header announces 352 \\+ {2 * 32767**3} "
                      f"for 32767x32767x32767 voxels of int16"):
        read_volume(path)


@pytest.mark.parametrize(("fields", "match"), [
    ({"datatype": 16}, r"bitpix 16 disagrees with datatype float32, 32 bits"),
    ({"datatype": 16, "bitpix": 32}, r"header announces 352 \+ 147456"),
    ({"datatype": 99}, r"datatype code 99 is not one NIfTI defines"),
    ({"datatype": 32, "bitpix": 64}, r"unsupported data type complex64"),
    # dim[0] outside 1..7 means the other byte order (NIfTI rule): the sizes read as garbage
    ({"dim": [9, 64, 48, 12, 1, 1, 1, 1]}, r"dimensions \[2304, .*\] are not 1 to 7"),
    ({"dim": [3, 64, -48, 12, 1, 1, 1, 1]}, r"are not 1 to 7 positive sizes"),
    ({"magic": b"ni1"}, r"magic b'ni1', expected b'n\+1': a \.hdr/\.img pair header"),
    ({"sizeof_hdr": 349}, r"the header size field is not 348 or 540"),
    ({"xyzt_units": 7}, r"xyzt_units 7 holds no known spatial unit code"),
    ({"scl_slope": 2.0, "scl_inter": np.inf}, r"Valid slope but invalid intercept inf"),
    ({"sform_code": 0, "qform_code": 1, "pixdim": [3, 1, 1, 1, 1, 1, 1, 1]},
     r"qfac \(pixdim\[0\]\) should be 1 or -1"),
])
def test_nifti_corrupt_header_fields(tmp_path, ct_crop, fields, match):
    path = tmp_path / "ct.nii"
    path.write_bytes(patch_nifti(nifti_bytes(ct_crop), **fields))
    with raises(path, r"not a readable NIfTI image|unsupported data type") as caught:
        read_volume(path)
    assert re.search(match, str(caught.value)), str(caught.value)


@pytest.mark.parametrize("slope", [0.0, np.nan])
def test_nifti_slope_zero_or_nan_means_unscaled(tmp_path, ct_crop, slope):
    # NIfTI-1: "if scl_slope is 0, no scaling"; nibabel also reads NaN so.
    path = tmp_path / "ct.nii"
    path.write_bytes(patch_nifti(nifti_bytes(ct_crop), scl_slope=slope, scl_inter=5.0))
    vol = read_volume(path)
    assert vol.array.dtype == np.int16
    np.testing.assert_array_equal(vol.array, ct_crop)


@pytest.mark.parametrize(("name", "version", "scaling", "endian"), [
    ("mr.nii", 1, None, "<"), ("mr.nii.gz", 1, (0.25, 3.0), "<"), ("mr.nii", 1, None, ">"),
    ("mr.nii", 2, None, "<"), ("mr.nii.gz", 2, (0.25, 3.0), ">"),
])
def test_nifti_same_as_nibabel(tmp_path, data_dir, name, version, scaling, endian):
    # The reader's own data path gives nibabel's own values and affine: NIfTI-1 and -2, both
    # byte orders, scaled or not.
    import nibabel as nib

    array, meta = load(data_dir, "mr_t1_itk_kmeans")
    image_class, header_class = ((nib.Nifti1Image, nib.Nifti1Header) if version == 1
                                 else (nib.Nifti2Image, nib.Nifti2Header))
    header = header_class(endianness=endian)
    header.set_data_dtype(np.int16)
    img = image_class(array, np.array(meta["affine"]), header)
    if scaling:
        img.header.set_slope_inter(*scaling)
    path = tmp_path / name
    nib.save(img, path)
    vol = read_volume(path)
    reference = nib.load(path)
    assert reference.header.endianness == endian
    expected = np.asanyarray(reference.dataobj)
    assert vol.array.dtype == expected.dtype.newbyteorder("=")
    np.testing.assert_array_equal(vol.array, expected)
    np.testing.assert_allclose(vol.index_to_physical()[:3],
                               (np.diag([-1, -1, 1, 1]) @ reference.affine)[:3])


# NRRD


def test_nrrd_misspelt_field(tmp_path, ct_crop):
    path = tmp_path / "ct.nrrd"
    write_nrrd(path, ct_crop, {"space": "left-posterior-superior", "encoding": "raw",
                               "space directions": np.eye(3), "space origin": [5.0, 6.0, 7.0]})
    data = path.read_bytes()
    path.write_bytes(data.replace(b"space origin:", b"space orign:", 1))
    with raises(path, r"header line \d+ has the unknown field 'space orign' \(did you mean "
                      r"'space origin'\?\)"):
        read_volume(path)
    path.write_bytes(data.replace(b"space origin:", b"my origin:=", 1))  # a key/value pair
    assert read_volume(path).origin == (0.0, 0.0, 0.0)


def test_nrrd_non_ascii_header(tmp_path, ct_crop):
    path = tmp_path / "ct.nrrd"
    write_nrrd(path, ct_crop, {"space": "left-posterior-superior", "encoding": "raw",
                               "space directions": np.eye(3), "space origin": [5.0, 6.0, 7.0]})
    data = path.read_bytes()
    path.write_bytes(data.replace(b"space origin: (5", b"space origin: (\xb55", 1))
    with raises(path, r"header line \d+ holds bytes that are not ASCII: b'space origin: "):
        read_volume(path)


def test_nrrd_trailing_bytes_and_shrunk_sizes(tmp_path, ct_crop):
    path = tmp_path / "ct.nrrd"
    write_nrrd(path, ct_crop, {"encoding": "raw"})
    data = path.read_bytes()
    path.write_bytes(data + b"\0")
    with raises(path, r"the data holds 73729 bytes but sizes \[64, 48, 12\] of int16 need "
                      r"exactly 73728"):
        read_volume(path)
    path.write_bytes(data.replace(b"sizes: 64 48 12", b"sizes: 64 48 11", 1))
    with raises(path, r"the data holds 73728 bytes but sizes \[64, 48, 11\]"):
        read_volume(path)
    path.write_bytes(data.replace(b"type: int16", b"type: int8", 1))  # a changed type
    with raises(path, r"the data holds 73728 bytes but sizes \[64, 48, 12\] of int8 need "
                      r"exactly 36864"):
        read_volume(path)


@pytest.mark.parametrize("encoding", ["gzip", "bzip2"])
def test_nrrd_compressed_stream_checked(tmp_path, ct_crop, encoding):
    path = tmp_path / "ct.nrrd"
    write_nrrd(path, ct_crop, {"encoding": encoding})
    data = path.read_bytes()
    path.write_bytes(data.replace(b"sizes: 64 48 12", b"sizes: 64 48 11", 1))
    with raises(path, f"the {encoding}-compressed NRRD data holds more than the 67584 bytes"):
        read_volume(path)
    path.write_bytes(data[:-10])
    with raises(path, f"the {encoding}-compressed NRRD data is corrupt or truncated"):
        read_volume(path)
    if encoding == "gzip":
        changed = bytearray(data)
        changed[-8] ^= 0x01  # the stored CRC-32
        path.write_bytes(bytes(changed))
        with raises(path, r"is corrupt or truncated \(BadGzipFile: CRC check failed"):
            read_volume(path)


def test_nrrd_huge_header(tmp_path, monkeypatch, ct_crop):
    path = tmp_path / "ct.nrrd"
    write_nrrd(path, ct_crop, {"encoding": "gzip"})
    path.write_bytes(path.read_bytes().replace(b"sizes: 64 48 12", b"sizes: 4096 4096 4096", 1))
    monkeypatch.setenv("VOLUMEEVM_MEMORY_LIMIT", "2G")
    with raises(path, r"reading a 4096x4096x4096 int16 volume needs about 256\.0 GiB of memory "
                      r"but only 2\.0 GiB is available"):
        read_volume(path)


@pytest.mark.parametrize(("old", "new", "match"), [
    (b"encoding: raw", b"encoding: hex", r"encoding 'hex' is not one VolumeEVM reads"),
    (b"endian: little", b"endian: middle", r"'endian' is 'middle'; 'little' or 'big' is required"),
    (b"type: int16", b"type: block", r"type 'block' is not a NRRD scalar type"),
    (b"sizes: 64 48 12", b"sizes: 64 48 x", r"corrupt NRRD file \(ValueError: "),
    (b"dimension: 3", b"dimension: 4", r"sizes \[64, 48, 12\] are not 4 positive numbers"),
    (b"sizes: 64 48 12", b"sizes: 64 0 12", r"sizes \[64, 0, 12\] are not 3 positive numbers"),
    (b"space origin: (5,6,7)", b"space origin: (5,6,7", r"Vector should be enclosed"),
    (b"space origin: (5,6,7)", b"space origin: (5,6)", r"'space origin' \[5\. 6\.\] is not 3-D"),
    (b"NRRD0005", b"NRRD0009", r"Unsupported NRRD file version"),
    (b"NRRD0005", b"PK\x03\x04\x00\x00\x00\x00", r"not a NRRD file: it does not start"),
    (b"encoding: raw\n", b"encoding: raw\nbyte skip: -2\n", r"byte skip -2: skips are >= 0"),
    (b"encoding: raw\n", b"encoding: raw\ndata file: a%03d.raw 0 9 1\n",
     r"the data is split over several files"),
    (b"encoding: raw\n", b"encoding: raw\nspace: left-posterior-superior\n",
     r"Duplicate header field: space"),
])
def test_nrrd_corrupt_header_fields(tmp_path, ct_crop, old, new, match):
    path = tmp_path / "ct.nrrd"
    write_nrrd(path, ct_crop, {"space": "left-posterior-superior", "encoding": "raw",
                               "space directions": np.eye(3), "space origin": [5.0, 6.0, 7.0]})
    data = path.read_bytes()
    assert old in data
    path.write_bytes(data.replace(old, new, 1))
    with raises(path, match):
        read_volume(path)


def test_nrrd_header_without_end(tmp_path):
    path = tmp_path / "ct.nrrd"
    path.write_bytes(b"NRRD0005\n" + b"# comment\n" * 200_000)  # 2 MB and no blank line
    with raises(path, r"no blank line ends the header within 1048576 bytes"):
        read_volume(path)


def test_nrrd_ascii_encoding(tmp_path, ct_crop):
    path = tmp_path / "ct.nrrd"
    write_nrrd(path, ct_crop, {"encoding": "ascii", "spacings": [0.5, 0.6, 0.7]})
    np.testing.assert_array_equal(read_volume(path).array, ct_crop)
    path.write_bytes(path.read_bytes() + b" 12")
    with raises(path, r"the ASCII data holds 36865 numbers but the sizes announce 36864"):
        read_volume(path)


# VolPack .den


def test_den_huge_and_negative_sizes(tmp_path, ct_crop):
    path = tmp_path / "v.den"
    array = np.ascontiguousarray(ct_crop[:16, :8, :4] > 0, dtype=np.uint8)
    write_den(path, array, "<")
    data = bytearray(path.read_bytes())
    data[50:56] = np.array([32767, 32767, 32767], "<i2").tobytes()  # map_len
    path.write_bytes(bytes(data))
    with raises(path, r"map_len \(32767, 32767, 32767\) and map_length 512 disagree"):
        read_volume(path)
    data[50:56] = np.array([16, -8, 4], "<i2").tobytes()
    path.write_bytes(bytes(data))
    with raises(path, r"map_len \(16, -8, 4\) and map_length 512 disagree"):
        read_volume(path)


# memory checked before reading (section 4)


@pytest.mark.parametrize("name", ["ct.npy", "ct.raw", "ct.nii", "ct.nii.gz", "ct.nrrd", "ct.nhdr",
                                  "ct.den"])
def test_import_memory_budget(tmp_path, monkeypatch, data_dir, name):
    import nibabel as nib

    array, _ = load(data_dir, "ct_head_invesalius")  # 256 x 256 x 108 int16: 13.5 MiB
    if name == "ct.den":
        array = np.clip(array // 16 + 64, 0, 255).astype(np.uint8)
    path = tmp_path / name
    options = {}
    if name == "ct.npy":
        np.save(path, array)
    elif name == "ct.raw":
        path.write_bytes(array.T.tobytes())
        options = {"shape": array.shape, "dtype": "int16"}
    elif name.startswith("ct.nii"):
        nib.save(nib.Nifti1Image(array, np.eye(4)), path)
    elif name == "ct.den":
        write_den(path, array, "<")
    else:
        write_nrrd(path, array, {}, detached_header=name.endswith(".nhdr"), compression_level=1)
    copies = 1 if name == "ct.npy" else 2  # the read buffer, and the C-ordered array
    needed = copies * array.nbytes / 2**20 + 1  # MiB, with one read chunk of headroom
    monkeypatch.setenv("VOLUMEEVM_MEMORY_LIMIT", f"{needed - 0.5:.1f}M")
    with raises(path, f"reading a 256x256x108 {array.dtype} volume needs about {needed:.1f} MiB "
                      f"of memory but only {needed - 0.5:.1f} MiB is available; crop or "
                      f"downsample"):
        read_volume(path, **options)
    monkeypatch.setenv("VOLUMEEVM_MEMORY_LIMIT", f"{needed + 0.5:.1f}M")
    np.testing.assert_array_equal(read_volume(path, **options).array, array)


def test_import_memory_estimate_bounds_the_peak(tmp_path, data_dir, monkeypatch):
    # The estimate is a close upper bound of what each reader allocates (tracemalloc).
    import tracemalloc

    import nibabel as nib

    from volumeevm_addon.readers import _checks

    array, _ = load(data_dir, "ct_head_invesalius")
    files = {"ct.nii.gz": None, "scaled.nii.gz": (2.5, -10.0), "ct.nrrd": None}
    estimates = []
    original = _checks.check_memory
    def spy(needed, *args, **kwargs):
        estimates.append(needed)
        return original(needed, *args, **kwargs)

    monkeypatch.setattr(_checks, "check_memory", spy)
    for name, scaling in files.items():
        path = tmp_path / name
        if name.endswith(".nii.gz"):
            img = nib.Nifti1Image(array, np.eye(4))
            if scaling:
                img.header.set_slope_inter(*scaling)
            nib.save(img, path)
        else:
            write_nrrd(path, array, {}, compression_level=1)  # gzip encoding
        tracemalloc.start()
        try:
            read_volume(path)
            peak = tracemalloc.get_traced_memory()[1]
        finally:
            tracemalloc.stop()
        assert peak <= estimates[-1] <= peak * 1.1 + (1 << 20), (name, peak, estimates[-1])
