"""Fetch one bundled wheel named in blender_manifest.toml from PyPI (pip download).

Usage: python scripts/fetch_wheels.py wheels/NAME.whl
The wheel's file name gives the package, version, Python tag and platform.
"""

import subprocess
import sys
from pathlib import Path


def main(target: str) -> int:
    path = Path(target)
    name, version, py, _abi, plat = path.stem.split("-")[:5]
    # A compound platform tag (a.b) lists alternatives; pip needs one of them.
    platform = plat.split(".")[-1]
    cmd = [
        sys.executable, "-m", "pip", "download", "-q", "--no-deps", "--only-binary=:all:",
        "--python-version", py.removeprefix("cp"), "--platform", platform,
        "-d", str(path.parent), f"{name}=={version}",
    ]
    subprocess.run(cmd, check=True)
    if not path.exists():
        print(f"pip downloaded something, but not {path.name}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1]))
