"""OME-Zarr stores (NGFF 0.4 on Zarr v2, 0.5 on Zarr v3) read lazily: exact data against the
array written, chunk by chunk, geometry from the coordinate transformations, and every kind of
bad store refused naming the store, level and chunk.

The stores are written by ``zarr_files.write_store`` (numcodecs-compressed chunks, as the Zarr
specifications lay them out) from the real CT head as a 3-level pyramid with 64³ chunks.
"""

import json
import re
import subprocess
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest

from volumeevm_addon import VolumeEVMError, read_volume, volume_levels
from zarr_files import chunk_files, pyramid, write_store


@pytest.fixture(scope="module")
def ct(data_dir):
    return np.load(data_dir / "ct_head_invesalius.npy")


@pytest.fixture(scope="module")
def stores(ct, tmp_path_factory):
    """One store per Zarr version and codec."""
    folder = tmp_path_factory.mktemp("stores")
    return {(version, codec): write_store(folder / f"v{version}_{codec}.ome.zarr", pyramid(ct, 3),
                                          version=version, codec=codec)
            for version in (2, 3) for codec in ("blosc", "zstd", "gzip", "raw")}


def raises(store, *parts):
    """``pytest.raises(VolumeEVMError)`` whose message starts with the store and holds
    ``parts`` (literally, in this order)."""
    pattern = f"^{_escape(store)}.*" + ".*".join(map(_escape, parts))
    return pytest.raises(VolumeEVMError, match=pattern)


def _escape(text):
    return re.escape(str(text))


@pytest.mark.parametrize("version", [2, 3])
@pytest.mark.parametrize("codec", ["blosc", "zstd", "gzip", "raw"])
def test_every_level_reads_exactly(stores, ct, version, codec):
    store = stores[version, codec]
    for level in range(3):
        volume = read_volume(store, level=level)
        expected = ct[::2 ** level, ::2 ** level, ::2 ** level]
        assert volume.array.shape == expected.shape
        computed = volume.array.compute()
        assert computed.dtype == ct.dtype and np.array_equal(computed, expected)
        assert volume.spacing == pytest.approx((0.957 * 2 ** level, 0.957 * 2 ** level,
                                                1.5 * 2 ** level))
        assert volume.spacing_known and volume.source == str(store)


def test_array_is_lazy_with_the_store_chunks(stores):
    store = stores[3, "zstd"]
    volume = read_volume(store)
    # x, y, z chunks: the store's 64³ (z, y, x) chunks, the last ones cut by the grid
    assert volume.array.chunks == ((64,) * 4, (64,) * 4, (64, 44))
    # Nothing is read when the volume is opened: with every chunk file unreadable as data,
    # opening still works and computing names the first chunk it decodes.
    broken = store.parent / "broken.ome.zarr"
    subprocess.run(["cp", "-r", str(store), str(broken)], check=True)
    for path in chunk_files(broken):
        path.write_bytes(b"not zstd")
    lazy = read_volume(broken)
    with raises(broken, "level 0 (0)", "chunk (", "cannot be decoded by zstd"):
        lazy.array.compute()


def test_levels_listed(stores, ct):
    levels = volume_levels(stores[2, "blosc"])
    assert [lv["shape"] for lv in levels] == [(256, 256, 108), (128, 128, 54), (64, 64, 27)]
    assert [lv["bytes"] for lv in levels] == [256 * 256 * 108 * 2, 128 * 128 * 54 * 2,
                                              64 * 64 * 27 * 2]
    assert levels[1]["spacing"] == pytest.approx((1.914, 1.914, 3.0))
    assert [lv["level"] for lv in levels] == [0, 1, 2]
    assert levels[0]["chunks"] == (64, 64, 64) and levels[0]["dtype"] == "int16"
    assert volume_levels(stores[3, "gzip"]) == [dict(lv) for lv in levels]


