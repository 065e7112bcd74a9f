"""Fetch the demo's CT head from the Debian archive and decode it to ``ct_head_invesalius.npy``.

The scan is InVesalius' sample "ProMED CT 0051" (``Cranium.inv3``) in the Debian package
``invesalius-examples`` 3.1.99998-4 (GPL-2 only). It is fetched rather than shipped: the
VolumeEVM code is GPL-3.0-or-later, the scan GPL-2 only, and fetching the pinned package keeps
the scan, its licence and its source where Debian publishes them. Both the package and the
decoded array are checked against pinned SHA-256 digests; a file already there with the right
digest is kept (nothing downloaded twice). Only the standard library and NumPy.

Run by ``make demo`` (``python sample_blends/fetch_ct_head.py sample_blends/data``); writes
``ct_head_invesalius.npy`` (int16 HU indexed ``[x, y, z]``, 256 × 256 × 108) and its sidecar
``ct_head_invesalius.json`` (spacing 0.957 × 0.957 × 1.5 mm, units HU) into the folder.
"""

import argparse
import hashlib
import io
import json
import plistlib
import sys
import tarfile
import urllib.request
from pathlib import Path

import numpy as np

PACKAGE, VERSION = "invesalius-examples", "3.1.99998-4"
URL = ("https://deb.debian.org/debian/pool/main/i/invesalius/"
       f"{PACKAGE}_{VERSION}_all.deb")
DEB_SHA256 = "f2f14bdfef6dc3812eafc5013d133c6c18370aaab5666b78d54af2e7db432f97"
MEMBER = "./usr/share/doc/invesalius-examples/examples/Cranium.inv3"
NAME = "ct_head_invesalius"
ARRAY_SHA256 = "3a36c40f21f6dc5c570c4c0a9e41614051b463cabad1ba1381ff84c4f7f09cd9"


def sha256(data):
    return hashlib.sha256(data).hexdigest()


def download():
    """The package's bytes, checked against the pinned digest."""
    print(f"[fetch] {URL}", flush=True)
    try:
        with urllib.request.urlopen(URL, timeout=60) as response:
            data = response.read()
    except OSError as error:
        sys.exit(f"[fetch] cannot download {PACKAGE} {VERSION} from {URL}: {error}\n"
                 f"[fetch] (Debian keeps every version at snapshot.debian.org)")
    if sha256(data) != DEB_SHA256:
        sys.exit(f"[fetch] {URL}: SHA-256 {sha256(data)} is not the pinned {DEB_SHA256}")
    return data


def data_tar(deb):
    """The ``data.tar.*`` member of a .deb (an ``ar`` archive: 8-byte magic, 60-byte headers)."""
    offset = 8
    while offset < len(deb):
        header = deb[offset:offset + 60]
        name, size = header[:16].decode().strip().rstrip("/"), int(header[48:58])
        offset += 60
        if name.startswith("data.tar"):
            return deb[offset:offset + size]
        offset += size + size % 2
    sys.exit(f"[fetch] {PACKAGE} {VERSION}: no data.tar in the package")


def decode(inv3):
    """The CT of an InVesalius project (a tar.gz: ``main.plist`` + raw ``matrix.dat``, z-major)
    as an array indexed ``[x, y, z]`` and its plist."""
    with tarfile.open(fileobj=io.BytesIO(inv3), mode="r:gz") as project:
        members = {Path(m.name).name: m for m in project.getmembers()}
        meta = plistlib.loads(project.extractfile(members["main.plist"]).read())
        matrix = meta["matrix"]
        raw = project.extractfile(members[matrix["filename"]]).read()
    array = np.frombuffer(raw, dtype=np.dtype(matrix["dtype"]).newbyteorder("<"))
    array = array.reshape(matrix["shape"]).transpose(2, 1, 0)
    return np.ascontiguousarray(array, dtype=np.int16), meta


def fetch(folder):
    """Write ``NAME.npy`` and ``NAME.json`` into ``folder`` unless the array is there already."""
    folder.mkdir(parents=True, exist_ok=True)
    npy = folder / f"{NAME}.npy"
    if npy.exists() and sha256(npy.read_bytes()) == ARRAY_SHA256:
        print(f"[fetch] {npy} is there (SHA-256 checked)", flush=True)
        return
    with tarfile.open(fileobj=io.BytesIO(data_tar(download()))) as files:
        inv3 = files.extractfile(MEMBER).read()
    array, meta = decode(inv3)
    buffer = io.BytesIO()
    np.save(buffer, array)
    if sha256(buffer.getvalue()) != ARRAY_SHA256:
        sys.exit(f"[fetch] {MEMBER}: the decoded array's SHA-256 {sha256(buffer.getvalue())} "
                 f"is not the pinned {ARRAY_SHA256}")
    sidecar = {
        "name": NAME, "shape": list(array.shape), "axis_order": "xyz", "dtype": "int16",
        "spacing_mm": [float(s) for s in meta["spacing"]], "units": "HU", "modality": "CT",
        "description": f"CT head, InVesalius sample {meta['name']!r}",
        "source": {"registry": "debian-bookworm", "package": PACKAGE, "version": VERSION,
                   "url": URL, "sha256": DEB_SHA256, "path_in_package": MEMBER[1:]},
        "license": "GPL-2 (Debian copyright of invesalius-examples, Files: *)",
    }
    (folder / f"{NAME}.json").write_text(json.dumps(sidecar, indent=1) + "\n")
    npy.write_bytes(buffer.getvalue())
    print(f"[fetch] wrote {npy} {array.shape} {array.dtype}", flush=True)


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("folder", type=Path, help="where the .npy and .json go")
    fetch(parser.parse_args().folder)
