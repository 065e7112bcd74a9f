"""Conformance: every volume file other projects ship for their own tests, read two ways.

The files are those inside the packages the tests already install (nibabel's ``tests/data`` and
``nicom/tests/data``, pydicom's ``data/test_files``, scikit-image's ``data``) and the 3D Slicer
files of the shared data (``slicer/``, from slicerio); pynrrd's wheel ships no test data. Every
file whose name ``read_volume`` claims is read in its place (a ``.dcm`` with its folder, as a
user would open it; nibabel's gzipped scanner files, ``.dcm.gz``, unzipped together into one
folder) and with the format's reference library (nibabel, pynrrd, pydicom,
tifffile). Each must end in one of:

- ``exact``: the same values and dtype, and the same geometry, as the reference library gives;
- ``refused``: a ``VolumeEVMError`` whose message starts with the file or a file of its folder.

Anything else (another exception, a read the reference disagrees with or cannot confirm) is a
failure. The table of every file and its outcome is printed (``pytest -s``). New readers add
their reference here when they land.
"""

import gzip
import importlib
import re
import warnings
from collections import Counter
from pathlib import Path

import numpy as np

from reader_files import DATA, assert_same_as_nibabel
from volumeevm_addon import VolumeEVMError
from volumeevm_addon.readers import SUPPORTED_EXTENSIONS, read_volume

#: (package, folder inside it) of the test files other projects ship.
SOURCES = [("nibabel", "tests/data"), ("nibabel", "nicom/tests/data"),
           ("pydicom", "data/test_files"), ("skimage", "data")]

#: Sign per space axis that maps a NRRD space to LPS (the reference's own table).
NRRD_TO_LPS = {"left-posterior-superior": (1, 1, 1), "right-anterior-superior": (-1, -1, 1),
               "left-anterior-superior": (1, -1, 1)}


def conformance_files(unzipped):
    """``(source, path)`` of every file with an extension ``read_volume`` claims, except raw
    data (``.raw``, ``.bin``: not self-describing, its layout is the caller's options);
    ``.dcm.gz`` files are unzipped into the folder ``unzipped``."""
    found = []
    for package, folder in SOURCES:
        root = Path(importlib.import_module(package).__file__).parent / folder
        found += [(f"{package}/{folder}", path) for path in sorted(root.iterdir())]
        for path in sorted(root.glob("*.dcm.gz")):
            unzipped.mkdir(exist_ok=True)
            target = unzipped / path.name.removesuffix(".gz")
            target.write_bytes(gzip.decompress(path.read_bytes()))
            found.append((f"{package}/{folder}", target))
    found += [("shared/data/slicer", path) for path in sorted((DATA / "slicer").iterdir())]
    return [(source, path) for source, path in found
            if path.is_file() and path.name.lower().endswith(tuple(REFERENCES))]


def assert_same_array(vol, data):
    """The same values and type (byte order aside: the reader returns native order)."""
    assert vol.array.dtype == data.dtype.newbyteorder("=")
    np.testing.assert_array_equal(vol.array, data)