@pytest.mark.parametrize("version", [2, 3])
def test_channels_times_units_and_translation(tmp_path, ct, version):
    small = ct[:100, :90, :40]
    frames = np.stack([np.stack([(small.transpose(2, 1, 0) + 10 * t + c).astype(np.int16)
                                 for c in range(2)]) for t in range(3)])
    store = write_store(tmp_path / "tc.zarr", [frames], version=version, axes="tczyx",
                        chunks=(16, 32, 64), spacing_zyx=(2.0, 0.5, 0.25),
                        translation_zyx=(30.0, 20.0, 10.0), unit="micrometer")
    volume = read_volume(store, channel=1, time=2)
    assert np.array_equal(volume.array.compute(), small + 21)
    assert volume.spacing == pytest.approx((0.25e-3, 0.5e-3, 2e-3))
    assert volume.origin == pytest.approx((10e-3, 20e-3, 30e-3))
    assert np.array_equal(read_volume(store).array.compute(), small)
    with raises(store, "channel=2 is not one of 0 .. 1"):
        read_volume(store, channel=2)
    with raises(store, "time=-1"):
        read_volume(store, time=-1)
    plain = write_store(tmp_path / "zyx.zarr", [small.transpose(2, 1, 0)], version=version,
                        unit=None)
    volume = read_volume(plain)
    assert not volume.spacing_known and volume.spacing == pytest.approx((0.957, 0.957, 1.5))
    with raises(plain, "channel=1", "no channel axis"):
        read_volume(plain, channel=1)


@pytest.mark.parametrize("version", [2, 3])
def test_missing_chunk_is_the_fill_value(tmp_path, ct, version):
    small = ct[:70, :70, :70].transpose(2, 1, 0)
    store = write_store(tmp_path / "s.zarr", [small], version=version, chunks=(32, 32, 32),
                        fill_value=-7, skip={(0, (1, 0, 2))})
    expected = small.copy()
    expected[32:64, 0:32, 64:70] = -7
    assert np.array_equal(read_volume(store).array.compute(), expected.transpose(2, 1, 0))


def test_separators_and_big_endian(tmp_path, ct):
    small = ct[:50, :40, :30].transpose(2, 1, 0)
    for version, separator in ((2, "/"), (3, ".")):
        store = write_store(tmp_path / f"s{version}.zarr", [small], version=version,
                            chunks=(16, 16, 16), separator=separator)
        assert np.array_equal(read_volume(store).array.compute(), small.transpose(2, 1, 0))
    store = write_store(tmp_path / "big.zarr", [small], version=3, chunks=(16, 16, 16), codec="raw")
    meta = json.loads((store / "0" / "zarr.json").read_text())
    meta["codecs"][0]["configuration"]["endian"] = "big"
    (store / "0" / "zarr.json").write_text(json.dumps(meta))
    for path in chunk_files(store):
        path.write_bytes(np.frombuffer(path.read_bytes(), "<i2").astype(">i2").tobytes())
    computed = read_volume(store).array.compute()
    assert computed.dtype == np.dtype("=i2") and np.array_equal(computed, small.transpose(2, 1, 0))


# ------------------------------------------------------------------------------------- bad stores

@pytest.fixture
def small_store(tmp_path, ct):
    def make(version=2, codec="zstd", **options):
        return write_store(tmp_path / f"bad{version}.ome.zarr", pyramid(ct[:80, :80, :40], 2),
                           version=version, codec=codec, chunks=(32, 32, 32), **options)
    return make


def _edit(path, change):
    meta = json.loads(path.read_text())
    change(meta)
    path.write_text(json.dumps(meta))


@pytest.mark.parametrize("version", [2, 3])
def test_truncated_and_wrong_size_chunks_refused(small_store, version):
    store = small_store(version)
    victim = chunk_files(store)[3]
    victim.write_bytes(victim.read_bytes()[:-5])
    with raises(store, "level 0 (0), chunk (", "cannot be decoded by zstd"):
        read_volume(store).array.compute()


@pytest.mark.parametrize("version", [2, 3])
def test_raw_chunk_of_wrong_length_refused(tmp_path, ct, version):
    store = write_store(tmp_path / "r.zarr", [ct[:40, :40, :40].transpose(2, 1, 0)],
                        version=version, codec="raw", chunks=(32, 32, 32))
    victim = chunk_files(store)[0]
    victim.write_bytes(victim.read_bytes()[:-2])
    with raises(store, "chunk (0, 0, 0)", "decodes to 65534 bytes", "65536"):
        read_volume(store).array.compute()
    victim.write_bytes(b"\0" * (65536 + (1 << 16) + 1))
    with raises(store, "chunk (0, 0, 0)", "more than a chunk"):
        read_volume(store).array.compute()


def test_codec_not_installed_refused(small_store):
    store = small_store(2)
    _edit(store / "1" / ".zarray", lambda m: m.update(compressor={"id": "nosuchcodec"}))
    with raises(store, "level 1 (1)", "codec 'nosuchcodec' is not installed"):
        read_volume(store)
    store3 = small_store(3)
    _edit(store3 / "0" / "zarr.json", lambda m: m["codecs"].append({"name": "sharding_indexed"}))
    with raises(store3, "level 0 (0)", "sharding_indexed", "not supported"):
        volume_levels(store3)


