"""Fuzzing the ``.vevm`` reader: each mutated file loads as exactly the original data or is refused
with a VolumeEVMError naming the file; never another exception, a hang or different data.

Two valid files are the seeds: a crop of the real CT head thresholded at 300 HU and a small
synthetic region with every field set. Each is mutated by truncation at many offsets, by byte
flips aimed at the ZIP directory, the member headers and the data, and by crafted members
(huge headers, deflate bombs, wrong dtypes, a pickled member, missing or extra members, bad
metadata, and regions that are wrong behind re-computed checksums, so that the semantic checks
and not the checksum must catch them). Crafted cases must all be refused; a truncation or a
byte flip may also land where it changes nothing (ZIP timestamps, attributes), and then the
load must give the original data exactly.

Run with ``pytest -s`` to see the summary line: cases by mutation and by outcome.
"""

import collections
import json
import re
import time
import zipfile
import zlib

import numpy as np

from vevm_helpers import (
    crafted_npy,
    ct_crop,
    deflate_zeros,
    members_of,
    npy_bytes,
    raw_entries,
    raw_zip,
    region_change,
    synthetic,
    write_vevm_members,
)
from volumeevm_addon import VolumeEVM, VolumeEVMError

SEED = 20261124
TRUNCATIONS = 60
FLIPS = {"zip directory": 50, "member headers": 50, "data": 30}
SLOWEST = 5.0  # seconds one case may take: far above any real load of these files

#: Outcome classes of a refusal, by what the message says (first match wins).
OUTCOMES = [
    ("refused: not a VolumeEVM file", r": not a VolumeEVM file"),
    ("refused: archive or member unreadable", r": not a readable VolumeEVM file"),
    ("refused: checksum", r": checksum mismatch"),
    ("refused: other version", r": format version"),
    ("refused: memory", r"needs about .* of memory"),
    ("refused: metadata or region",
     r": corrupt VolumeEVM file|: (spacing|origin|orientation) must"),
]


