"""Volume files written by the reference libraries, shared by the reader tests and fuzzers.

Each format is written as its own tools write it: a DICOM series cloned from pydicom's real
``CT_small.dcm``; TIFF stacks by tifffile in its plain, ImageJ and OME flavours; NRRD by pynrrd;
VolPack ``.den`` with brainsmall's header; NIfTI headers patched without repair. DICOM volumes
can be compared with nibabel's own DICOM reading (:func:`assert_same_as_nibabel`).
"""

import copy
import io
import warnings
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
DATA = REPO.parent / "shared" / "data"  # the real volumes (../shared/data beside the repo)

#: Voxel size (mm) and the centre of voxel (0, 0, 0) (mm, LPS) of the written DICOM series.
SPACING = (0.5, 0.75, 1.25)
ORIGIN = np.array([-16.0, -20.5, 42.0])


def write_series(folder, hu, edit=None):
    """Write ``hu`` (``(X, Y, Z)`` int16) as an axial CT series cloned from pydicom's CT_small.

    Stored values are HU + 1024 with intercept -1024; slice ``k`` is ``IM000k.dcm`` at
    ``ORIGIN + k * 1.25 mm`` along z. ``edit(k, ds)`` may change a slice's dataset before it is
    saved. Returns the files in slice order.
    """
    import pydicom
    from pydicom.data import get_testdata_file
    from pydicom.uid import generate_uid

    folder.mkdir(exist_ok=True)
    template = pydicom.dcmread(get_testdata_file("CT_small.dcm"))
    uid = generate_uid()
    files = []
    for k in range(hu.shape[2]):
        ds = copy.deepcopy(template)
        ds.SeriesInstanceUID = uid
        ds.SOPInstanceUID = generate_uid()
        ds.file_meta.MediaStorageSOPInstanceUID = ds.SOPInstanceUID
        ds.InstanceNumber = k + 1
        ds.Rows, ds.Columns = hu.shape[1], hu.shape[0]
        ds.PixelSpacing = [SPACING[1], SPACING[0]]
        ds.ImageOrientationPatient = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0]
        ds.ImagePositionPatient = [float(v) for v in ORIGIN + [0, 0, k * SPACING[2]]]
        ds.RescaleSlope, ds.RescaleIntercept = 1, -1024
        ds.BitsAllocated, ds.BitsStored, ds.HighBit, ds.PixelRepresentation = 16, 16, 15, 1
        ds.PixelData = np.ascontiguousarray(hu[:, :, k].T + 1024, dtype="<i2").tobytes()
        if edit is not None:
            edit(k, ds)
        files.append(folder / f"IM{k:04d}.dcm")
        with warnings.catch_warnings():  # crafted invalid values make pydicom warn
            warnings.simplefilter("ignore")
            ds.save_as(files[-1], enforce_file_format=True)
    return files


def write_tiff(path, hu, kind):
    """Write ``hu`` as an uncompressed TIFF stack: ``plain``, ``imagej`` or ``ome``."""
    import tifffile

    if kind == "imagej":
        tifffile.imwrite(path, hu.T, imagej=True, resolution=(2.0, 4.0),
                         metadata={"spacing": 1.5, "unit": "mm", "axes": "ZYX"})
    elif kind == "ome":
        tifffile.imwrite(path, hu.T, ome=True, photometric="minisblack",
                         metadata={"axes": "ZYX", "PhysicalSizeX": 0.5, "PhysicalSizeY": 0.5,
                                   "PhysicalSizeZ": 2.0})
    else:
        tifffile.imwrite(path, hu.T, photometric="minisblack", metadata=None)
    return path


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


def assert_same_as_nibabel(vol, path, scale=1.0):
    """Voxel centres of ``vol`` (the corners and 20000 more) land on voxels of nibabel's reading
    of ``path`` (by the two affines) holding the same value (times ``scale``, which nibabel
    leaves out)."""
    import pydicom

    with warnings.catch_warnings():  # nibabel: "The DICOM readers are highly experimental"
        warnings.simplefilter("ignore")
        from nibabel.nicom import dicomwrappers

        wrapper = dicomwrappers.wrapper_from_data(pydicom.dcmread(path))
        data = wrapper.get_data()
    ours = np.eye(4)
    ours[:3, :3] = vol.orientation * np.array(vol.spacing)
    ours[:3, 3] = vol.origin
    shape = np.array(vol.array.shape)
    corners = np.array(np.meshgrid(*[[0, n - 1] for n in shape])).reshape(3, -1)
    index = np.hstack([corners, np.random.default_rng(5).integers(0, shape[:, None],
                                                                   (3, 20000))])
    world = ours[:3, :3] @ index + ours[:3, 3:]
    theirs = np.linalg.solve(wrapper.affine[:3, :3], world - wrapper.affine[:3, 3:])
    assert np.abs(theirs - np.round(theirs)).max() < 0.01
    theirs = tuple(np.round(theirs).astype(int))
    expected = data[theirs].astype(np.float32) * np.float32(scale)
    np.testing.assert_array_equal(vol.array[tuple(index)], expected.astype(vol.array.dtype))
    return data
