"""lanes.json: the LaneModel written and read (format `FORMAT`)."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from lidar2xodr.data import MARK_TYPES, Boundary, Candidate, GeoOrigin, LaneModel, LaneSection
from lidar2xodr.errors import InputError
from lidar2xodr.fileio import write_text
from lidar2xodr.lanes.tapers import LANE_TYPES

FORMAT = "lidar2xodr.lanes/1"


def _num(a: np.ndarray) -> list:
    """Array as nested lists with NaN as null (JSON has no NaN)."""
    arr = np.asarray(a, dtype=np.float64)
    return (
        [None if not math.isfinite(v) else float(v) for v in arr.ravel()]
        if arr.ndim == 1
        else [_num(row) for row in arr]
    )


def save_lanes(model: LaneModel, path: str | Path, network: dict | None = None) -> None:
    """Write the lane model as JSON (format `lidar2xodr.lanes/1`, NaN written as null), atomically.

    Each section carries `divider_id` (null: one direction), `lane_types` (one of `LANE_TYPES` per
    lane, left to right; null: every lane driving) and `marks` (boundary id -> mark type where the
    section's paint differs from the boundary's; null: none differs); files written before them load
    with no divider, driving lanes and the boundaries' own marks. `network` (from
    `branches.save_network`) adds the roads and junction links of a carriageway that splits or
    merges; readers of the single road ignore it."""
    data = model_dict(model)
    if network is not None:
        data["network"] = network
    write_text(path, json.dumps(data, separators=(",", ":"), sort_keys=True) + "\n")


def model_dict(model: LaneModel) -> dict:
    """The JSON-ready dictionary of one lane model (NaN as null)."""
    return {
        "format": FORMAT,
        "s": _num(model.s),
        "reference": _num(model.reference),
        "boundaries": [
            {
                "id": b.id,
                "t": _num(b.t),
                "mark_type": b.mark_type,
                "mark_width": float(b.mark_width),
                "dash_length": b.dash_length,
                "gap_length": b.gap_length,
            }
            for b in model.boundaries
        ],
        "sections": [
            {
                "s_start": sec.s_start,
                "s_end": sec.s_end,
                "boundary_ids": list(sec.boundary_ids),
                "divider_id": sec.divider_id,
                "lane_types": None if sec.lane_types is None else list(sec.lane_types),
                "marks": None if not sec.marks else {str(k): v for k, v in sorted(sec.marks.items())},
            }
            for sec in model.sections
        ],
        "candidates": [
            {
                "id": c.id,
                "superline": c.superline,
                "centers": _num(c.centers),
                "directions": _num(c.directions),
                "cluster_ids": [int(i) for i in c.cluster_ids],
            }
            for c in model.candidates
        ],
        "origin": {
            "lat": model.origin.lat,
            "lon": model.origin.lon,
            "alt": model.origin.alt,
            "proj": model.origin.proj,
        },
        "warnings": list(model.warnings),
    }


def _arr(value: object, shape_tail: tuple[int, ...], where: str, name: str) -> np.ndarray:
    try:
        arr = np.array(
            [[np.nan if v is None else v for v in row] for row in value]
            if shape_tail
            else [np.nan if v is None else v for v in value],
            dtype=np.float64,
        )  # type: ignore[union-attr]
    except (TypeError, ValueError):
        raise InputError(where, f"{name} is not a list of numbers") from None
    if len(arr) == 0 and shape_tail:
        arr = arr.reshape(0, *shape_tail)
    if arr.shape[1:] != shape_tail:
        raise InputError(
            where,
            f"{name} has shape {arr.shape}, expected (n, {', '.join(map(str, shape_tail))})"
            if shape_tail
            else f"{name} has shape {arr.shape}, expected (n,)",
        )
    return arr


def _lane_types(value: object, n_lanes: int, where: str) -> list[str] | None:
    """A section's lane types as read (absent or null: every lane driving, as files written before them)."""
    if value is None:
        return None
    if not isinstance(value, list) or len(value) != n_lanes or not all(v in LANE_TYPES for v in value):
        raise InputError(where, f"lane_types {value!r} is not a list of {n_lanes} of {', '.join(LANE_TYPES)}")
    return [str(v) for v in value]