def crafted_cases(good, rng):
    """``{label: write(path)}`` of crafted files made from the good file ``good``."""
    arrays, meta = members_of(good)
    cases = {}

    def with_entries(change):
        """Rewrite the archive by hand after ``change(entries by name, entries)``."""
        def write(path):
            entries = raw_entries(good)
            change({e["name"]: e for e in entries}, entries)
            raw_zip(path, entries)
        return write

    def with_members(change, *, recompute=True, raw_meta=False):
        """Rewrite the members after ``change(arrays, meta dict)``: the meta member made from the
        dict (checksums re-computed unless ``recompute`` is False), or as ``change`` set it
        (``raw_meta``)."""
        def write(path):
            a = {k: v.copy() for k, v in arrays.items()}
            m = json.loads(json.dumps(meta))
            change(a, m)
            write_vevm_members(path, a, None if raw_meta else m, recompute=recompute)
        return write

    # Huge or impossible .npy headers, deflate bombs, lying sizes, flags, members missing or extra.
    huge = {"format": ("<U1000000000", ()), "version": ("<i8", (10**9,)),
            "meta": ("<U2000000000", ()), "vertices": ("<i8", (10**12, 3)),
            "table": ("<f8", (2**40,))}
    for name, (descr, shape) in huge.items():
        cases[f"huge header {name}"] = with_entries(
            lambda by, _, n=name, d=descr, s=shape: by[n].update(
                payload=crafted_npy(d, s, bytes(64))))
    for name in arrays:
        cases[f"missing {name}"] = with_entries(lambda by, entries, n=name: entries.remove(by[n]))
    archive_changes = {
        "negative shape": lambda by, _: by["table"].update(
            payload=crafted_npy("<f4", (-4,), bytes(64))),
        "bomb beyond declared size": lambda by, _: by["table"].update(
            payload=deflate_zeros(64 << 20), method=8, size=len(by["table"]["payload"])),
        "bomb beyond deflate ratio": lambda by, _: by["table"].update(payload=bytes(512), method=8,
                                                                      size=3 << 30),
        "honest 1 GiB member": lambda by, _: by["table"].update(_honest_bomb()),
        "stored size lie": lambda by, _: by["vertices"].update(
            size=len(by["vertices"]["payload"]) - 8),
        "wrong crc": lambda by, _: by["meta"].update(crc=12345),
        "encrypted flag": lambda by, _: by["version"].update(flags=1),
        "bzip2 method": lambda by, _: by["meta"].update(method=12),
        "extra member": lambda by, entries: entries.append(
            {"name": "x", "payload": npy_bytes(np.ones(2))}),
        "repeated member": lambda by, entries: entries.insert(0, dict(by["table"])),
        "empty archive": lambda by, entries: entries.clear(),
    }
    for label, change in archive_changes.items():
        cases[label] = with_entries(change)
    # Wrong dtypes and shapes (checksums re-computed), pickles, a changed table under the old
    # checksum.
    members = {
        "vertices float": ("vertices", lambda v: v.astype(np.float32)),
        "vertices uint64 huge": ("vertices", lambda v: v.astype(np.uint64) + np.uint64(2**63)),
        "vertices (n, 4)": ("vertices", lambda v: np.c_[v, v[:, :1]]),
        "table bool": ("table", lambda t: t > 0),
        "table complex": ("table", lambda t: t.astype(np.complex128)),
        "table structured": ("table", lambda t: np.zeros(len(t), [("a", "<f8")])),
        "table 2-D": ("table", lambda t: t[:, None]),
        "table pickled objects": ("table", lambda t: t.astype(object)),
        "format bytes": ("format", lambda f: np.array(b"volumeevm")),
        "format other": ("format", lambda f: np.array("volumeev")),
        "version 0": ("version", lambda v: np.array(0)),
        "version float": ("version", lambda v: np.array(1.0)),
    }
    for label, (name, change) in members.items():
        cases[label] = with_members(lambda a, m, n=name, c=change: a.__setitem__(n, c(a[n])))
    cases["meta pickled"] = with_members(
        lambda a, m: a.__setitem__("meta", np.array([{"x": 1}], object)), raw_meta=True)
    cases["table changed, old checksum"] = with_members(
        lambda a, m: a.__setitem__("table", a["table"][::-1].copy()), recompute=False)
    # Metadata: wrong types, non-finite numbers, bad geometry, shape too small for the region.
    edits = {
        "shape 2 values": ("shape", lambda m: m["shape"][:2]),
        "shape float": ("shape", lambda m: [float(s) for s in m["shape"]]),
        "shape too small": ("shape", lambda m: [m["shape"][0] - 1] + m["shape"][1:]),
        "shape zero": ("shape", lambda m: [0] + m["shape"][1:]),
        "shape bool": ("shape", lambda m: [True, True, True]),
        "spacing negative": ("spacing", lambda m: [-s for s in m["spacing"]]),
        "spacing zero": ("spacing", lambda m: [0.0] + m["spacing"][1:]),
        "spacing text": ("spacing", lambda m: "1 1 1"),
        "spacing huge int": ("spacing", lambda m: [10**400, 1, 1]),
        "origin null": ("origin", lambda m: None),
        "origin 4 values": ("origin", lambda m: m["origin"] + [0.0]),
        "orientation scaled": ("orientation", lambda m: (2 * np.array(m["orientation"])).tolist()),
        "orientation sheared": ("orientation", lambda m: [[1, 0.2, 0], [0, 1, 0], [0, 0, 1]]),
        "orientation 2x2": ("orientation", lambda m: [[1, 0], [0, 1]]),
        "units number": ("units", lambda m: 5),
        "threshold text": ("threshold", lambda m: "300"),
        "threshold list": ("threshold", lambda m: [300]),
        "upper below threshold": ("upper", lambda m: (m["threshold"] or 0) - 1),
        "voxels negative": ("voxels", lambda m: -3),
        "voxels off by one": ("voxels", lambda m: m["voxels"] + 1),
        "voxels float": ("voxels", lambda m: float(m["voxels"])),
        "extra key": ("colour", lambda m: "red"),
    }
    for label, (key, change) in edits.items():
        cases[f"meta {label}"] = with_members(lambda a, m, k=key, c=change: m.__setitem__(k, c(m)))
    cases["meta key missing"] = with_members(lambda a, m: m.pop("origin"))
    cases["meta sha not text"] = with_members(lambda a, m: m.__setitem__("table_sha256", 0),
                                              recompute=False)
    texts = {"meta NaN token": lambda m: json.dumps(m).replace(str(m["spacing"][0]), "NaN", 1),
             "meta not JSON": lambda m: json.dumps(m)[:-3],
             "meta a list": lambda m: "[1, 2]",
             "meta deep nesting": lambda m: "[" * 50000 + "]" * 50000}
    for label, text in texts.items():
        cases[label] = with_members(lambda a, m, t=text: a.__setitem__("meta", np.array(t(m))),
                                    raw_meta=True)
    # Regions wrong behind re-computed checksums.
    for name in ("outside", "negative", "odd line", "duplicate", "short table", "nan table",
                 "other region"):
        cases[f"region {name}"] = with_members(lambda a, m, n=name: region_change(n)(a, m))
    vertex_count, voxel_count = len(arrays["vertices"]), len(arrays["table"])
    for _ in range(8):  # one vertex moved by one step: always odd lines (or a duplicate)
        row, axis, step = (int(rng.integers(vertex_count)), int(rng.integers(3)),
                           int(rng.choice([-1, 1])))
        cases[f"vertex {row} moved"] = with_members(
            lambda a, m, r=row, x=axis, s=step: _move(a, r, x, s))
    for value in (np.nan, np.inf, -np.inf, np.nan):
        row, spot = int(rng.integers(vertex_count)), int(rng.integers(voxel_count))
        cases[f"vertex {row} dropped"] = with_members(
            lambda a, m, r=row: a.__setitem__("vertices", np.delete(a["vertices"], r, 0)))
        cases[f"table {value} at {spot}"] = with_members(
            lambda a, m, s=spot, v=value: _set_float(a, s, v))
    return cases


