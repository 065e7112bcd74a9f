""".vevm files: every member and the metadata checked before anything is built; saves that never
replace a file unasked, even one that appears while they write; file-system errors as
VolumeEVMError naming the path.

The helpers that write archives by hand and rewrite good files live in ``vevm_helpers.py``,
shared with ``test_fuzz_vevm.py``.
"""

import errno
import os
import tempfile
import threading
import tracemalloc
import zipfile
import zlib

import numpy as np
import pytest

from skips import skip_unless_ci
from vevm_helpers import (
    assert_same,
    crafted_npy,
    ct_crop,
    deflate_zeros,
    members_of,
    npy_bytes,
    raw_entries,
    raw_zip,
    refused,
    region_change,
    sha,
    synthetic,
    write_vevm_members,
)
from volumeevm_addon import VolumeEVM, VolumeEVMError, write_png
from volumeevm_addon.model import _volumeevm
from volumeevm_addon.system import write_atomically


# ---------------------------------------------------------------------- fixtures
@pytest.fixture(scope="module")
def small():
    return synthetic()


@pytest.fixture
def good(tmp_path, small):
    path = tmp_path / "good.vevm"
    small.save(path)
    return path


# ---------------------------------------------------------------------- loading: what is accepted
@pytest.mark.parametrize("which", ["synthetic", "ct"])
def test_round_trip_is_exact(tmp_path, data_dir, which):
    original = synthetic() if which == "synthetic" else ct_crop(data_dir)
    path = tmp_path / f"{which}.vevm"
    original.save(path)
    assert_same(VolumeEVM.load(path), original)
    assert_same(VolumeEVM.load(os.fsencode(path)), original)  # a bytes path too


def test_deflated_and_big_endian_members_load_exactly(tmp_path, good, small):
    arrays, meta = members_of(good)
    arrays["table"] = arrays["table"].astype(">f4")  # as a big-endian machine writes it
    path = tmp_path / "deflated.vevm"
    write_vevm_members(path, arrays, meta, compression=zipfile.ZIP_DEFLATED)
    loaded = VolumeEVM.load(path)
    assert loaded.table(0).dtype == np.dtype("=f4")
    assert_same(loaded, small)


# ---------------------------------------------------------------------- loading: the archive
def test_not_a_regular_file_is_refused_without_blocking(tmp_path):
    fifo = tmp_path / "pipe.vevm"
    os.mkfifo(fifo)
    outcome = []

    def load():
        try:
            VolumeEVM.load(fifo)
        except VolumeEVMError as error:
            outcome.append(str(error))

    reader = threading.Thread(target=load)
    reader.start()
    reader.join(10)
    if reader.is_alive():  # unblock the reader before failing
        with open(fifo, "wb"):
            pass
        pytest.fail("loading a FIFO blocked")
    assert outcome == [f"{fifo}: is not a regular file (a pipe or a device), not a VolumeEVM file"]
    refused(tmp_path, "is a folder")
    refused(tmp_path / "missing.vevm", "file not found")


@pytest.mark.parametrize("change, match", [
    ("drop table", r"missing \['table.npy'\]"),
    ("add extra", r"unexpected or repeated \['extra.npy'\]"),
    ("repeat table", r"unexpected or repeated \['table.npy'\]"),
    ("encrypt table", "member 'table' is encrypted"),
    ("bzip2 table", "compression method 12"),
])
def test_members_must_be_exactly_the_five(tmp_path, good, change, match):
    entries = raw_entries(good)
    table = next(e for e in entries if e["name"] == "table")
    if change == "drop table":
        entries.remove(table)
    elif change == "add extra":
        entries.append({"name": "extra", "payload": npy_bytes(np.arange(3))})
    elif change == "repeat table":
        entries.append(dict(table))
    elif change == "encrypt table":
        table["flags"] = 0x1
    else:
        table["method"] = 12
    path = tmp_path / "bad.vevm"
    raw_zip(path, entries)
    refused(path, match)


def test_object_member_is_refused_never_unpickled(tmp_path, good):
    marker = tmp_path / "unpickled"
    arrays, meta = members_of(good)
    arrays["meta"] = np.array([Unpickled(str(marker))], dtype=object)
    path = tmp_path / "pickled.vevm"
    write_vevm_members(path, arrays)
    refused(path, r"member 'meta' holds Python objects \(dtype object\), which are never unpickled")
    assert not marker.exists()


