"""Readers of single scan files: PCD, LAS/LAZ, PLY, KITTI .bin, .npy.

Field names are matched case-insensitively: intensity from `intensity`, `i`, `reflectivity`,
`reflectance`, `remission`; per-point time from `t`, `time`, `timestamp`, `offset_time`,
`gps_time`. Per-point time units are guessed from the sweep duration (`base.time_unit`).
A file that cannot be decoded raises `CorruptScan` (the scan is skipped and counted).

Every size, count and offset a header states is checked against the file's own size before a
library is given the file: laspy, pypcd4 and numpy allocate what a header promises, so a random
or lying header would otherwise make them loop or allocate without bound (a 604-byte `LASF` file
with random bytes ran laspy out of memory). The bounds come from the formats themselves: a point
record takes its record length on disk (LAS, binary PCD, PLY, .npy, KITTI), LZF (binary
compressed PCD) expands at most `LZF_MAX_RATIO` times, and LAZ is decompressed in chunks of
`LAS_CHUNK_POINTS` so that a point count beyond the data ends at the end of the data.
"""

from __future__ import annotations

import io
import struct
from pathlib import Path

import numpy as np

from lidar2xodr.datasets.base import CorruptScan, RawScan, time_unit
from lidar2xodr.errors import InputError, one_line

SCAN_SUFFIXES = (".pcd", ".las", ".laz", ".ply", ".bin", ".npy")
INTENSITY_NAMES = ("intensity", "i", "reflectivity", "reflectance", "remission")
TIME_NAMES = ("t", "time", "timestamp", "timestamps", "offset_time", "gps_time")
LAS_HEADER_SIZE = {0: 227, 1: 227, 2: 227, 3: 235, 4: 375}  # bytes of the public header per LAS 1.x
LAS_VLR_HEADER, LAS_EVLR_HEADER = 54, 60
LAS_CHUNK_POINTS = 1 << 18
LZF_MAX_RATIO = 88  # one 3-byte LZF back-reference copies at most 264 bytes
PCD_TYPES = {("F", 4), ("F", 8), ("I", 1), ("I", 2), ("I", 4), ("I", 8), ("U", 1), ("U", 2), ("U", 4), ("U", 8)}


def _find(names: tuple[str, ...] | list[str], wanted: tuple[str, ...]) -> str | None:
    low = {n.lower(): n for n in names}
    for w in wanted:
        if w in low:
            return low[w]
    return None


def seconds(raw: np.ndarray | None) -> np.ndarray | None:
    """Per-point times in seconds; None when absent or constant (no usable per-point timing)."""
    if raw is None or raw.size == 0:
        return None
    t = raw.astype(np.float64)
    finite = t[np.isfinite(t)]
    if finite.size == 0:
        return t
    span = float(finite.max() - finite.min())
    if span <= 0.0:
        return None
    return t * time_unit(span)


def from_structured(arr: np.ndarray, name: str | Path) -> RawScan:
    """A RawScan from a structured array with x, y, z and optional intensity/time fields."""
    names = list(arr.dtype.names or ())
    arr = arr.reshape(-1)  # pypcd4 gives an empty cloud the shape (0, n_fields)
    xs = [_find(names, (c,)) for c in ("x", "y", "z")]
    if any(c is None for c in xs):
        raise InputError(name, f"scan has no x, y, z fields (fields: {names})")
    xyz = np.column_stack([np.asarray(arr[c], dtype=np.float64) for c in xs])  # type: ignore[index]
    inten_name = _find(names, INTENSITY_NAMES)
    time_name = _find(names, TIME_NAMES)
    times = seconds(None if time_name is None else np.asarray(arr[time_name]))
    return RawScan(
        xyz=xyz,
        intensity=None if inten_name is None else np.asarray(arr[inten_name]),
        times=times,
        untimed=time_name is not None and times is None and len(xyz) > 0,
    )