def _honest_bomb():
    """A table member declaring 1 GiB of float32 that really inflates to it from ~1 MiB."""
    count = (1 << 30) // 4
    header = crafted_npy("<f4", (count,))
    compressor = zlib.compressobj(9, zlib.DEFLATED, -15)
    stream = (compressor.compress(header) + compressor.flush(zlib.Z_FULL_FLUSH)
              + deflate_zeros(1 << 30))
    return {"payload": stream, "method": 8, "size": len(header) + 4 * count}


def _move(arrays, row, axis, step):
    vertices = arrays["vertices"].astype(np.int64)
    vertices[row, axis] += step
    arrays["vertices"] = vertices


def _set_float(arrays, spot, value):
    table = arrays["table"].astype(np.float64)
    table[spot] = value
    arrays["table"] = table


def byte_regions(good):
    """``{region: (start, stop) ranges}`` of the good file: ZIP directory, member headers, data."""
    size = good.stat().st_size
    with zipfile.ZipFile(good) as archive:
        directory_start = archive.start_dir
        headers, payloads = [], []
        for info in archive.infolist():
            local = info.header_offset
            body = local + 30 + len(info.filename.encode())
            with archive.open(info) as member:
                np.lib.format.read_magic(member)
                np.lib.format.read_array_header_1_0(member)
                header_length = member.tell()
            headers.append((local, body + header_length))
            payloads.append((body + header_length, body + info.compress_size))
    return {"zip directory": [(directory_start, size)], "member headers": headers,
            "data": [p for p in payloads if p[1] > p[0]]}


def mutations(good, rng):
    """``{label: write(path)}``: truncations and byte flips of the good file."""
    data = good.read_bytes()
    cases = {}
    ends = {0, 1, 4, 22, len(data) - 22, len(data) - 1}
    offsets = sorted(ends | set(rng.choice(len(data), TRUNCATIONS - len(ends),
                                           replace=False).tolist()))
    for offset in offsets:
        cases[f"truncated at {offset}"] = lambda path, o=offset: path.write_bytes(data[:o])
    for region, ranges in byte_regions(good).items():
        spans = np.array([stop - start for start, stop in ranges], float)
        for _ in range(FLIPS[region]):
            start, stop = ranges[rng.choice(len(ranges), p=spans / spans.sum())]
            position, flip = int(rng.integers(start, stop)), int(rng.integers(1, 256))
            changed = bytearray(data)
            changed[position] ^= flip
            cases[f"{region} byte {position} ^ {flip}"] = (
                lambda path, c=bytes(changed): path.write_bytes(c))
    return cases