class Unpickled:
    """Unpickling this writes a marker file: proof that a pickle was (not) loaded."""

    def __init__(self, marker):
        self.marker = marker

    def __reduce__(self):
        return (open, (self.marker, "w"))


@pytest.mark.parametrize("member, descr, shape", [
    ("vertices", "<i8", (10**12, 3)),
    ("table", "<f8", (2**40,)),
    ("meta", "<U1000000000", ()),
    ("table", "<f8", (-5,)),
])
def test_huge_header_is_refused_before_allocating(tmp_path, good, member, descr, shape):
    entries = raw_entries(good)
    entry = next(e for e in entries if e["name"] == member)
    entry["payload"] = crafted_npy(descr, shape, data=bytes(64))
    path = tmp_path / "huge.vevm"
    raw_zip(path, entries)
    tracemalloc.start()
    try:
        refused(path, f"member '{member}' (declares an array|has shape|has an unsupported dtype)")
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 8 << 20


def test_deflate_bombs_are_refused_before_inflating(tmp_path, good):
    entries = raw_entries(good)
    table = next(e for e in entries if e["name"] == "table")
    declared = len(table["payload"])
    cases = {
        # The directory declares the true small size; the stream would inflate to 256 MiB more.
        "beyond its declared size": dict(payload=deflate_zeros(256 << 20), size=declared),
        # The directory declares 3 GiB from 1 KiB: more than deflate can expand.
        "deflate cannot expand": dict(payload=bytes(1024), size=3 << 30),
    }
    for problem, change in cases.items():
        path = tmp_path / "bomb.vevm"
        raw_zip(path, [dict(e, method=8, **change) if e is table else e for e in entries])
        tracemalloc.start()
        try:
            refused(path, f"member 'table' declares .* compressed bytes; .*{problem}")
            peak = tracemalloc.get_traced_memory()[1]
        finally:
            tracemalloc.stop()
        assert peak < 8 << 20, problem


def test_honest_huge_member_is_refused_by_the_memory_budget(tmp_path, good, monkeypatch):
    """A 1 GiB table that deflates to 1 MiB: refused by the budget before a byte is inflated."""
    monkeypatch.setenv("VOLUMEEVM_MEMORY_LIMIT", "64M")
    entries = raw_entries(good)
    table = next(e for e in entries if e["name"] == "table")
    count = (1 << 30) // 4
    header = crafted_npy("<f4", (count,))
    compressor = zlib.compressobj(9, zlib.DEFLATED, -15)
    stream = (compressor.compress(header) + compressor.flush(zlib.Z_FULL_FLUSH)
              + deflate_zeros(1 << 30))
    table.update(payload=stream, method=8, size=len(header) + 4 * count)
    path = tmp_path / "big.vevm"
    raw_zip(path, entries)
    tracemalloc.start()
    try:
        refused(path, r"reading the VolumeEVM file needs about 1\.0 GiB of memory but only "
                      r"64\.0 MiB")
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 8 << 20


def test_memory_budget_for_a_valid_file(tmp_path, data_dir, monkeypatch):
    bone = ct_crop(data_dir)
    path = tmp_path / "bone.vevm"
    bone.save(path)
    estimate = bone.evm.vertices.nbytes + bone.table(0).nbytes
    monkeypatch.setenv("VOLUMEEVM_MEMORY_LIMIT", str(estimate))  # the arrays alone: too little
    refused(path, "reading the VolumeEVM file needs about")
    monkeypatch.setenv("VOLUMEEVM_MEMORY_LIMIT", str(100 * estimate))
    assert_same(VolumeEVM.load(path), bone)


def test_lying_stored_size_is_refused(tmp_path, good):
    entries = raw_entries(good)
    entries[-1]["size"] = len(entries[-1]["payload"]) + 8
    path = tmp_path / "lying.vevm"
    raw_zip(path, entries)
    refused(path, "a stored member's two sizes must be equal")