def check_pcd_header(data: bytes) -> None:
    """Raise CorruptScan unless the PCD header is complete and its point count fits the data.

    pypcd4 trusts POINTS and the compressed sizes: it allocates POINTS x point size, or the stated
    uncompressed size, before it looks at the data.
    """
    header: dict[str, list[str]] = {}
    pos = 0
    while "DATA" not in header:
        end = data.find(b"\n", pos)
        if end < 0:
            raise CorruptScan("PCD header has no DATA line")
        line = data[pos:end].decode("ascii", errors="replace").strip()
        pos = end + 1
        tok = line.split()
        if tok and not tok[0].startswith("#"):
            header[tok[0].upper()] = tok[1:]
    missing = [k for k in ("FIELDS", "SIZE", "TYPE", "WIDTH", "POINTS") if not header.get(k)]
    if missing:
        raise CorruptScan(f"PCD header lacks {', '.join(missing)}")
    fields, sizes, types = header["FIELDS"], header["SIZE"], header["TYPE"]
    counts = header.get("COUNT") or ["1"] * len(fields)
    try:
        size_n, count_n = [int(v) for v in sizes], [int(v) for v in counts]
        width, height = int(header["WIDTH"][0]), int((header.get("HEIGHT") or ["1"])[0])
        points = int(header["POINTS"][0])
    except ValueError as exc:
        raise CorruptScan(f"PCD header: not an integer ({exc})") from None
    if not len(fields) == len(size_n) == len(types) == len(count_n):
        raise CorruptScan(f"PCD header: {len(fields)} FIELDS, {len(size_n)} SIZE, {len(types)} TYPE, "
                          f"{len(count_n)} COUNT")
    if any((t.upper(), n) not in PCD_TYPES for t, n in zip(types, size_n, strict=True)) or min(count_n) < 1:
        raise CorruptScan(f"PCD header: unsupported TYPE/SIZE/COUNT {types} {sizes} {counts}")
    if min(width, height, points) < 0 or width * height != points:
        raise CorruptScan(f"PCD header: WIDTH {width} x HEIGHT {height} is not POINTS {points}")
    need = points * sum(n * c for n, c in zip(size_n, count_n, strict=True))
    body = len(data) - pos
    encoding = (header["DATA"] or [""])[0].lower()
    if encoding == "binary":
        if need > body:
            raise CorruptScan(f"truncated PCD: {points} points need {need} bytes, {body} present")
    elif encoding == "binary_compressed":
        if points == 0:
            return
        if body < 8:
            raise CorruptScan("truncated PCD: no compressed block sizes")
        packed, unpacked = struct.unpack_from("<II", data, pos)
        if unpacked != need or packed > body - 8 or unpacked > LZF_MAX_RATIO * packed:
            raise CorruptScan(f"PCD compressed block of {packed} bytes cannot hold {points} points "
                              f"({need} bytes; {body - 8} bytes present)")
    elif encoding == "ascii":
        if points > data.count(b"\n", pos) + 1:
            raise CorruptScan(f"truncated PCD: {points} points stated, fewer lines present")
    else:
        raise CorruptScan(f"PCD header: unknown DATA {encoding!r}")


def read_pcd(path: Path) -> RawScan:
    from pypcd4 import PointCloud

    data = _read_bytes(path)
    check_pcd_header(data)
    try:
        arr = PointCloud.from_fileobj(io.BytesIO(data)).pc_data  # type: ignore[arg-type]
    except Exception as exc:  # pypcd4 raises many kinds on a broken file
        raise CorruptScan(f"cannot decode PCD: {one_line(exc)}") from None
    return from_structured(arr, path)


def _read_bytes(path: Path) -> bytes:
    try:
        return path.read_bytes()
    except OSError as exc:
        raise CorruptScan(f"cannot read: {exc.strerror or exc}") from None