def test_fuzz_vevm(tmp_path, data_dir, monkeypatch):
    # A bomb let through is refused, not swapped.
    monkeypatch.setenv("VOLUMEEVM_MEMORY_LIMIT", "64M")
    rng = np.random.default_rng(SEED)
    outcomes, failures, slowest = collections.defaultdict(collections.Counter), [], 0.0
    started = time.perf_counter()
    for source, original in (("synthetic", synthetic()), ("ct", ct_crop(data_dir))):
        good = tmp_path / f"{source}.vevm"
        original.save(good)
        for kind, cases in (("mutation", mutations(good, rng)),
                            ("crafted", crafted_cases(good, rng))):
            for label, write in cases.items():
                path = tmp_path / f"case-{source}.vevm"
                write(path)
                begin = time.perf_counter()
                outcome = run_case(path, original, must_refuse=kind == "crafted")
                slowest = max(slowest, time.perf_counter() - begin)
                group = ("truncation" if label.startswith("truncated") else
                         f"flip in {label.split(' byte ')[0]}" if " byte " in label else "crafted")
                outcomes[group][outcome] += 1
                if outcome.startswith("FAIL"):
                    failures.append(f"{source} {label}: {outcome}")
    elapsed = time.perf_counter() - started
    total = sum(map(sum, (counter.values() for counter in outcomes.values())))
    overall = sum(outcomes.values(), collections.Counter())
    print(f"\nfuzz .vevm: {total} cases in {elapsed:.1f} s (slowest {slowest:.2f} s): "
          + ", ".join(f"{k} {n}" for k, n in sorted(overall.items())))
    for group, counter in sorted(outcomes.items()):
        print(f"  {group} ({sum(counter.values())}): "
              + ", ".join(f"{k} {n}" for k, n in sorted(counter.items())))
    assert not failures, "\n".join(failures)
    assert slowest < SLOWEST
    assert total >= 300


def run_case(path, original, *, must_refuse):
    """The outcome class of loading ``path``: ``"exact"``, ``"refused: ..."`` or ``"FAIL ..."``."""
    try:
        loaded = VolumeEVM.load(path)
    except VolumeEVMError as error:
        message = str(error)
        if not message.startswith(f"{path}: "):
            return f"FAIL: message does not name the file: {message}"
        for outcome, pattern in OUTCOMES:
            if re.search(pattern, message):
                return outcome
        return "refused: other"
    except Exception as error:  # noqa: BLE001 (any other type is the failure this suite looks for)
        return f"FAIL: {type(error).__name__}: {error}"
    if must_refuse:
        return "FAIL: a crafted file was accepted"
    return "exact" if same_data(loaded, original) else "FAIL: loaded different data"


def same_data(loaded, original):
    return (np.array_equal(loaded.evm.vertices, original.evm.vertices)
            and loaded.table(0).dtype == original.table(0).dtype
            and np.array_equal(loaded.table(0), original.table(0))
            and (loaded.shape, loaded.spacing, loaded.origin, loaded.units, loaded.threshold,
                 loaded.upper)
            == (original.shape, original.spacing, original.origin, original.units,
                original.threshold, original.upper)
            and np.array_equal(loaded.orientation, original.orientation))


def test_fuzz_classifier(tmp_path):
    """The classifier itself: an unchanged file is "exact", a refused one gets a class."""
    original = synthetic()
    path = tmp_path / "x.vevm"
    original.save(path)
    assert run_case(path, original, must_refuse=False) == "exact"
    assert run_case(path, original, must_refuse=True) == "FAIL: a crafted file was accepted"
    path.write_bytes(path.read_bytes()[:100])
    assert run_case(path, original, must_refuse=False) == "refused: archive or member unreadable"