@pytest.mark.parametrize("member, value, match", [
    ("vertices", lambda a: a.astype(np.float64),
     "member 'vertices' has dtype float64, expected integers"),
    ("vertices", lambda a: a[:, :2], r"member 'vertices' has shape \(\d+, 2\), expected \(n, 3\)"),
    ("table", lambda a: a > 100,
     "member 'table' has dtype bool, expected integers or real numbers"),
    ("table", lambda a: a.astype(np.complex64), "member 'table' has dtype complex64"),
    ("table", lambda a: a.reshape(1, -1), r"member 'table' has shape \(1, \d+\), expected \(n,\)"),
    ("table", lambda a: np.zeros(len(a), [("a", "<f4")]),
     r"member 'table' has an unsupported dtype \[\('a', '<f4'\)\]"),
    ("format", lambda a: np.array(b"volumeevm"),
     "member 'format' has dtype |S9, expected a string"),
    ("version", lambda a: np.array(1.0), "member 'version' has dtype float64, expected integers"),
    ("version", lambda a: np.array(2), "format version 2, this add-on reads 1"),
    ("format", lambda a: np.array("othertool"), r"not a VolumeEVM file \(format 'othertool'\)"),
    ("meta", lambda a: np.array(7), "member 'meta' has dtype int64, expected a string"),
])
def test_member_dtypes_and_shapes(tmp_path, good, member, value, match):
    arrays, meta = members_of(good)
    arrays[member] = value(arrays[member])
    path = tmp_path / "typed.vevm"
    write_vevm_members(path, arrays, None if member == "meta" else meta)
    refused(path, match)


# ---------------------------------------------------------------------- loading: the metadata
def turned(degrees):
    a = np.radians(degrees)
    return [[np.cos(a), -np.sin(a), 0.0], [np.sin(a), np.cos(a), 0.0], [0.0, 0.0, 1.0]]


@pytest.mark.parametrize("change, match", [
    ({"shape": [7, 6]}, "shape .* must be 3 integers"),
    ({"shape": [7, 6, 5.0]}, "shape .* must be 3 integers"),
    ({"shape": [7, 0, 5]}, "shape .* must be 3 integers from 1 to"),
    ({"shape": [7, 6, 2**21]}, "shape .* must be 3 integers from 1 to"),
    ({"spacing": [0.5, -0.75, 2.0]}, "spacing must be three finite positive numbers"),
    ({"spacing": [0.5, 10**400, 2.0]}, "spacing must be three finite positive numbers"),
    ({"spacing": "0.5"}, "spacing must be three finite positive numbers"),
    ({"origin": [0.0, None, 1.0]}, "origin must be three finite numbers"),
    ({"orientation": [[2.0, 0, 0], [0, 1, 0], [0, 0, 1]]}, "orientation must be orthonormal"),
    ({"orientation": [[1.0, 0.1, 0], [0, 1, 0], [0, 0, 1]]}, "orientation must be orthonormal"),
    ({"orientation": [[1.0, 0], [0, 1]]}, "orientation must be a 3x3 matrix"),
    ({"units": 7}, "units 7 must be a string"),
    ({"threshold": "90"}, "threshold '90' must be a finite number or null"),
    ({"threshold": 10**400}, r"threshold 1000+\.\.\. must be a finite number or null"),
    ({"upper": 10.0}, "upper 10.0 is below threshold 90.0"),
    ({"voxels": -1}, "voxels -1 must be a non-negative integer"),
    ({"voxels": 3.5}, "voxels 3.5 must be a non-negative integer"),
    ({"vertices_sha256": None}, "vertices_sha256 None must be a string"),
    ({"spare": 1}, r"metadata keys missing \[\], unexpected \['spare'\]"),
    ({"drop": "units"}, r"metadata keys missing \['units'\]"),
])
def test_metadata_keys_and_types(tmp_path, good, change, match):
    arrays, meta = members_of(good)
    change = dict(change)
    meta.pop(change.pop("drop", None), None)
    meta.update(change)
    if "vertices_sha256" not in change:
        meta["vertices_sha256"] = sha(arrays["vertices"])
    path = tmp_path / "meta.vevm"
    write_vevm_members(path, arrays, meta, recompute=False)
    refused(path, match)