def check_las_header(path: Path) -> None:
    """Raise CorruptScan unless the LAS header's sizes, VLRs and point count fit inside the file.

    laspy trusts them: a random VLR count or length makes it read and allocate without bound.
    """
    import laspy

    try:
        size = path.stat().st_size
        with path.open("rb") as fh:
            head = fh.read(LAS_HEADER_SIZE[4])
            if len(head) < LAS_HEADER_SIZE[0] or head[:4] != b"LASF":
                raise CorruptScan(f"not a LAS file ({len(head)} bytes, no complete LASF header)")
            major, minor = head[24], head[25]
            if major != 1 or minor not in LAS_HEADER_SIZE:
                raise CorruptScan(f"unsupported LAS version {major}.{minor}")
            header_size, offset, n_vlr, fmt_id, rec_len, n_points = struct.unpack_from("<HIIBHI", head, 94)
            if not LAS_HEADER_SIZE[minor] <= header_size <= offset <= size or len(head) < LAS_HEADER_SIZE[minor]:
                raise CorruptScan(f"LAS header size {header_size} and point offset {offset} do not fit "
                                  f"a {size}-byte file")
            fmt = fmt_id & 0x3F
            if fmt > 10 or rec_len < laspy.PointFormat(fmt).size:
                raise CorruptScan(f"LAS point format {fmt_id} with {rec_len}-byte records is not valid")
            fh.seek(header_size)
            vlrs = fh.read(offset - header_size)
            pos = 0
            for _ in range(n_vlr):
                if pos + LAS_VLR_HEADER > len(vlrs):
                    raise CorruptScan(f"{n_vlr} VLRs stated, they do not fit before the points at {offset}")
                pos += LAS_VLR_HEADER + struct.unpack_from("<H", vlrs, pos + 20)[0]
            if pos > len(vlrs):
                raise CorruptScan(f"the VLRs run past the point data offset {offset}")
            end = size
            if minor == 4:
                evlr_start, n_evlr, n_points64 = struct.unpack_from("<QIQ", head, 235)
                n_points = n_points64 or n_points
                if n_evlr:
                    if not offset <= evlr_start <= size:
                        raise CorruptScan(f"EVLRs start at {evlr_start}, outside the {size}-byte file")
                    end, pos = evlr_start, evlr_start
                    for _ in range(n_evlr):
                        fh.seek(pos)
                        top = fh.read(LAS_EVLR_HEADER)
                        if len(top) < LAS_EVLR_HEADER:
                            raise CorruptScan(f"{n_evlr} EVLRs stated, they do not fit in the file")
                        pos += LAS_EVLR_HEADER + struct.unpack_from("<Q", top, 20)[0]
                    if pos > size:
                        raise CorruptScan("the EVLRs run past the end of the file")
            compressed = bool(fmt_id & 0x80)
            if compressed:
                _check_laz_chunk_table(fh, offset, size)
    except OSError as exc:
        raise CorruptScan(f"cannot read: {exc.strerror or exc}") from None
    if not compressed and n_points * rec_len > end - offset:
        raise CorruptScan(f"truncated LAS: {n_points} points of {rec_len} bytes need {n_points * rec_len} bytes, "
                          f"{end - offset} present")


def _check_laz_chunk_table(fh, offset: int, size: int) -> None:
    """The LAZ chunk table (its offset is the first 8 bytes of the point data) must lie in the file
    and hold no more chunks than the data has bytes: lazrs allocates 16 bytes per stated chunk
    natively, and a failed native allocation aborts the process instead of raising."""
    fh.seek(offset)
    head = fh.read(8)
    if len(head) < 8:
        raise CorruptScan("LAZ point data has no chunk table offset")
    (table,) = struct.unpack("<q", head)
    if table == -1:
        return  # not written: lazrs walks the chunks
    if not offset + 8 <= table <= size - 8:
        raise CorruptScan(f"LAZ chunk table offset {table} is outside the point data")
    fh.seek(table)
    _, n_chunks = struct.unpack("<II", fh.read(8))
    if n_chunks > table - offset:
        raise CorruptScan(f"LAZ chunk table states {n_chunks} chunks in {table - offset} bytes of point data")


def read_las(path: Path, time_scale: float | None = None) -> RawScan:
    """LAS/LAZ via laspy; `gps_time` is the per-point time (unit guessed unless `time_scale`).

    Points are read in chunks of `LAS_CHUNK_POINTS`, so memory follows the data, not the header's
    count. LAZ is decompressed by single-threaded lazrs: its parallel backend starts a thread pool
    that a forked extraction worker inherits dead (it hangs), and the workers are the parallelism.
    """
    import laspy

    check_las_header(path)
    xyz, inten, raw_t = [], [], []
    try:
        with laspy.open(path, laz_backend=laspy.LazBackend.Lazrs) as reader:
            names = list(reader.header.point_format.dimension_names)
            for chunk in reader.chunk_iterator(LAS_CHUNK_POINTS):
                xyz.append(np.column_stack([np.asarray(chunk.x), np.asarray(chunk.y), np.asarray(chunk.z)]))
                if "intensity" in names:
                    inten.append(np.asarray(chunk.intensity))
                if "gps_time" in names:
                    raw_t.append(np.asarray(chunk.gps_time))
    except Exception as exc:  # laspy/lazrs raise several kinds on a broken file
        raise CorruptScan(f"cannot decode LAS/LAZ: {one_line(exc)}") from None
    points = np.concatenate(xyz) if xyz else np.zeros((0, 3))
    intensity = (np.concatenate(inten) if inten else np.zeros(0, np.uint16)) if "intensity" in names else None
    gps = (np.concatenate(raw_t) if raw_t else np.zeros(0)) if "gps_time" in names else None
    if gps is not None and time_scale is not None:
        times = gps.astype(np.float64) * time_scale
    else:
        times = seconds(gps)
    return RawScan(xyz=points, intensity=intensity, times=times)


