"""Child process of `check`: `python -m lidar2xodr.quality.worker pyxodr|carla|lanelet2 MAP` prints one JSON line."""

from __future__ import annotations

import json
import sys
from pathlib import Path

from lidar2xodr.errors import InputError
from lidar2xodr.quality.readers import RESULT_PREFIX, run_pyxodr


def main(argv: list[str]) -> int:
    reader, path = argv[0], Path(argv[1])
    from lidar2xodr.opendrive import OpenDriveMap

    try:
        odr = OpenDriveMap.load(path)
    except InputError:
        odr = None
    if reader == "carla":
        from lidar2xodr.quality.carla_reader import run_carla

        result = run_carla(path, odr)
    elif reader == "lanelet2":
        from lidar2xodr.lanelet2_reader import run_lanelet2

        result = run_lanelet2(path)
    else:
        result = run_pyxodr(path, odr)
    sys.stdout.write("\n" + RESULT_PREFIX + json.dumps(result) + "\n")
    sys.stdout.flush()
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
