"""Plain data passed between the pipeline stages.

Every stage reads and writes these small dataclasses of numpy arrays, so each stage can be run,
tested, timed and inspected alone. Frames: vehicle frame is ISO 8855 (x forward, y left, z up);
the world frame is a local east-north-up frame whose origin is stored with its geodetic position.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass
class Scan:
    """One LiDAR scan in the sensor frame of the vehicle (x forward, y left, z up).

    `intensity` is normalised to 0..1 (the reader divides by the sensor's own scale).
    `times` are absolute per-point times in seconds (or None); `stamp` is the scan time.
    """

    index: int
    stamp: float
    xyz: np.ndarray  # (N, 3) float64
    intensity: np.ndarray  # (N,) float32 in 0..1
    times: np.ndarray | None = None  # (N,) float64


@dataclass
class Trajectory:
    """Poses of the vehicle frame in the world frame: T_world_vehicle at each time."""

    times: np.ndarray  # (M,)
    poses: np.ndarray  # (M, 4, 4)

    def __len__(self) -> int:
        return len(self.times)

    @property
    def positions(self) -> np.ndarray:
        return self.poses[:, :3, 3]


@dataclass
class GeoOrigin:
    """Geodetic position of the world-frame origin (None when the drive has no GNSS)."""

    lat: float | None = None
    lon: float | None = None
    alt: float = 0.0
    proj: str | None = None  # PROJ string of the local frame, written as OpenDRIVE geoReference


@dataclass
class SensorInfo:
    """What a reader knows about the sensor: preset name, mount pose and nominal range."""

    name: str = "unknown"
    mount: np.ndarray = field(default_factory=lambda: np.eye(4))  # T_vehicle_sensor
    max_range_m: float = 200.0
    intensity_scale: float = 1.0  # raw value that means 100 % reflectivity


@dataclass
class GroundPlanes:
    """Per-scan RANSAC ground plane, kept for superelevation.

    `normals_world` are unit normals (pointing up) in the world frame; `points_world` the point
    of the plane below the vehicle origin; `times` the scan times.
    """

    times: np.ndarray  # (S,)
    normals_world: np.ndarray  # (S, 3)
    points_world: np.ndarray  # (S, 3)


@dataclass
class MarkingCloud:
    """Output of extraction: accumulated lane-marking points in the world frame."""

    xyz: np.ndarray  # (N, 3) float64
    intensity: np.ndarray  # (N,) float32
    scan_index: np.ndarray  # (N,) int32
    time: np.ndarray  # (N,) float64
    planes: GroundPlanes
    trajectory: Trajectory
    origin: GeoOrigin = field(default_factory=GeoOrigin)

    def subset(self, idx: np.ndarray, trajectory: Trajectory | None = None) -> MarkingCloud:
        """The points `idx` (indices or a mask) with the same planes and origin; the trajectory too,
        unless another is given."""
        return MarkingCloud(xyz=np.asarray(self.xyz)[idx], intensity=np.asarray(self.intensity)[idx],
                            scan_index=np.asarray(self.scan_index)[idx], time=np.asarray(self.time)[idx],
                            planes=self.planes, trajectory=self.trajectory if trajectory is None else trajectory,
                            origin=self.origin)


@dataclass
class Candidate:
    """A candidate line: ordered cluster centres chained by SearchMark and Combine."""

    id: int
    centers: np.ndarray  # (n, 3) ordered along the unified direction
    directions: np.ndarray  # (n, 2) unit directions (stabilised)
    cluster_ids: np.ndarray  # (n,) ids of the clusters the centres come from
    superline: int = -1


MARK_TYPES = ("solid", "broken", "none")
TAPER_LANE_TYPES = ("entry", "exit")
"""Lane types of a road's own lanes that begin or end in a taper (LaneSection.lane_types)."""


@dataclass
class Boundary:
    """One lane boundary (a superline), ordered along the road.

    `t` is the signed lateral offset from the reference line (left positive) at the reference
    line's stations `s`; NaN where the boundary does not exist (lane drop, entry/exit lane).
    """

    id: int
    t: np.ndarray  # (M,) aligned with LaneModel.s
    mark_type: str = "solid"  # one of MARK_TYPES; "none": an unpainted border (unpainted_lanes.py)
    mark_width: float = 0.15
    dash_length: float | None = None
    gap_length: float | None = None


@dataclass
class LaneSection:
    """A stretch with a constant set of boundaries (ordered left to right).

    `divider_id` is the boundary that separates the two directions of a road whose carriageways
    are only separated by paint (None: one direction only, e.g. a motorway carriageway beside a
    physical median). Boundaries left of it bound the lanes of the opposite direction.
    `lane_types` names the OpenDRIVE type of each lane, left to right (lane k lies between
    boundary_ids[k] and boundary_ids[k + 1]): "driving", or "entry" / "exit" for an acceleration /
    deceleration lane that ends / begins in a taper; None means every lane is "driving".
    `marks` gives, by boundary id, the mark type of a boundary whose paint in this section differs
    from its own `mark_type` (a road's edge line that goes on as the broken divider of an exit lane
    beside it); None or a missing id: the boundary's own type.
    """

    s_start: float
    s_end: float
    boundary_ids: list[int]
    divider_id: int | None = None
    lane_types: list[str] | None = None
    marks: dict[int, str] | None = None

    def mark_of(self, boundary: Boundary) -> str:
        """The mark type `boundary` has in this section."""
        return (self.marks or {}).get(boundary.id, boundary.mark_type)


@dataclass
class LaneModel:
    """Output of the lanes stage: reference line, boundaries, sections. Read by the exporter."""

    s: np.ndarray  # (M,) stations along the reference line
    reference: np.ndarray  # (M, 3) xyz of the reference line (road centre), z from the markings
    boundaries: list[Boundary]
    sections: list[LaneSection]
    candidates: list[Candidate] = field(default_factory=list)
    origin: GeoOrigin = field(default_factory=GeoOrigin)
    warnings: list[str] = field(default_factory=list)


@dataclass
class RoadLink:
    """Lanes of road `incoming` at its end continue in road `outgoing` at its start (a direct junction).

    Lane k of a section is the lane between its boundary_ids[k] and boundary_ids[k + 1] (left to
    right). `lanes` pairs lane indices of the incoming road's last section with lane indices of the
    outgoing road's first section. `continuation`: the outgoing road is the same carriageway as the
    incoming one (a split of one measured road, its reference line goes on exactly); otherwise one
    of the two is a branch that diverges from (or a ramp that merges into) the other.
    `open_in`: lanes of the incoming road's last section that leave to a road that was not built (a
    branch seen too little to measure): they end at their measured width there, as a lane linked
    into a branch does, instead of closing to width 0. `open_out`: likewise lanes of the outgoing
    road's first section that join from a road that was not built (an on-ramp with one painted
    line): they start at their measured width, as a lane linked from a ramp does, instead of opening
    from width 0.
    """

    incoming: int  # index into RoadNetwork.roads
    outgoing: int
    lanes: list[tuple[int, int]]
    continuation: bool = True
    open_in: list[int] = field(default_factory=list)
    open_out: list[int] = field(default_factory=list)


@dataclass
class RoadNetwork:
    """Output of the lanes stage when the carriageway splits or merges: roads joined by direct junctions.

    A single road is a network with one road and no links. Links that share an incoming road's end
    (a diverge) or an outgoing road's start (a merge) form one junction.
    """

    roads: list[LaneModel]
    links: list[RoadLink] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)