def read_ply_scan(path: Path) -> RawScan:
    from lidar2xodr.markings_io import read_ply

    try:
        arr = read_ply(path)
    except InputError as exc:
        raise CorruptScan(exc.problem) from None
    return from_structured(arr, path)


def read_kitti_bin(path: Path) -> RawScan:
    """KITTI Velodyne .bin: float32 x y z reflectance (0..1), no per-point time."""
    data = _read_bytes(path)
    if len(data) % 16:
        raise CorruptScan(f"size {len(data)} bytes is not a multiple of 16 (x y z r float32)")
    pts = np.frombuffer(data, dtype="<f4").reshape(-1, 4)
    return RawScan(xyz=pts[:, :3].astype(np.float64), intensity=pts[:, 3])


def read_npy(path: Path) -> RawScan:
    """.npy: a structured array with named fields, or (N, >=4) columns x y z intensity [time]."""
    from numpy.lib import format as npy

    try:
        with path.open("rb") as fh:
            version = npy.read_magic(fh)
            read_header = npy.read_array_header_1_0 if version == (1, 0) else npy.read_array_header_2_0
            shape, _, dtype = read_header(fh)
            need = int(np.prod(shape, dtype=object)) * dtype.itemsize
            if dtype.hasobject or need > path.stat().st_size - fh.tell():
                raise CorruptScan(f".npy header promises {shape} of {dtype}, more than the file holds")
            fh.seek(0)
            arr = np.load(fh, allow_pickle=False)
    except (OSError, ValueError, EOFError, TypeError) as exc:
        raise CorruptScan(f"cannot decode .npy: {one_line(exc)}") from None
    if arr.dtype.names:
        return from_structured(arr, path)
    if arr.ndim != 2 or arr.shape[1] < 3:
        raise InputError(path, f".npy scan must be (N, 4+) x y z intensity [time], found shape {arr.shape}")
    if arr.shape[1] < 4:
        return RawScan(xyz=arr[:, :3], intensity=None)
    return RawScan(xyz=arr[:, :3], intensity=arr[:, 3], times=seconds(arr[:, 4]) if arr.shape[1] > 4 else None)


def read_scan_file(path: Path) -> RawScan:
    suffix = path.suffix.lower()
    if suffix == ".pcd":
        return read_pcd(path)
    if suffix in (".las", ".laz"):
        return read_las(path)
    if suffix == ".ply":
        return read_ply_scan(path)
    if suffix == ".bin":
        return read_kitti_bin(path)
    if suffix == ".npy":
        return read_npy(path)
    raise InputError(path, f"unknown scan file type {suffix!r} (known: {', '.join(SCAN_SUFFIXES)})")


def scan_files(folder: Path) -> list[Path]:
    """Scan files of the most common supported type in `folder`, in natural (numeric) name order.

    Anything with a scan suffix that is not a folder counts, so that a broken link or an
    unreadable file is reported as a skipped scan instead of vanishing from the drive.
    """
    files = [p for p in folder.iterdir() if p.suffix.lower() in SCAN_SUFFIXES and not p.is_dir()]
    if not files:
        return []
    suffixes = [p.suffix.lower().replace(".laz", ".las") for p in files]
    main = max(sorted(set(suffixes)), key=suffixes.count)
    return sorted((p for p, s in zip(files, suffixes, strict=True) if s == main), key=_natural_key)


def _natural_key(p: Path) -> tuple:
    import re

    return tuple(int(t) if t.isdigit() else t for t in re.split(r"(\d+)", p.name))
