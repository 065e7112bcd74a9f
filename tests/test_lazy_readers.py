"""Lazy reading of NIfTI, NRRD, VolPack .den and TIFF (``read_volume(path, lazy=True)``).

Each file is read twice, whole and lazily with chunks made small so a real volume spans several:
the lazy array must be a Dask array that has read nothing yet, equal the eager one value for
value (dtype, byte order, scaling, geometry), and build exactly the same VolumeEVM chunk by
chunk. What cannot be mapped (compressed streams, a segmentation in layers) is refused with
the file named; damage found while a lazy TIFF chunk is decoded names the file and its pages.
"""

import gzip

import numpy as np
import pytest

from reader_files import patch_nifti, write_den, write_nrrd, write_tiff
from skips import required_module, skip_unless_ci
from volumeevm_addon import VolumeEVM, VolumeEVMError, read_volume
from volumeevm_addon.readers import _checks


@pytest.fixture
def small_chunks(monkeypatch):
    """Chunks of a few planes, so every test volume is read in several."""
    monkeypatch.setattr(_checks, "LAZY_CHUNK_BYTES", 40_000)
    from volumeevm_addon.readers import _tiff

    monkeypatch.setattr(_tiff, "LAZY_CHUNK_BYTES", 40_000)


@pytest.fixture(scope="module")
def brain(data_dir):
    """The real MR brain (uint8, 256 x 256 x 109) cropped to a quick size."""
    brain = np.load(data_dir / "mr_brainsmall_volpack.npy")
    return np.ascontiguousarray(brain[40:200, 50:190, 20:80])


@pytest.fixture(scope="module")
def head(data_dir):
    """A crop of the real CT head (int16, HU)."""
    head = np.load(data_dir / "ct_head_invesalius.npy")
    return np.ascontiguousarray(head[60:180, 50:170, 30:90])


def assert_same_volume(lazy, eager, threshold):
    """The lazy volume is unread Dask, equals the eager one, and builds the same VolumeEVM."""
    assert type(lazy.array).__module__.startswith("dask")
    assert len(lazy.array.chunks[0]) * len(lazy.array.chunks[1]) * len(lazy.array.chunks[2]) > 1
    values = np.asarray(lazy.array)
    assert values.dtype == eager.array.dtype and values.dtype.isnative
    np.testing.assert_array_equal(values, eager.array)
    for name in ("spacing", "origin", "units", "spacing_known", "source"):
        assert getattr(lazy, name) == getattr(eager, name), name
    np.testing.assert_array_equal(lazy.orientation, eager.orientation)
    got = VolumeEVM.from_volume(lazy, threshold)
    expected = VolumeEVM.from_volume(eager, threshold)
    np.testing.assert_array_equal(got.evm.vertices, expected.evm.vertices)
    assert got.table(0).dtype == expected.table(0).dtype
    np.testing.assert_array_equal(got.table(0), expected.table(0))
    assert got.voxel_count == expected.voxel_count > 0


@pytest.mark.parametrize("scaled", [False, True])
@pytest.mark.parametrize("order", ["<", ">"])
def test_nifti_lazily(tmp_path, head, small_chunks, scaled, order):
    nib = required_module("nibabel")
    image = nib.Nifti1Image(head.astype(f"{order}i2"), np.diag([0.9, 0.8, 1.5, 1.0]))
    path = tmp_path / "head.nii"
    image.to_filename(path)
    if scaled:  # slope and intercept: float64 values, per chunk as nibabel gives them whole
        path.write_bytes(patch_nifti(path.read_bytes(), scl_slope=0.5, scl_inter=-3.0))
    eager = read_volume(path)
    assert eager.array.dtype == (np.float64 if scaled else np.int16)
    assert_same_volume(read_volume(path, lazy=True), eager, 100.0)


def test_compressed_nifti_refused_lazily(tmp_path, head):
    nib = required_module("nibabel")
    path = tmp_path / "head.nii.gz"
    nib.Nifti1Image(head, np.eye(4)).to_filename(path)
    with pytest.raises(VolumeEVMError, match=r"head\.nii\.gz: lazy=True needs uncompressed"):
        read_volume(path, lazy=True)


@pytest.mark.parametrize("detached", [False, True])
def test_nrrd_raw_lazily(tmp_path, head, small_chunks, detached):
    header = {"space": "left-posterior-superior", "endian": "big",
              "space directions": np.diag([0.9, 0.8, 1.5]), "space origin": [1.0, 2.0, 3.0],
              "encoding": "raw"}
    path = tmp_path / ("head.nhdr" if detached else "head.nrrd")
    write_nrrd(path, head, header, detached_header=detached)
    assert_same_volume(read_volume(path, lazy=True), read_volume(path), 100.0)


def test_compressed_nrrd_refused_lazily(tmp_path, head):
    path = tmp_path / "head.nrrd"
    write_nrrd(path, head, {"encoding": "gzip"})
    with pytest.raises(VolumeEVMError, match=r"head\.nrrd: lazy=True needs raw data.*gzip"):
        read_volume(path, lazy=True)


def test_layered_segmentation_refused_lazily(data_dir):
    layered = [p for p in (data_dir / "slicer").glob("*.seg.nrrd")
               if read_volume(p).layers is not None]
    if not layered:
        skip_unless_ci("no segmentation in layers among the Slicer samples")
    with pytest.raises(VolumeEVMError, match="lazy=True needs raw data in one layer"):
        read_volume(layered[0], lazy=True)


@pytest.mark.parametrize("order", ["<", ">"])
def test_den_lazily(tmp_path, brain, small_chunks, order):
    path = tmp_path / "brain.den"
    write_den(path, brain, order)
    assert_same_volume(read_volume(path, lazy=True), read_volume(path), 60.0)


@pytest.mark.parametrize("kind", ["plain", "imagej", "ome", "zlib"])
def test_tiff_lazily(tmp_path, head, small_chunks, kind):
    path = tmp_path / ("head.ome.tif" if kind == "ome" else "head.tif")
    if kind == "zlib":
        import tifffile

        tifffile.imwrite(path, head.T, compression="zlib")
    else:
        write_tiff(path, head, kind)
    assert_same_volume(read_volume(path, lazy=True), read_volume(path), 100.0)


def test_damaged_tiff_page_named_when_computed(tmp_path, head, small_chunks):
    import tifffile

    path = tmp_path / "head.tif"
    tifffile.imwrite(path, head.T, compression="zlib")
    volume = read_volume(path, lazy=True)  # checks the structure; decodes nothing
    data = bytearray(path.read_bytes())
    with tifffile.TiffFile(path) as tif:  # scramble the compressed data of the last page
        page = tif.pages[len(tif.pages) - 1]
        start, count = page.dataoffsets[0], page.databytecounts[0]
    data[start:start + count] = gzip.compress(b"not the page")[:count].ljust(count, b"\0")
    path.write_bytes(bytes(data))
    with pytest.raises(VolumeEVMError, match=r"head\.tif: pages \d+-59"):
        np.asarray(volume.array)



def test_dicom_takes_no_lazy_option(tmp_path, head):
    from reader_files import write_series

    write_series(tmp_path / "series", head[:, :, :4])
    with pytest.raises(TypeError):
        read_volume(tmp_path / "series", lazy=True)
