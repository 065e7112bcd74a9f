"""What every benchmark shares: best-of-N timing, the run's facts, atomic output files."""

import json
import os
import platform
import subprocess
import tempfile
import time
from contextlib import contextmanager
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def best_time(function, repeat, setup=None):
    """Best wall time of ``repeat`` calls of ``function`` (``setup`` runs untimed before each),
    and the last result."""
    best = float("inf")
    result = None
    for _ in range(repeat):
        if setup is not None:
            setup()
        start = time.perf_counter()
        result = function()
        best = min(best, time.perf_counter() - start)
    return best, result


def run_facts():
    """Commit, versions, machine and load: what a result file needs to be read later."""
    import numpy as np

    git = ["git", "-C", str(REPO)]
    commit = subprocess.run(git + ["rev-parse", "HEAD"], capture_output=True, text=True).stdout.strip()
    modified = subprocess.run(git + ["status", "--porcelain", "--untracked-files=no"],
                              capture_output=True, text=True).stdout.splitlines()
    return {
        "commit": commit,
        "modified_files_at_start": sorted(line[3:] for line in modified if line.strip()),
        "date_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "python": platform.python_version(),
        "numpy": np.__version__,
        "machine": f"{platform.machine()}, {os.cpu_count()} cores",
        "load_average_at_start": round(os.getloadavg()[0], 2),
    }


@contextmanager
def atomic_path(path):
    """A temporary path beside ``path`` to write to; renamed onto ``path`` when the block ends
    without error, removed otherwise."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    handle, temporary = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=path.suffix)
    os.close(handle)
    try:
        yield temporary
        os.replace(temporary, path)
    finally:
        Path(temporary).unlink(missing_ok=True)


def write_json(path, data):
    """Write ``data`` as indented JSON, atomically (NumPy values become lists or numbers)."""
    with atomic_path(path) as temporary, open(temporary, "w") as file:
        json.dump(data, file, indent=1, default=lambda o: o.tolist() if hasattr(o, "tolist") else str(o))
    print(f"wrote {path}")