def test_inconsistent_levels_refused(small_store):
    store = small_store(3)
    _edit(store / "1" / "zarr.json", lambda m: m.update(shape=[20, 30, 40]))
    with raises(store, "level 1 (1)", "level 0 covers"):
        read_volume(store)


@pytest.mark.parametrize("version", [2, 3])
def test_bad_axes_and_units_refused(small_store, version):
    store = small_store(version)
    attrs = store / (".zattrs" if version == 2 else "zarr.json")

    def scales(meta):
        return (meta if version == 2 else meta["attributes"]["ome"])["multiscales"][0]

    _edit(attrs, lambda m: scales(m)["axes"].reverse())
    with raises(store, "axes x, y, z are not supported", "zyx, czyx, tczyx"):
        read_volume(store)
    _edit(attrs, lambda m: scales(m)["axes"].reverse())
    _edit(attrs, lambda m: scales(m)["axes"][1].update(unit="parsec"))
    with raises(store, "axis y has unit 'parsec'"):
        read_volume(store)
    _edit(attrs, lambda m: scales(m)["axes"][1].update(unit="millimeter", type="time"))
    with raises(store, "axis y has type 'time'"):
        read_volume(store)
    _edit(attrs, lambda m: scales(m)["axes"][1].update(type="space"))
    _edit(attrs, lambda m: scales(m)["datasets"][0]["coordinateTransformations"][0].update(
        scale=[1.0, -2.0, 1.0]))
    with raises(store, "level 0 (0)", "scale [1.0, -2.0, 1.0] must be positive"):
        read_volume(store)


@pytest.mark.parametrize("version", [2, 3])
def test_bad_json_wrong_dtypes_and_huge_shapes_refused(small_store, version):
    store = small_store(version)
    array = store / "0" / (".zarray" if version == 2 else "zarr.json")
    text = array.read_text()
    array.write_text(text[:-3])
    with raises(store, "is not valid JSON"):
        read_volume(store)
    key = "dtype" if version == 2 else "data_type"
    for dtype in (["|O", "<c8", "|b1", "<U4"] if version == 2 else ["complex64", "bool", "x"]):
        array.write_text(text)
        _edit(array, lambda m: m.update({key: dtype}))
        with raises(store, "level 0 (0)", "data type"):
            read_volume(store)
    for shape in ([2 ** 40, 80, 80], [0, 80, 80], [80.5, 80, 80], [80, 80]):
        array.write_text(text)
        _edit(array, lambda m: m.update(shape=shape))
        with pytest.raises(VolumeEVMError, match=f"^{_escape(store)}"):
            read_volume(store)
    array.write_text(text)
    if version == 2:
        _edit(array, lambda m: m.update(chunks=[4096, 4096, 4096]))
    else:
        _edit(array, lambda m: m["chunk_grid"]["configuration"].update(
            chunk_shape=[4096, 4096, 4096]))
    with raises(store, "decoding one chunk needs about 256.0 GiB"):
        read_volume(store)  # refused before allocating anything


def test_not_a_store_refused(tmp_path):
    (tmp_path / "empty.zarr").mkdir()
    with raises(tmp_path / "empty.zarr", "not an OME-Zarr store"):
        read_volume(tmp_path / "empty.zarr")
    (tmp_path / "file.zarr").write_bytes(b"x")
    with raises(tmp_path / "file.zarr", "an OME-Zarr store is a folder"):
        read_volume(tmp_path / "file.zarr")
    group = tmp_path / "nogroup.zarr"
    group.mkdir()
    (group / ".zattrs").write_text("{}")
    with raises(group, "no OME-NGFF 'multiscales'"):
        volume_levels(group)


def test_importing_needs_neither_dask_nor_numcodecs():
    code = ("import sys, volumeevm_addon; "
            "print([m for m in ('dask', 'numcodecs') if m in sys.modules])")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True, cwd=Path(__file__).parents[1])
    assert out.stdout.strip() == "[]"


# ------------------------------------------------------------------------------------- fuzz

SEED = 20261128