@pytest.mark.parametrize("text, match", [
    ("{not json", "the metadata is not valid JSON"),
    ('{"shape": NaN}', "NaN is not a number"),
    ("[1, 2, 3]", "the metadata is a JSON list, not an object"),
    ("[" * 100000 + "]" * 100000, "the metadata is not valid JSON"),
])
def test_metadata_must_be_a_json_object(tmp_path, good, text, match):
    arrays, _ = members_of(good)
    arrays["meta"] = np.array(text)
    path = tmp_path / "json.vevm"
    write_vevm_members(path, arrays)
    refused(path, match)


def test_rotated_orientation_round_trips(tmp_path, small):
    rotated = VolumeEVM(small.evm, small.table(0), shape=small.shape, spacing=small.spacing,
                        origin=small.origin, orientation=turned(33), units=small.units,
                        threshold=small.threshold, upper=small.upper)
    rotated.save(tmp_path / "rotated.vevm")
    assert_same(VolumeEVM.load(tmp_path / "rotated.vevm"), rotated)


# ---------------------------------------------------------------------- loading: the region
def test_checksums_catch_a_changed_member(tmp_path, good):
    arrays, meta = members_of(good)
    arrays["table"] = arrays["table"].copy()
    arrays["table"][3] += 1
    path = tmp_path / "tampered.vevm"
    write_vevm_members(path, arrays, meta, recompute=False)
    refused(path, r"checksum mismatch \(table\), the file is corrupt")


@pytest.mark.parametrize("name, match", [
    ("outside", r"vertices span .* outside the grid \[0, 0, 0\] \.\. \[7, 6, 5\]"),
    ("negative", r"vertices span \[-1, 0, 0\] .* outside the grid"),
    ("odd line", r"an odd number of vertices on \d+ line\(s\) along ."),
    ("duplicate", "vertices contain duplicates"),
    ("short table", r"the region has \d+ voxels, the metadata says \d+ and the table holds \d+"),
    ("voxels", r"the region has \d+ voxels, the metadata says"),
    ("nan table", "1 densities are NaN or infinite"),
    ("other region", "the region has 8 voxels"),
])
def test_region_checks_behind_valid_checksums(tmp_path, good, name, match):
    arrays, meta = members_of(good)
    region_change(name)(arrays, meta)
    path = tmp_path / "region.vevm"
    write_vevm_members(path, arrays, meta)
    refused(path, f"corrupt VolumeEVM file: {match}")


# ---------------------------------------------------------------------- saving
def race(path, contents, *, overwrite=False):
    """Two threads write ``contents[i]`` to ``path`` at once: both pass the initial existence check
    and finish writing before either publishes. Returns the outcomes in thread order."""
    barrier = threading.Barrier(len(contents), timeout=10)
    outcomes = [None] * len(contents)

    def save(i):
        def write(temporary):
            temporary.write_bytes(contents[i])
            barrier.wait()

        try:
            write_atomically(path, write, overwrite=overwrite)
            outcomes[i] = "saved"
        except VolumeEVMError as error:
            outcomes[i] = error

    threads = [threading.Thread(target=save, args=(i,)) for i in range(len(contents))]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(20)
    return outcomes


@pytest.mark.parametrize("links", ["hard links", "no hard links"])
def test_racing_saves_to_a_new_path_one_wins(tmp_path, monkeypatch, links):
    if links == "no hard links":
        def refuse(*_args, **_kwargs):
            raise OSError(errno.EPERM, "Operation not permitted")

        monkeypatch.setattr(os, "link", refuse)
    for round_ in range(10):
        path = tmp_path / f"race{round_}.png"
        contents = [bytes([i]) * (100_000 + i) for i in range(2)]
        outcomes = race(path, contents)
        assert sorted(map(str, outcomes)).count("saved") == 1, outcomes
        winner = outcomes.index("saved")
        loser = outcomes[1 - winner]
        assert isinstance(loser, VolumeEVMError)
        assert str(loser) == f"{path}: exists; choose another name or allow overwriting"
        assert isinstance(loser.__cause__, FileExistsError)
        assert path.read_bytes() == contents[winner]
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(f"race{i}.png" for i in range(10))