def assert_geometry(vol, spacing, origin, orientation):
    np.testing.assert_allclose(vol.spacing, spacing, rtol=1e-6)
    np.testing.assert_allclose(vol.origin, origin, rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(vol.orientation, orientation, atol=1e-6)


def check_nifti(vol, path):
    import nibabel as nib

    img = nib.load(path)
    data = np.asanyarray(img.dataobj)
    data = data.reshape(data.shape[:3] + tuple(n for n in data.shape[3:] if n != 1))
    assert_same_array(vol, data)
    unit = img.header.get_xyzt_units()[0]
    scale = {"unknown": 1.0, "mm": 1.0, "meter": 1000.0, "micron": 1e-3}[unit]
    lps = np.diag([-1.0, -1.0, 1.0]) @ img.affine[:3] * scale
    steps = lps[:, :3]
    spacing = np.linalg.norm(steps, axis=0)
    assert_geometry(vol, spacing, lps[:, 3], steps / spacing)


def check_nrrd(vol, path):
    import nrrd

    data, header = nrrd.read(str(path))
    directions = header["space directions"]
    if vol.layers is None:
        assert_same_array(vol, data)
    else:  # a Slicer segmentation in layers: each layer's labels, moved by one offset per layer
        assert len(vol.layers) == len(data)
        for layer, reference in zip(vol.layers, data):
            inside = reference > 0
            np.testing.assert_array_equal(layer > 0, inside)
            assert len(np.unique(layer[inside].astype(np.int64) - reference[inside])) == 1
        directions = directions[1:]
    assert "space units" not in header or set(header["space units"]) == {"mm"}
    sign = np.array(NRRD_TO_LPS[header["space"]]) if "space" in header else np.ones(3)
    spacing = np.linalg.norm(directions, axis=1)
    assert_geometry(vol, spacing, header.get("space origin", np.zeros(3)) * sign,
                    (directions * sign).T / spacing)


def check_dicom(vol, path):
    """The chosen file's slice of the volume against pydicom's reading of that file; an
    enhanced multi-frame or mosaic file against nibabel's reading of it."""
    import pydicom

    ds = pydicom.dcmread(path)
    if "PerFrameFunctionalGroupsSequence" in ds or "MOSAIC" in ds.get("ImageType", []):
        groups = ds.PerFrameFunctionalGroupsSequence[0] if "NumberOfFrames" in ds else ds
        rescale = groups.get("PixelValueTransformationSequence", [ds])[0]
        assert float(rescale.get("RescaleIntercept", 0)) == 0
        assert_same_as_nibabel(vol, path, float(rescale.get("RescaleSlope", 1)))
        return
    pixels = ds.pixel_array.T
    slope, intercept = float(ds.get("RescaleSlope", 1)), float(ds.get("RescaleIntercept", 0))
    if (slope, intercept) != (1.0, 0.0):
        pixels = pixels * slope + intercept
    z = vol.orientation[:, 2]
    k = int(round((np.asarray(ds.ImagePositionPatient, float) - vol.origin) @ z
                  / vol.spacing[2]))
    assert 0 <= k < vol.array.shape[2]
    np.testing.assert_array_equal(vol.array[:, :, k], pixels)
    iop = np.asarray(ds.ImageOrientationPatient, float)
    np.testing.assert_allclose(vol.orientation[:, :2], iop.reshape(2, 3).T, atol=1e-4)
    np.testing.assert_allclose(vol.spacing[:2], np.asarray(ds.PixelSpacing, float)[::-1])
    np.testing.assert_allclose(vol.origin + k * vol.spacing[2] * z, ds.ImagePositionPatient,
                               atol=1e-3)


def check_tiff(vol, path):
    import tifffile

    data = tifffile.imread(path).T
    assert_same_array(vol, data)


def check_npy(vol, path):
    data = np.load(path, allow_pickle=False)
    assert_same_array(vol, data)


REFERENCES = {".npy": check_npy, ".nii": check_nifti, ".nii.gz": check_nifti, ".nrrd": check_nrrd,
              ".nhdr": check_nrrd, ".dcm": check_dicom, ".tif": check_tiff, ".tiff": check_tiff}


def outcome(path):
    """``(class, detail)`` of reading ``path`` (see the module notes)."""
    ending = next(e for e in REFERENCES if path.name.lower().endswith(e))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            vol = read_volume(path)
        except VolumeEVMError as exc:
            message = str(exc)
            named = re.match(rf"{re.escape(str(path.parent))}/[^:]+", message)
            if not named:
                return "FAILURE", f"the message does not start with the file: {message[:200]}"
            return "refused", message[named.end():].lstrip(": ").splitlines()[0][:90]
        except Exception as exc:  # noqa: BLE001 - the point of the suite: nothing else escapes
            return "FAILURE", f"{type(exc).__name__} escaped: {exc}"[:300]
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            REFERENCES[ending](vol, path)
    except Exception as exc:  # noqa: BLE001 - a mismatch or a reference that cannot confirm
        return "FAILURE", f"read {vol.array.shape} but the reference disagrees: {exc}"[:300]
    shape = "x".join(map(str, vol.array.shape))
    note = f", {len(caught)} warning(s)" if caught else ""
    return "exact", f"{shape} {vol.array.dtype}{note}"


def test_every_self_describing_format_has_a_reference():
    assert set(SUPPORTED_EXTENSIONS) - set(REFERENCES) == {".raw", ".bin", ".den"}


def test_other_projects_test_files(tmp_path):
    files = conformance_files(tmp_path / "nicom_gz")
    assert len(files) >= 90
    rows = [(source, path.name, *outcome(path)) for source, path in files]
    width = max(len(name) for _, name, _, _ in rows)
    print(f"\nreader conformance over {len(rows)} files of other projects:")
    for source, name, result, detail in rows:
        print(f"  {source:22} {name:{width}} {result:8} {detail}")
    counts = Counter((source, result) for source, _, result, _ in rows)
    print("  " + "; ".join(f"{source}: {result} {n}" for (source, result), n in
                           sorted(counts.items())))
    failures = [row for row in rows if row[2] == "FAILURE"]
    assert not failures, "\n".join(f"{s}/{n}: {d}" for s, n, _, d in failures)
    assert sum(row[2] == "exact" for row in rows) >= 20
