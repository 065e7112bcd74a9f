"""Tests for ``volumeevm_addon.readers``: real volumes written with each format's reference
library, read back, compared exactly; every bad-input path raises ``VolumeEVMError`` naming the
file and the problem."""

import copy
import json
import re
import shutil
import subprocess
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest

from volumeevm_addon._errors import VolumeEVMError
from volumeevm_addon.readers import SUPPORTED_EXTENSIONS, read_volume

pytestmark = pytest.mark.filterwarnings("error")

REPO = Path(__file__).resolve().parents[1]


# ---------------------------------------------------------------------------------------------
# helpers


def load(data_dir, name):
    """A real volume ``[x, y, z]`` and its JSON metadata from the shared data folder."""
    meta = json.loads((data_dir / f"{name}.json").read_text())
    return np.load(data_dir / f"{name}.npy"), meta


@pytest.fixture(scope="module")
def ct_crop():
    """A non-cubic crop (64 x 48 x 12) of the real CT head in HU, int16: skull and air."""
    array = np.load(REPO.parent / "shared" / "data" / "ct_head_invesalius.npy")
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


def write_nrrd(path, array, header, **kwargs):
    """pynrrd's writer, silencing its own ``datetime.utcnow`` deprecation (Python 3.12+)."""
    import nrrd

    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", "datetime.datetime.utcnow", DeprecationWarning)
        nrrd.write(str(path), array, header, **kwargs)


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
        pytest.skip("Debian's libvolpack1-dev examples are not installed")
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
