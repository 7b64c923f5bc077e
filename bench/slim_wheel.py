r"""Repack a wheel without some of its folders, for carrying it to the device machine.

Ray's wheel is 75.6 MiB, of which 32 MB are the jars of its Java API, which Python never loads,
and 5 MB its libraries (RLlib, Data, Serve, Tune, Train, LLM), which gsplatam does not use;
without them it is 40.1 MiB and fits a device call beside gsplat and cyclonedds:

    python bench/slim_wheel.py ray-2.60.0-cp312-cp312-manylinux2014_x86_64.whl .device-ray \
        --drop ray/jars/ --drop ray/rllib/ --drop ray/data/ --drop ray/serve/ --drop ray/tune/ \
        --drop ray/train/ --drop ray/llm/
"""

from __future__ import annotations

import argparse
import zipfile
from pathlib import Path
from typing import IO

from pipeline.io.files.atomic import atomic_write


def slim(wheel: Path, out_dir: Path, drop: list[str]) -> Path:
    """Copy `wheel` into `out_dir` without the entries under the `drop` prefixes (and their RECORD lines)."""
    out_dir.mkdir(parents=True, exist_ok=True)
    target = out_dir / wheel.name

    def write(file: IO[bytes]) -> None:
        with zipfile.ZipFile(wheel) as source, zipfile.ZipFile(file, "w", zipfile.ZIP_DEFLATED) as slimmed:
            for item in source.infolist():
                if any(item.filename.startswith(prefix) for prefix in drop):
                    continue
                data = source.read(item)
                if item.filename.endswith(".dist-info/RECORD"):
                    lines = data.decode().splitlines()
                    data = ("\n".join(line for line in lines if not line.startswith(tuple(drop))) + "\n").encode()
                slimmed.writestr(item, data)

    atomic_write(target, write)
    return target


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("wheel", type=Path)
    parser.add_argument("out_dir", type=Path)
    parser.add_argument("--drop", action="append", required=True, help="a folder prefix to leave out (repeatable)")
    args = parser.parse_args()
    target = slim(args.wheel, args.out_dir, args.drop)
    print(f"{target}: {target.stat().st_size / 2**20:.1f} MiB (was {args.wheel.stat().st_size / 2**20:.1f} MiB)")


if __name__ == "__main__":
    main()
