"""Download the wheels the extension bundles into ``wheels/``: exactly the files the manifest's
``wheels`` names, from PyPI; files already there are kept.

Pure wheels (``py3-none-any``) are fetched by their pin; Numba and llvmlite by their pin for the
wheel's own platform and Python (``pip download --platform --python-version``), so one machine
fetches every platform's. ``--platform`` fetches only what one platform's zip needs: the pure
wheels and that platform's (the Blender tests build the Linux x64 zip)::

    python requirements/fetch_wheels.py [--platform linux-x64]
"""

import argparse
import re
import subprocess
import sys
import tomllib
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
_SYSTEMS = {"win": "windows", "manylinux": "linux", "macosx": "macos"}
_MACHINES = {"x86_64": "x64", "amd64": "x64", "aarch64": "arm64", "arm64": "arm64"}


def manifest_wheels():
    """The wheels ``blender_manifest.toml`` lists, as paths in the repository."""
    manifest = tomllib.loads((REPO / "blender_manifest.toml").read_text())
    return [REPO / wheel for wheel in manifest["wheels"]]


def wheel_tags(path):
    """``(distribution, version, python, abi, platform)`` from a wheel's file name."""
    return tuple(Path(path).name.removesuffix(".whl").split("-"))


def blender_platform(platform_tag):
    """The Blender platform (``linux-x64``, ``macos-arm64``...) of a wheel's platform tag, as
    Blender maps it; ``"any"`` for a pure wheel."""
    if platform_tag == "any":
        return "any"
    first = platform_tag.split(".")[0]  # manylinux_2_27_x86_64.manylinux_2_28_x86_64: one machine
    system = _SYSTEMS[re.match(r"[a-z]+", first).group()]
    machine = next(name for suffix, name in _MACHINES.items() if first.endswith("_" + suffix))
    return f"{system}-{machine}"


def pip_options(path):
    """What ``pip download`` needs to fetch exactly this wheel: its pin, and for a platform
    wheel the platform, Python and ABI it is for."""
    distribution, version, python, abi, platform = wheel_tags(path)
    options = [f"{distribution}=={version}"]
    if platform != "any":
        options += [f"--platform={tag}" for tag in platform.split(".")]
        options += [f"--python-version={python[2]}.{python[3:]}", "--implementation=cp",
                    f"--abi={abi}"]
    return options


def fetch(platform=None):
    """Download the manifest's missing wheels (of ``platform`` and pure ones, if given).

    Returns the wanted paths; raises ``RuntimeError`` if pip fails or fetches another file.
    """
    wanted = [w for w in manifest_wheels()
              if platform is None or blender_platform(wheel_tags(w)[4]) in ("any", platform)]
    batches = {}  # one pip call per platform and Python
    for wheel in wanted:
        if not wheel.is_file():
            pin, *options = pip_options(wheel)
            batches.setdefault(tuple(options), []).append(pin)
    for options, pins in batches.items():
        done = subprocess.run(
            [sys.executable, "-m", "pip", "download", "--quiet", "--disable-pip-version-check",
             "--no-deps", "--only-binary=:all:", "--dest", str(REPO / "wheels"), *options, *pins],
            capture_output=True, text=True)
        if done.returncode != 0:
            raise RuntimeError(f"pip download {' '.join([*options, *pins])} failed:\n{done.stderr}")
    missing = [w.name for w in wanted if not w.is_file()]
    if missing:
        raise RuntimeError(f"PyPI did not give the files the manifest names: {', '.join(missing)}")
    return wanted


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--platform", help="only this Blender platform's wheels (and pure ones)")
    try:
        fetch(parser.parse_args().platform)
    except RuntimeError as error:
        sys.exit(str(error))


if __name__ == "__main__":
    main()