@pytest.mark.parametrize("version", [2, 3])
def test_fuzz_metadata_and_chunks(small_store, ct, version):
    """Mutated metadata and chunk files: each read gives the original data, other data of the
    right shape (a flipped free number or an uncompressed voxel; blosc and zstd frames carry no
    checksum) or a VolumeEVMError naming the store; never another exception."""
    store = small_store(version, codec="gzip")
    expected = ct[:80, :80, :40]
    rng = np.random.default_rng(SEED + version)
    files = [store / "0" / (".zarray" if version == 2 else "zarr.json"),
             store / (".zattrs" if version == 2 else "zarr.json"), *chunk_files(store)[:4]]
    outcomes = {"exact": 0, "refused": 0, "changed": 0}
    for path in files:
        original = path.read_bytes()
        cases = [original[:n] for n in rng.integers(0, len(original), 8)]
        for offset in rng.integers(0, len(original), 25):
            flipped = bytearray(original)
            flipped[offset] ^= 1 << int(rng.integers(8))
            cases.append(bytes(flipped))
        for case in cases:
            path.write_bytes(case)
            try:
                data = read_volume(store).array.compute()
            except VolumeEVMError as error:
                assert str(error).startswith(str(store)), error
                outcomes["refused"] += 1
                continue
            same = data.shape == expected.shape and np.array_equal(data, expected)
            outcomes["exact" if same else "changed"] += 1
            # gzip chunks carry a CRC: a changed chunk file never reads as other data
            assert same or path.name in (".zarray", ".zattrs", "zarr.json"), path
        path.write_bytes(original)
    print(version, outcomes)
    assert outcomes["refused"] > 0 and outcomes["exact"] > 0


@pytest.mark.parametrize("version", [2, 3])
def test_a_label_image_is_a_label_map_with_its_colours(tmp_path, data_dir, version):
    """A store whose group says ``image-label`` (NGFF 0.4 and 0.5) reads as a label map with
    its colours and the names its properties give, lazily; a colour for an absent label warns;
    ``labels=True`` keeps them, ``labels=False`` reads the values (without the labels' pass);
    bad colours are refused naming the store and the entry."""
    liver = np.load(data_dir / "seg_liver_cgal.npy")[150:278, 100:196, 60:108]
    present = sorted(set(np.unique(liver).tolist()) - {0})
    colors = [{"label-value": label, "rgba": [255, 10 * k, 0, 255]}
              for k, label in enumerate(present)] + [{"label-value": 9, "rgba": [1, 2, 3, 4]}]
    image_label = {"version": "0.4", "colors": colors,
                   "properties": [{"label-value": present[0], "name": "vessel"}]}
    store = write_store(tmp_path / "seg.zarr", pyramid(liver, 2), version=version,
                        chunks=(16, 32, 32), attributes={"image-label": image_label})
    with pytest.warns(UserWarning, match=r"names labels the data does not have: \[9\]"):
        vol = read_volume(store)
    assert vol.is_label_map and not isinstance(vol.array, np.ndarray)
    assert sorted(vol.labels) == present
    assert vol.labels[present[0]].name == "vessel"
    assert vol.labels[present[1]].name == f"label {present[1]}"
    assert vol.labels[present[1]].color == (1.0, round(10 / 255, 6), 0.0)
    with pytest.warns(UserWarning):
        assert read_volume(store, labels=True).labels == vol.labels
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no pass over the labels, hence no warning
        assert not read_volume(store, labels=False).is_label_map
    for entry, message in (({"label-value": 1, "rgba": [1, 2, 3]}, "colors[0]: rgba must be 4"),
                           ({"label-value": -1, "rgba": [1, 2, 3, 4]}, "label-value must be"),
                           ("red", "colors[0] is not an object")):
        bad = write_store(tmp_path / f"bad{len(message)}.zarr", [liver], version=version,
                          attributes={"image-label": {"colors": [entry]}})
        with raises(bad, "image-label", message):
            read_volume(bad)


def test_a_label_store_is_a_label_map_found_chunk_by_chunk(tmp_path, data_dir):
    """``labels=True`` on a store: its labels found one chunk at a time (the array stays lazy),
    the same as in memory; a negative label in one chunk is refused naming the store."""
    liver = np.load(data_dir / "seg_liver_cgal.npy")[150:278, 100:196, 60:108]
    store = write_store(tmp_path / "liver.zarr", pyramid(liver, 2), chunks=(16, 32, 32))
    chunk_files(store, 1)[0].write_bytes(b"")  # level 1 is never read for level 0
    vol = read_volume(store, labels=True)
    assert vol.is_label_map and not isinstance(vol.array, np.ndarray)
    present = sorted(set(np.unique(liver).tolist()) - {0})
    assert sorted(vol.labels) == present and len(present) >= 2
    signed = liver.astype(np.int16)
    signed[100, 50, 40] = -1
    bad = write_store(tmp_path / "signed.zarr", pyramid(signed, 1), chunks=(16, 32, 32))
    with raises(bad, "negative"):
        read_volume(bad, labels=True)