def test_racing_vevm_saves_keep_the_winners_file(tmp_path, monkeypatch, small, data_dir):
    """Two real VolumeEVM saves to one new name, held until both have written: one file wins."""
    barrier = threading.Barrier(2, timeout=10)
    real = _volumeevm.write_atomically

    def held(path, write, *, overwrite):
        return real(path, lambda temporary: (write(temporary), barrier.wait()), overwrite=overwrite)

    monkeypatch.setattr(_volumeevm, "write_atomically", held)
    path = tmp_path / "shared.vevm"
    candidates = [small, ct_crop(data_dir)]
    outcomes = [None, None]

    def save(i):
        try:
            candidates[i].save(path)
            outcomes[i] = "saved"
        except VolumeEVMError as error:
            outcomes[i] = error

    threads = [threading.Thread(target=save, args=(i,)) for i in range(2)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(20)
    assert outcomes.count("saved") == 1, outcomes
    winner = outcomes.index("saved")
    assert "exists" in str(outcomes[1 - winner])
    assert_same(VolumeEVM.load(path), candidates[winner])
    assert list(tmp_path.iterdir()) == [path]


def test_overwrite_replaces_atomically(tmp_path):
    path = tmp_path / "image.png"
    path.write_bytes(b"old")
    outcomes = race(path, [b"first", b"second"], overwrite=True)
    assert outcomes == ["saved", "saved"]
    assert path.read_bytes() in (b"first", b"second")
    mask = os.umask(0o022)
    os.umask(mask)
    assert path.stat().st_mode & 0o777 == 0o666 & ~mask
    assert list(tmp_path.iterdir()) == [path]


@pytest.mark.parametrize("overwrite", [False, True])
def test_failed_write_keeps_the_old_file_and_no_temporary(tmp_path, overwrite):
    path = tmp_path / "kept.vevm"
    if overwrite:
        path.write_bytes(b"the user's own file")

    def broken(temporary):
        temporary.write_bytes(b"half a fi")
        raise RuntimeError("writer failed")

    with pytest.raises(RuntimeError, match="writer failed"):
        write_atomically(path, broken, overwrite=overwrite)

    def disk_full(temporary):
        temporary.write_bytes(b"half a fi")
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    with pytest.raises(VolumeEVMError) as info:
        write_atomically(path, disk_full, overwrite=overwrite)
    assert str(info.value) == (f"{path}: could not write the file (No space left on device); the "
                               f"disk is full; free some space or choose another disk")
    assert info.value.__cause__.errno == errno.ENOSPC
    assert list(tmp_path.iterdir()) == ([path] if overwrite else [])
    if overwrite:
        assert path.read_bytes() == b"the user's own file"


def test_folder_that_refuses_files(small):
    folder = "/sys"  # even root may not create files there (permissions do not stop root)
    if not os.path.isdir(folder) or _can_create(folder):
        skip_unless_ci("no folder here refuses new files")
    with pytest.raises(VolumeEVMError) as info:
        small.save(f"{folder}/refused.vevm")
    assert str(info.value).startswith(f"{folder}/refused.vevm: cannot create a file in its "
                                      f"folder (")
    assert isinstance(info.value.__cause__, OSError)


def _can_create(folder):
    try:
        descriptor, name = tempfile.mkstemp(dir=folder)
    except OSError:
        return False
    os.close(descriptor)
    os.unlink(name)
    return True


def test_path_under_a_file(tmp_path, small):
    blocker = tmp_path / "notes.txt"
    blocker.write_text("a file, not a folder")
    target = blocker / "sub" / "x.vevm"
    expected = f"^{target}: cannot make its folder {blocker / 'sub'}"
    with pytest.raises(VolumeEVMError, match=expected) as info:
        small.save(target)
    assert isinstance(info.value.__cause__, OSError)
    with pytest.raises(VolumeEVMError, match=f"^{blocker / 'x.png'}: cannot "):
        write_png(blocker / "x.png", np.zeros((2, 2, 4), np.float32))
    assert blocker.read_text() == "a file, not a folder"


def test_png_writer_never_replaces_unasked(tmp_path):
    path = tmp_path / "view.png"
    path.write_bytes(b"mine")
    with pytest.raises(VolumeEVMError, match="view.png: exists"):
        write_png(path, np.zeros((2, 2, 4), np.float32))
    assert path.read_bytes() == b"mine"


def test_long_file_name(tmp_path, small):
    path = tmp_path / ("n" * 245 + ".vevm")  # 250 characters: the longest most file systems allow
    small.save(path)
    assert_same(VolumeEVM.load(path), small)
    assert list(tmp_path.iterdir()) == [path]
