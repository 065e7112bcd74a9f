"""What every benchmark shares: best-of-N timing, the run's facts, JSON results written
atomically."""

import json
import os
import platform
import re
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from volumeevm_addon.rendering import render_options  # noqa: E402
from volumeevm_addon.system import write_atomically  # noqa: E402


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
    commit = subprocess.run(git + ["rev-parse", "HEAD"], capture_output=True,
                            text=True).stdout.strip()
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


def write_json(path, data):
    """Write ``data`` as indented JSON, atomically (NumPy values become lists or numbers).

    A list of numbers (a curve, a matrix row, a shape) stays on one line, so that a result
    file reads (and diffs) by entry rather than by number. Only a list that ``json.dumps`` spread
    over lines is joined: a string never holds a newline, so its text is never touched."""
    text = json.dumps(data, indent=1,
                      default=lambda o: o.tolist() if hasattr(o, "tolist") else str(o))
    text = re.sub(r"\[\n[-+.\deE,\s]*\]",
                  lambda m: "[" + " ".join(m.group()[1:-1].split()) + "]", text)
    write_atomically(path, lambda temporary: temporary.write_text(text), overwrite=True)
    print(f"wrote {path}")


def non_default(method, options):
    """``options`` without the entries equal to the method's own defaults
    (:func:`volumeevm_addon.rendering.render_options`; so a swept setting that is the default is
    recognised as it)."""
    defaults = render_options(method)
    return {k: v for k, v in options.items() if k not in defaults or defaults[k] != v}


def accepts(method, options):
    """Whether this version of the renderer ``method`` takes every option in ``options`` (so a
    bench runs on renderers that do not have a quality setting yet, and says so by leaving it
    out)."""
    return set(options) <= set(render_options(method)) | {"level"}