def _section_marks(value: object, ids: list[int], where: str) -> dict[int, str] | None:
    """A section's marks as read (absent or null: the boundaries' own, as files written before them)."""
    if value is None:
        return None
    try:
        marks = {int(k): v for k, v in value.items()}  # type: ignore[attr-defined]
    except (AttributeError, TypeError, ValueError):
        marks = None
    if marks is None or not all(k in ids and v in MARK_TYPES for k, v in marks.items()):
        raise InputError(where, f"marks {value!r} is not a map of the section's boundary ids to "
                                f"{', '.join(MARK_TYPES)}")
    return {k: str(v) for k, v in marks.items()} or None


def load_lanes(path: str | Path) -> LaneModel:
    """Read lanes.json written by `save_lanes`; InputError naming the file and element when malformed."""
    return model_from(read_lanes_json(path), path)


def read_lanes_json(path: str | Path) -> dict:
    """The parsed lanes.json, checked to be a lane model; InputError naming the file otherwise."""
    path = Path(path)
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise InputError(path, "lane model not found") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise InputError(path, f"cannot read the lane model: {exc}") from None
    if not isinstance(data, dict) or data.get("format") != FORMAT:
        raise InputError(path, f"not a lane model (expected format {FORMAT!r})")
    return data


def model_from(data: dict, path: str | Path) -> LaneModel:
    """A lane model from its dictionary (`model_dict`); InputError naming `path` when malformed."""
    try:
        s = _arr(data["s"], (), str(path), "s")
        ref = _arr(data["reference"], (3,), str(path), "reference")
        if len(ref) != len(s):
            raise InputError(path, f"reference has {len(ref)} rows for {len(s)} stations")
        boundaries = []
        for i, b in enumerate(data["boundaries"]):
            where = f"{path} boundary {b.get('id', i)}"
            t = _arr(b["t"], (), where, "t")
            if len(t) != len(s):
                raise InputError(where, f"t has {len(t)} values for {len(s)} stations")
            if b["mark_type"] not in MARK_TYPES:
                raise InputError(where, f"mark_type {b['mark_type']!r} (solid, broken or none)")
            boundaries.append(
                Boundary(
                    int(b["id"]),
                    t,
                    str(b["mark_type"]),
                    float(b["mark_width"]),
                    None if b["dash_length"] is None else float(b["dash_length"]),
                    None if b["gap_length"] is None else float(b["gap_length"]),
                )
            )
        ids = {b.id for b in boundaries}
        sections = []
        for j, sec in enumerate(data["sections"]):
            bad = [i for i in sec["boundary_ids"] if i not in ids]
            if bad:
                raise InputError(f"{path} section {j}", f"names unknown boundaries {bad}")
            divider = sec.get("divider_id")
            if divider is not None and divider not in sec["boundary_ids"][1:-1]:
                raise InputError(
                    f"{path} section {j}", f"divider_id {divider} is not an inner boundary of the section"
                )
            sections.append(
                LaneSection(
                    float(sec["s_start"]),
                    float(sec["s_end"]),
                    [int(i) for i in sec["boundary_ids"]],
                    None if divider is None else int(divider),
                    _lane_types(sec.get("lane_types"), len(sec["boundary_ids"]) - 1, f"{path} section {j}"),
                    _section_marks(sec.get("marks"), [int(i) for i in sec["boundary_ids"]], f"{path} section {j}"),
                )
            )
        candidates = []
        for c in data["candidates"]:
            where = f"{path} candidate {c.get('id')}"
            candidates.append(
                Candidate(
                    int(c["id"]),
                    _arr(c["centers"], (3,), where, "centers"),
                    _arr(c["directions"], (2,), where, "directions"),
                    np.asarray(c["cluster_ids"], dtype=np.int64),
                    int(c["superline"]),
                )
            )
        o = data["origin"]
        origin = GeoOrigin(o["lat"], o["lon"], float(o["alt"]), o["proj"])
        warnings = [str(w) for w in data["warnings"]]
    except (KeyError, TypeError, AttributeError) as exc:
        raise InputError(path, f"malformed lane model: missing or wrong field {exc}") from None
    return LaneModel(
        s=s,
        reference=ref,
        boundaries=boundaries,
        sections=sections,
        candidates=candidates,
        origin=origin,
        warnings=warnings,
    )
