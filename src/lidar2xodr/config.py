"""The one configuration. Every parameter of the method is named once, with the paper's value.

Values the paper does not give are marked "ours" with the reason in the field description.
Load from YAML/JSON with `Config.load(path)`; every field can be overridden there.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Literal

import yaml
from pydantic import AfterValidator, BaseModel, ConfigDict, Field, ValidationError, model_validator

from lidar2xodr.errors import InputError
from lidar2xodr.scheduler import valid_scheduler


class _Section(BaseModel):
    """A configuration section: unknown keys, NaN and infinities are refused; every range is in its Field."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


PositiveLength = Annotated[float, Field(gt=0, allow_inf_nan=False)]


class ExtractionConfig(_Section):
    """Stage 1 (paper Sec. III-B): per-scan marking extraction and accumulation."""

    max_range_m: float | None = Field(None, gt=0, description="Crop radius; None = the sensor preset's data-sheet "
                                                  "range")
    below_sensor_margin_m: float = Field(0.0, ge=0, description="Keep points this far below the sensor mount height")
    ransac_distance_m: float = Field(0.08, gt=0, description="ours: inlier distance of the ground-plane RANSAC")
    ransac_iterations: int = Field(60, ge=1, description="ours: hypotheses of the vectorised ground-plane RANSAC")
    ground_margin_m: float = Field(0.15, ge=0, description="paper: plane raised by European curb height")
    reflectivity_threshold: float = Field(0.5, ge=0, le=1, description="paper: 50 % reflectivity")
    auto_threshold: bool = Field(True, description="ours: per-drive threshold from the intensity distribution")
    outlier_radius_m: float = Field(0.5, gt=0, description="paper: radius of the outlier removal")
    outlier_min_neighbors: int = Field(4, ge=0, description="paper: fewer neighbours than this are removed")
    max_bad_scan_share: float = Field(0.1, ge=0, le=1, description="ours: abort when more scans than this are "
                                                       "unreadable")
    odometry: Literal["auto", "gnss", "lidar"] = Field("auto", description="auto = GNSS poses when present")
    seed: int = Field(0, ge=0, description="seed of every random choice (RANSAC)")
    ground_below_m: float = Field(0.3, ge=0, description="ours: points this far below the plane still count as road "
                                             "(range noise, crown); deeper ones are ditches or multipath")
    ransac_range_m: float = Field(40.0, gt=0, description="ours: the plane is fitted to ground within this radius "
                                              "(local plane; far points are sparse and bend with the road)")
    ransac_max_tilt_deg: float = Field(15.0, gt=0, le=90, description="ours: plane normals tilted more from vehicle z "
                                                          "are rejected")
    ransac_sample_points: int = Field(1000, ge=3, description="ours: points that score the RANSAC hypotheses")
    auto_threshold_scans: int = Field(10, ge=1, description="ours: scans whose ground intensities set the auto "
                                                "threshold")
    auto_threshold_range_m: float = Field(40.0, gt=0, description="ours: ground points within this radius feed it")
    auto_threshold_mad_k: float = Field(3.0, gt=0, description="ours: the auto threshold is at least median + k "
                                                   "robust sigmas (MAD) of the road intensities: paint is an outlier "
                                                   "of the road")
    pose_time_tolerance_s: float = Field(0.1, ge=0, description="ours: point times may exceed the poses by this much")
    odometry_voxel_m: float = Field(1.0, gt=0, description="ours: KISS-ICP voxel size (highway structure is coarse)")
    odometry_max_range_m: float = Field(200.0, gt=0, description="ours: KISS-ICP uses points within this radius of a "
                                                     "forward-looking sensor (far trees, posts and signs fix its "
                                                     "heading: 80 m drifted 3-10 deg/km on simulated motorways, 200 m "
                                                     "0.1-0.4 deg/km)")
    odometry_surround_range_m: float = Field(80.0, gt=0, description="ours: the same for a sensor whose scans cover "
                                             "more than half the horizon (structure all around fixes the heading)")
    odometry_min_height_m: float = Field(-0.3, description="ours: extraction hands the odometry the points this far "
                                         "above the scan's ground plane (negative: the road too, for odometry_ground)")
    odometry_threshold_m: float | None = Field(1.0, gt=0, description="ours: fixed ICP kernel; None = KISS-ICP "
                                               "adaptive")
    odometry_iterations: int = Field(2, ge=1, description="ours: deskew-and-register rounds per scan")
    odometry_max_speed_mps: float = Field(70.0, gt=0, description="ours: upper end of the start-speed search")
    odometry_bootstrap_s: float = Field(0.3, gt=0, description="ours: time between the two scans of the "
                                        "start-speed search")
    odometry_structure_height_m: float = Field(0.3, gt=0, description="ours: KISS-ICP registers only the points "
                                               "this far above the scan's ground plane (the flat road has no "
                                               "longitudinal structure)")
    odometry_ground: bool = Field(True, description="ours: height, roll and pitch of LiDAR odometry from the road: "
                                  "each scan's road is moved onto the road the scans before it mapped (registration "
                                  "alone drifted 0.3-0.4 deg/km in pitch on simulated motorways)")
    odometry_ground_band_m: float = Field(0.15, gt=0, description="ours: road = points this close to the scan's "
                                          "ground plane")
    odometry_ground_range_m: float = Field(40.0, gt=0, description="ours: ... and this close to the vehicle (where "
                                           "the plane was fitted; simulated 2 km motorways, seed 1, end +0.4..1.0 m "
                                           "high with 35-40 m, +4..6 m with 30 m, +8..14 m with 45 m; seeds 2-3 up "
                                           "to +5.5 m with 40 m: odometry.py)")
    odometry_ground_cell_m: float = Field(2.0, gt=0, description="ours: xy cell of the road map; a cell's plane has "
                                          "the normal of its 3 x 3 neighbourhood")
    odometry_ground_scale_m: float = Field(0.1, gt=0, description="ours: final cut-off of the road fit's Tukey "
                                           "weights (starting at 8 x)")
    odometry_ground_min_cells: int = Field(20, ge=3, description="ours: a scan sharing fewer road cells with the "
                                           "map keeps KISS-ICP's height, roll and pitch")
    auto_method: Literal["local", "drive"] = Field(
        "local", description="ours, with auto_threshold: 'local' = paint is a bright outlier of the road surface "
        "around it (per point: range-, beam- and sensor-independent); 'drive' = one threshold per drive from the "
        "first scans (Otsu / median + k MAD)")
    local_neighbors: int = Field(16, ge=1, description="ours: road-surface samples around a point that judge it")
    local_cell_m: float = Field(0.25, gt=0, description="ours: road-surface samples are taken one per cell of this "
                                            "size, so dense near-range returns on a wide line cannot be their own "
                                            "background")
    local_contrast_k: float = Field(4.0, gt=0, description="ours: paint is this many robust sigmas (MAD) brighter "
                                               "than the median of its surroundings ...")
    local_min_contrast: float = Field(0.08, ge=0, le=1, description="ours: ... and at least this much brighter (0..1 "
                                                        "scale)")
    local_max_radius_m: float = Field(3.0, gt=0, description="ours: a point whose surface samples reach farther than "
                                                 "this has no road around it to compare with (far range, where only "
                                                 "paint returns): the fixed reflectivity_threshold judges it")
    local_max_roughness_m: float = Field(0.02, gt=0, description="ours: robust height spread (MAD) of the "
                                                     "surroundings above which they are not road surface (vegetation, "
                                                     "gravel, kerbs)")
    lateral_crop_m: float | None = Field(20.0, gt=0, description="ours: points farther than this left or right of the "
                                                     "vehicle are dropped (embankments, other roads); None = no crop")
    ground_prior_m: float = Field(0.5, gt=0, description="ours: the ground plane passes within this height of the "
                                             "vehicle origin (on the road by definition of the vehicle frame); RANSAC "
                                             "draws and scores its hypotheses on points this close to z = 0")
    ground_rings: int = Field(3, ge=0, description="ours: range rings beyond ransac_range_m with their own ground "
                                       "plane, each twice as wide as the one before; 0 = one plane per scan (paper)")
    ground_ring_window_m: float = Field(0.5, gt=0, description="ours: a ring's plane is refitted from its points this "
                                                   "close to the plane of the ring before")
    workers: Annotated[int, Field(ge=1)] | Literal["auto"] = Field(
        "auto", description="ours: processes reading and filtering scans in parallel (same bytes as 1); "
        "auto = the CPUs this process may use, at most 8")
    scheduler: Annotated[str | None, AfterValidator(valid_scheduler)] = Field(
        None, description="ours: where the per-scan work runs: None = a process pool of `workers` on this machine; "
        "'local' = a Dask LocalCluster of `workers` processes; a Dask address (tcp://host:8786) = that cluster's "
        "workers, which must see the drive at the same path. Same bytes in every case (lidar2xodr.scheduler)")
    moving_filter: bool = Field(True, description="ours: remove the trails of moving objects (the low, bright rear of "
                                      "a vehicle driving with the ego) from the accumulated marking cloud")
    moving_voxel_m: float = Field(1.0, gt=0, description="ours: a point is transient when its cell of this size (xy) "
                                             "holds points of at most moving_max_scans scans; static paint is "
                                             "re-observed as the sensor approaches it (simple_highway: 2 % of paint, "
                                             "90 % of the trail)")
    moving_max_scans: int = Field(2, ge=1, description="ours: ... at most this many scans")
    moving_link_m: float = Field(1.0, gt=0, description="ours: transient points this close (xy), and within "
                                            "moving_pair_s, are one blob (one object's view)")
    moving_min_scans: int = Field(3, ge=2, description="ours: a trail seed spans at least this many scans")
    moving_min_speed_mps: float = Field(3.0, ge=0, description="ours: a trail seed moves at least this fast (world "
                                                   "frame)")
    moving_min_travel_m: float = Field(3.0, ge=0, description="ours: ... and at least this far over its time span")
    moving_seed_rms_m: float = Field(0.25, gt=0, description="ours: RMS distance along the motion between a seed's "
                                                 "points and its constant-velocity fit (a vehicle's rear is a thin "
                                                 "face moving on a straight space-time line; paint seen through a "
                                                 "detection window scatters by the window's depth); widened by speed "
                                                 "x scan period / sqrt(12) when the points carry only the scan's time")
    moving_gate_m: float = Field(0.5, gt=0, description="ours: a trail grows by transient points within this distance "
                                            "along the motion of its position predicted at their time (widened by "
                                            "speed x scan period / 2 without per-point times) ...")
    moving_half_width_m: float = Field(1.5, gt=0, description="ours: ... and within this distance across it (half a "
                                                  "vehicle width plus margin; a lane line beside a lane-centred car "
                                                  "is 1.75 m away)")
    moving_max_speed_mps: float = Field(70.0, gt=0, description="ours: fastest object followed from one scan's view "
                                                    "of it to the next (world frame)")
    moving_pair_s: float = Field(0.25, gt=0, description="ours: an object that jumps between scans (a spinning sensor "
                                             "hits it in a few ms) is followed from one view to the next this far "
                                             "apart in time (one missed scan at 10 Hz)")
    moving_min_width_m: float = Field(0.1, ge=0, description="ours: a trail narrower than this (RMS across its "
                                                 "motion) is a painted line swept by a moving observation edge, not "
                                                 "an object: it stays (a line 0.1-0.3 m wide: 0.03-0.09 m; a licence "
                                                 "plate 0.15 m); 0 = no width veto")
    moving_paint_radius_m: float = Field(0.5, gt=0, description="ours: a trail point with points of "
                                                    "moving_paint_min_scans other scans this close lies on paint ...")
    moving_paint_min_scans: int = Field(2, ge=1, description="ours: ... (a following car crossing the same spot adds "
                                                 "one scan)")
    moving_on_paint_share: float = Field(0.5, ge=0, description="ours: ... and a trail with this share of such points "
                                                    "is paint swept by a moving observation edge (one ring of a "
                                                    "spinning sensor along a line), not an object: it stays; above 1 "
                                                    "= no paint veto")
    moving_max_gap_s: float = Field(0.5, gt=0, description="ours: a trail ends when no point joins it for this long")
    moving_step_s: float = Field(0.05, gt=0, description="ours: a trail grows by the points it predicts within this "
                                             "time of the next such point, then refits (half a scan period at 10 Hz)")
    moving_fit_window_s: float = Field(1.0, gt=0, description="ours: the trail's velocity is refitted on its points "
                                                  "within this time of its newest (oldest) end while it grows")


class MarkingsConfig(_Section):
    """Stage 2 (paper Alg. 1): clusters, directions, SearchMark, Combine."""

    dbscan_eps_m: float = Field(0.6, gt=0, description="ours: DBSCAN radius; dashes are 0.15-0.3 m wide, 12 m apart")
    dbscan_min_samples: int = Field(5, ge=1, description="ours: DBSCAN core-point neighbours")
    slice_threshold_m: float = Field(30.0, gt=0, description="paper: clusters longer than this are sliced")
    slice_length_m: float = Field(6.0, gt=0, description="paper: slice length (German dash length)")
    line_ransac_distance_m: float = Field(0.1, gt=0, description="ours: inlier distance of the per-cluster line RANSAC")
    gamma: float = Field(0.5, ge=0, le=1, description="paper Eq. 1: direction stabilisation weight")
    search_step_m: float = Field(3.0, gt=0, description="paper: SearchMark step")
    search_max_m: float = Field(27.0, gt=0, description="paper: SearchMark reach (1.5 x dash centre spacing)")
    search_radius_m: float = Field(1.75, gt=0, description="paper: ball radius (half the minimum lane width)")
    combine_search_m: float = Field(63.0, gt=0, description="paper: Combine search beyond each candidate end")
    min_cluster_points: int = Field(5, ge=1, description="ours: smaller clusters are noise")
    dbscan_voxel_m: float = Field(0.2, gt=0, description="ours: DBSCAN runs on point-count-weighted voxel centroids "
                                             "of this size, which bounds its memory on 50 km drives")
    line_ransac_iterations: int = Field(32, ge=1, description="ours: line hypotheses per cluster (vectorised RANSAC)")
    min_direction_length_m: float = Field(1.0, gt=0, description="ours: clusters shorter than this (or than 3x their "
                                                     "width) do not steer SearchMark: their RANSAC direction is noise")
    segment_tolerance_m: float = Field(0.5, gt=0, description="ours: point-to-segment distance that adds a missed "
                                                  "cluster")
    search_z_tolerance_m: float = Field(1.0, gt=0, description="ours: height gate of the ball search (keeps bridges "
                                                   "apart)")
    combine_max_angle_deg: float = Field(30.0, gt=0, le=180, description="ours: candidates meeting at a larger angle "
                                                             "are not combined")
    max_turn_deg: float = Field(10.0, gt=0, le=180, description="ours: a found cluster whose direction turns the "
                                                    "search by more than this keeps the previous direction (stray "
                                                    "blobs beside a line)")
    max_lateral_offset_m: float = Field(0.8, gt=0, description="ours: SearchMark and Combine reject a target farther "
                                                   "than this beside the line extrapolated from the recent centres "
                                                   "(and, in Combine, the source beside the target's extrapolation): "
                                                   "about a third of the minimum lane width, so a link never crosses "
                                                   "to the next lane line")
    seed: int = Field(0, ge=0, description="seed of the line RANSAC")


class LanesConfig(_Section):
    """Stage 3 (paper Alg. 2): relative lookups, superlines, lanes, reference line."""

    lookup_modulo_m: float = Field(3.0, gt=0, description="paper: distance % 3.0 m in the relative lookup")
    max_normal_length_m: float = Field(20.0, gt=0, description="ours: normals look this far left and right")
    min_lane_width_m: float = Field(2.5, gt=0, description="ours: narrower spacings are not lanes")
    narrow_lane_width_m: float = Field(1.8, gt=0, description="ours: where no two lines lie min_lane_width_m-"
                                              "max_lane_width_m apart anywhere, the drive's road is built once "
                                              "more with lanes from this width on (with a warning): below every "
                                              "lane cars use (2.0 m), above the 1.75 m from which a lane counts "
                                              "as open; >= min_lane_width_m turns this off")
    max_lane_width_m: float = Field(5.0, gt=0, description="ours: wider spacings are not one lane")
    station_step_m: float = Field(1.0, gt=0, description="ours: spacing of the reference-line stations")
    min_section_length_m: float = Field(30.0, gt=0, description="ours: shorter lane-count changes are noise")
    carriageway_gap_m: float = Field(10.0, gt=0, description="ours: a wider space between two lines separates "
                                                 "carriageways (an unobserved line between two others leaves two "
                                                 "lanes)")
    max_intersect_angle_deg: float = Field(30.0, gt=0, le=180, description="ours: normals ignore segments crossing at "
                                                               "a larger angle (ramps, crossing lines)")
    z_tolerance_m: float = Field(1.5, gt=0, description="ours: normals ignore lines this much higher or lower "
                                            "(bridges)")
    same_line_tolerance_m: float = Field(0.5, gt=0, description="ours: pieces at the same offset from a shared "
                                                    "neighbour (within this) are one superline; closer parallel lines "
                                                    "are duplicates")
    max_link_gap_m: float = Field(500.0, gt=0, description="ours: the global lookup joins pieces of a line across "
                                               "unobserved stretches up to this long")
    line_join_gap_m: float = Field(40.0, gt=0, description="ours: a fitted line that ends where another begins within "
                                               "this gap, at the same offset, is one line (marking chains break in "
                                               "tight curves and occlusions, all lines at once, where the global "
                                               "lookup has no neighbour)")
    assign_distance_m: float = Field(0.5, gt=0, description="ours: marking points this close to a boundary belong to "
                                                "it")
    double_line_max_spacing_m: float = Field(1.0, gt=0, description="ours: a boundary's points in two parallel modes "
                                                        "at most this far apart (centre to centre) are a double line, "
                                                        "whose boundary is their midpoint; farther apart they are two "
                                                        "boundaries")
    double_line_block_m: float = Field(20.0, gt=0, description="ours: stretch over which a double line's two modes "
                                                  "are counted (a broken line's dash and gap fit in it); a double "
                                                  "line spans three such blocks or more")
    boundary_smoothing_m: float = Field(40.0, gt=0, description="ours: shortest wavelength kept in a boundary's t(s) "
                                                    "(robust Whittaker smoother)")
    shift_smoothing_m: float = Field(12.0, ge=0, description="ours: shortest wavelength kept in the road's "
                                     "common lateral shift (a lane shift moves every line alike, faster than "
                                     "boundary_smoothing_m follows); 0 turns this off")
    reference_smoothing_m: float = Field(60.0, gt=0, description="ours: shortest wavelength kept in the reference line")
    stable_lane_slope: float = Field(0.02, gt=0, le=1, description="ours: a lane is stable where its width changes "
                                                       "less than this per metre; every lane needs a stable stretch "
                                                       "of min_section_length_m")
    end_dash_drift: bool = Field(False, description="ours, experimental (off: BENCHMARKS.md): a line's end dash is "
                                 "judged against the line continued with the other lines' common drift along the "
                                 "frame, not parallel to the frame; builds the drive's first ~100 m where the frame "
                                 "runs at an angle to the road, but 12 of 112 sweep cases get worse")
    max_taper_length_m: float = Field(300.0, gt=0, description="ours: longest lane taper followed back to zero width")
    taper_min_length_m: float = Field(20.0, gt=0, description="ours: a straight line converging onto (diverging from) "
                                                  "the carriageway's right edge makes an entry (exit) lane only when "
                                                  "marking points lie on it at stations spanning this much road")
    taper_max_slope: float = Field(0.2, gt=0, le=1, description="ours: steepest taper (width change per metre, ~11 "
                                                    "deg); the flattest is stable_lane_slope (flatter lines run "
                                                    "beside the road: guard rails)")
    taper_line_tolerance_m: float = Field(0.3, gt=0, description="ours: points within this of a straight taper line "
                                                     "lie on it; their RMS distance must stay below half of it (one "
                                                     "consistent angle of convergence, not clutter)")
    taper_meet_width_m: float = Field(1.5, gt=0, description="ours: a taper line must be seen this close to the edge "
                                                 "it meets; the meeting point is extrapolated along the line from "
                                                 "there")
    taper_max_gap_m: float = Field(15.0, gt=0, description="ours: a taper line is followed across unobserved "
                                               "stretches up to this long (a broken line's gap, an occlusion)")
    solid_min_run_m: float = Field(20.0, gt=0, description="ours: painted runs longer than this (length-weighted "
                                               "median) make a solid line")
    mark_stretch_min_m: float = Field(40.0, gt=0, description="ours: a line's paint is typed again in each lane "
                                      "section where its points there span this much (two periods of a 6 m dash "
                                      "and 12 m gap): a road's solid edge goes on as an exit lane's broken divider; "
                                      "a shorter stretch keeps the type of the whole line")
    divider_min_length_m: float = Field(300.0, gt=0, description="ours: a solid line with lanes on both sides that "
                                                     "the ego never crosses separates the two directions when it is "
                                                     "that long")
    divider_short_share: float = Field(0.75, ge=0, le=1, description="ours: on a road shorter than "
                                                         "divider_min_length_m, a line separates the two directions "
                                                         "when it has lanes on both sides and the ego drove both ways "
                                                         "beside it (along s right of it, against s left of it), each "
                                                         "over this share of the road's length")
    divider_max_wrong_side_m: float = Field(10.0, gt=0, description="ours: stations with the ego on the wrong side of "
                                                        "a divider candidate it may have (projection noise at a "
                                                        "U-turn); a lane change across it lasts far longer")
    traffic_directions: bool = Field(True, description="ours: lanes with oncoming recorded traffic (the drive's "
                                           "object list) left of lanes with traffic along the drive make a two-way "
                                           "road where paint and ego gave no divider (lane_directions.py)")
    unpainted_lanes: bool = Field(True, description="ours: a broken line always has a lane on both sides: where the "
                                        "outermost line is broken (dash pattern measured), the lane beyond it is built "
                                        "at its neighbour's width with an unpainted border (unpainted_lanes.py)")
    traffic_min_m: float = Field(40.0, gt=0, description="ours: metres of tracked traffic in a lane that decide its "
                                             "direction")
    traffic_share: float = Field(0.8, ge=0, le=1, description="ours: share of a lane's tracked traffic that must run "
                                                  "one way")
    traffic_min_speed_mps: float = Field(3.0, ge=0, description="ours: slower track samples say nothing about a "
                                                    "direction")
    branch_widening_m: float = Field(1.0, gt=0, description="ours: an outermost lane wider than its median width by "
                                                "this at a section end (start) leaves (joins) the road: a split, exit "
                                                "or merge")
    branch_window_m: float = Field(120.0, gt=0, description="ours: a branch is measured from the markings within this "
                                                "distance of its junction (a sensor beside it sees no farther; "
                                                "clutter beyond would bend its road axis)")
    branch_min_line_m: float = Field(10.0, gt=0, description="ours: a branch is measured only from the points of "
                                                 "marking lines (candidates) spanning at least this; shorter paint "
                                                 "(clutter at a U-turn, arrows, blobs) would bend its road axis")
    branch_min_length_m: float = Field(30.0, gt=0, description="ours: a leaving or joining lane becomes a road of its "
                                                   "own when its markings give lanes over at least this length")


    @model_validator(mode="after")
    def _widths_ordered(self) -> LanesConfig:
        if self.min_lane_width_m >= self.max_lane_width_m:
            raise ValueError(f"min_lane_width_m ({self.min_lane_width_m}) must be below max_lane_width_m "
                             f"({self.max_lane_width_m})")
        return self


class ExportConfig(_Section):
    """Stage 4 (paper Alg. 3): OpenDRIVE export."""

    piece_length_m: float = Field(100.0, gt=0, description="paper: paramPoly3 piece length")
    look_fraction: float = Field(0.125, gt=0, le=0.5, description="paper: look-ahead/back = 1/8 piece length")
    endpoint_weight: float = Field(10.0, gt=0, description="ours: weight of the first and last marking in the fit")
    opendrive_minor: int = Field(8, ge=0, le=8, description="OpenDRIVE 1.x; >= 7 so the ASAM checker applies its rules")
    road_name: str = Field("lidar2xodr", description="name of the written road")
    road_type: Literal["unknown", "rural", "motorway", "town"] = Field(
        "motorway", description="ours: OpenDRIVE road type (the paper's drives are motorways)")
    lane_record_m: float = Field(25.0, gt=0, description="ours: length of the laneOffset/width cubic records")
    taper_length_m: float = Field(60.0, gt=0, description="ours: an appearing lane whose markings start at full width "
                                              "opens from 0 over this length (ends likewise); markings "
                                              "under half the width over its first tenth and at 90 % of "
                                              "it only after half of it are followed as measured")
    right_shoulder_m: float = Field(0.0, ge=0, description="ours: width of a 'shoulder' lane outside the right edge "
                                               "line; 0 = none (not measured, so off by default)")
    left_border_m: float = Field(0.0, ge=0, description="ours: width of a 'border' lane left of the leftmost line; 0 "
                                            "= none")
    elevation_record_m: float | None = Field(None, ge=5.0, description="ours: length of the elevation cubic records "
                                                           "(C2 spline); None = the paper's one cubic per planView "
                                                           "piece, which misses vertical curves shorter than a piece")
    superelevation_median_scans: int = Field(9, ge=1, description="ours: running median over the per-scan roll angles")
    superelevation_smoothing: float = Field(0.01, ge=0, description="ours: P-spline penalty of the superelevation fit")
    plane_max_offset_m: float = Field(15.0, gt=0, description="ours: ground planes farther from the reference are "
                                                  "ignored")
    junction_blend_m: float = Field(30.0, gt=0, description="ours: a branch road is bent onto the road it leaves or "
                                    "joins over this length from the junction (or its whole length if shorter)")
    fold_appearing_lanes: bool = Field(False, description="ours, opt-in: an outer lane that opens from width 0 "
                                       "stays in the section before at width 0 instead of starting a section. Off "
                                       "by default: a lane exists where it has width (plus its taper); the fold "
                                       "silences SUMO's 'not connected from any incoming edge' warning but CARLA "
                                       "spawns vehicles on the zero-width lane and SUMO 1.28 makes it a 1.8 m lane "
                                       "(see export_sections.py)")
    connecting_road_m: float = Field(20.0, gt=0, description="ours: length of a connecting road cut from the road "
                                     "end at a classic junction (at most its end lane section and half the road)")


class EvaluationConfig(_Section):
    """The paper's parametrisation-invariant lateral distance."""

    sample_step_m: float = Field(0.5, gt=0, description="ours: uniform sampling of both maps")
    near_m: float = Field(3.0, gt=0, description="ours: reference samples farther than this from the generated map's "
                                     "carriageway edge are outside the evaluated part (see README)")
    heading_tolerance_deg: float = Field(45.0, gt=0, le=180, description="ours: lines are matched only to lines whose "
                                                             "travel direction differs by at most this (keeps the "
                                                             "opposite carriageway out)")
    lane_count_min_width_m: float = Field(1.75, gt=0, description="ours: narrower driving lanes (opening or closing "
                                          "tapers) are not counted; half the paper's 3.5 m lane")
    mark_match_m: float = Field(1.0, gt=0, description="ours: a generated boundary sample's road mark is compared "
                                "with its nearest reference boundary's when that lies this close (lines of a "
                                "road lie 2 m or more apart, so the nearest one within 1 m is the same line)")
    lane_graph_step_m: float = Field(0.5, gt=0, description="ours: lane-graph agreement follows each reference "
                                     "lane centre in steps of this length; a tenth of a 6 m dash, so no lane "
                                     "section or link change is stepped over")
    lane_graph_min_width_m: float = Field(1.75, gt=0, description="ours: a generated lane narrower than this where "
                                          "it holds a reference lane's centre is not a lane there (half the "
                                          "paper's 3.5 m lane; issue #13's 0.54 m sliver is far below it)")
    lane_graph_taper_m: float = Field(60.0, ge=0, description="ours: a narrower generated lane still counts within "
                                      "this length of its lane's first or last end (an opening or closing taper; "
                                      "issue #13's 60 m, a little under roadgen's 70 m motorway taper)")


class ScenarioConfig(_Section):
    """OpenSCENARIO of the recorded traffic: track cleaning, association, replay and manoeuvres."""

    osc_minor_version: int = Field(2, ge=2, le=3, description="ours: OpenSCENARIO 1.x (1.2: widest support)")
    map_sample_step_m: float = Field(0.5, gt=0, description="ours: sampling of the map for z and lane lookup")
    off_map_margin_m: float = Field(0.5, ge=0, description="ours: this far outside the outer border = off the map")
    vertex_tolerance_m: float = Field(0.05, gt=0, description="ours: polyline vertices kept until replay error < this")
    vertex_yaw_tolerance_rad: float = Field(0.02, gt=0, description="ours: same for the heading")
    min_track_samples: int = Field(5, ge=1, description="ours: shorter tracks are dropped")
    min_track_duration_s: float = Field(0.5, gt=0, description="ours: shorter tracks are dropped")
    max_gap_s: float = Field(1.0, gt=0, description="ours: a track is split where no sample arrives for longer")
    spike_m: float = Field(2.0, gt=0, description="ours: this far from the neighbours' robust prediction = spike")
    max_spike_share: float = Field(0.3, ge=0, le=1, description="ours: a larger share of spikes drops the track "
                                                    "(jumpy)")
    max_speed_mps: float = Field(80.0, gt=0, description="ours: faster implied motion between samples splits a track")
    gate_m: float = Field(3.0, gt=0, description="ours: association gate (doubled for 1-sample tracks)")
    heading_min_speed_mps: float = Field(1.0, ge=0, description="ours: slower: box yaw; faster: motion direction")
    spawn_tolerance_s: float = Field(0.2, ge=0, description="ours: tracks starting this early go into Init")
    lane_change_dwell_s: float = Field(1.0, ge=0, description="ours: a lane must be held this long to count "
                                                  "(hysteresis)")
    lane_change_margin_m: float = Field(0.5, gt=0, description="ours: the centre must get this deep into the new lane")
    cut_in_range_m: float = Field(50.0, gt=0, description="task: a cut-in/out happens within this distance ahead of "
                                              "the ego")
    ego_dims_m: tuple[PositiveLength, PositiveLength, PositiveLength] = Field((4.9, 1.9, 1.5), description="ours: ego "
                                                                                               "length, width, height")
    ego_center_x_m: float = Field(0.0, description="ours: box centre ahead of the ego pose origin")
    gnss_smoothing_s: float = Field(2.0, gt=0, description="ours: time scale of GNSS correction of dead reckoning")
    class_map: dict[str, str] = Field(default_factory=dict, description="raw class -> category, e.g. {'7': 'car'}")
    drop_off_map: bool = Field(False, description="ours: drop tracks that never touch the map (default: keep, warn)")


class ReportConfig(_Section):
    """The build report: what is drawn, and how much of it, so a 10 km drive's page stays quick to open."""

    map_step_m: float = Field(2.0, gt=0, description="ours: lane borders of the written map sampled this often "
                              "for the drawing (chord error below 1 cm on radii over 50 m)")
    max_cloud_points: int = Field(30_000, ge=0, description="ours: at most this many marking points on the map "
                                  "(evenly thinned beyond; an SVG plot stays responsive up to a few 10k points)")
    cloud_cell_m: float = Field(0.25, gt=0, description="ours: marking points are thinned to one per cell of this "
                                "size first (finer than a marking's 0.15 m width adds nothing visible)")
    closeup_m: float = Field(160.0, gt=0, description="ours: width of a close-up window (a gore with its taper, "
                             "or a lane that opens over ~100 m, fits in)")
    max_closeups: int = Field(24, ge=0, description="ours: close-up pictures drawn (all junctions and lane-count "
                              "changes beyond this are still listed and zoom the main map)")
    reference_margin_m: float = Field(100.0, ge=0, description="ours: the reference map is drawn only this far "
                                      "around the generated map (a reference network may be far larger)")
    lane_hover_step_m: float = Field(25.0, gt=0, description="ours: spacing of the points that name a lane "
                                     "(road, id, type, width) when the pointer rests on it")


class CheckConfig(_Section):
    """`check`: lane widths a map should not have (issue #13: sliver lanes, zero-width lanes kept long, lanes
    wider than any lane)."""

    narrow_lane_m: float = Field(1.0, gt=0, description="ours: a driving lane narrower than this holds no car "
                                 "(~1.9 m wide); warned about where it stays so over more than narrow_lane_max_m")
    narrow_lane_max_m: float = Field(30.0, gt=0, description="ours: longest narrow stretch outside a taper not "
                                     "warned about (about 1 s at motorway speed)")
    taper_m: float = Field(60.0, gt=0, description="ours: a lane whose width goes to or from 0 at a lane section's "
                           "start or end is a taper over its first or last this many metres (compare's lane-graph "
                           "rule)")
    zero_width_m: float = Field(0.05, gt=0, description="ours: a lane narrower than this has zero width: it exists "
                                "only for a reader's sake (no paint, no room)")
    zero_width_max_m: float = Field(30.0, gt=0, description="ours: longest zero-width stretch not warned about (a "
                                    "taper's first metre is far shorter)")
    width_step_m: float = Field(0.5, gt=0, description="ours: lane widths are sampled this often along each section")
    wide_lane_m: float = Field(5.0, gt=0, description="ours: a driving lane wider than this is two lanes built as one "
                               "or has a border that left the road (motorway lanes are 3.5-3.75 m, ramps in tight "
                               "curves up to ~4.5 m); as lanes.max_lane_width_m, the widest spacing of one lane")
    wide_lane_max_m: float = Field(30.0, gt=0, description="ours: longest wide stretch not warned about (about 1 s "
                                   "at motorway speed, as narrow_lane_max_m)")


class InterchangeConfig(_Section):
    """Lanelet2 and GeoJSON copies of an OpenDRIVE map (export_lanelet2.py, export_geojson.py)."""

    sample_step_m: float = Field(1.0, gt=0, description="ours: lane borders are sampled at most this far apart "
                                 "along the road; on a 250 m radius a 1 m chord is 0.5 mm off the arc")
    join_tolerance_m: float = Field(0.1, gt=0, description="ours: the ends of two linked lanes this close become "
                                    "one point, so Lanelet2 routes from one to the other; farther apart they stay "
                                    "apart with a warning (a gap in the map, not ours to close)")
    min_lanelet_length_m: float = Field(0.01, ge=0, description="ours: a lane section shorter than this (CARLA's "
                                        "Town04 has some of 1e-7 m) gets no lanelets: the lanelets before and after "
                                        "it meet; Lanelet2's .osm keeps ~1 um, so shorter ones lose their direction")
    default_location: Literal["urban", "nonurban"] = Field(
        "nonurban", description="ours: Lanelet2 location of a road whose OpenDRIVE <type> does not say (town* and "
        "lowSpeed types are urban, the rest nonurban)")
    geojson_decimals: int = Field(8, ge=7, le=12, description="ours: decimals of GeoJSON longitudes and latitudes; "
                                  "8 is about 1 mm, RFC 7946's 6 (10 cm) would move lane borders visibly")


class FusionConfig(_Section):
    """Several drives in one build (fusion.py): each aligned to the drives before it by its markings."""

    search_radius_m: float = Field(3.0, gt=0, description="ours: largest horizontal GNSS disagreement between two "
                                   "drives that the alignment searches (GNSS without corrections: 1-2 m)")
    coarse_step_m: float = Field(0.5, gt=0, description="ours: grid step of the first offset search")
    fine_step_m: float = Field(0.1, gt=0, description="ours: grid step of the second search, around the first's best")
    inlier_m: float = Field(0.15, gt=0, description="ours: a marking point matches when a fused one is this close "
                            "(about a marking's width)")
    max_correspondence_m: float = Field(0.3, gt=0, description="ours: ICP pairs points at most this far apart "
                                        "after the grid search")
    voxel_m: float = Field(0.25, gt=0, description="ours: the alignment uses one marking point per cell of this size")
    max_search_points: int = Field(8000, ge=100, description="ours: the grid search scores at most about this many "
                                   "points (an even sample along the drive)")
    min_overlap_points: int = Field(200, ge=1, description="ours: a drive sharing fewer sampled marking points with "
                                    "the drives before (within search_radius_m) is left out: no overlap")
    min_inlier_share: float = Field(0.3, ge=0, le=1, description="ours: a drive whose aligned markings match fewer "
                                    "of its points than this is left out (it cannot be aligned)")
    anchor: int | None = Field(None, ge=1, description="ours: the drive (1 = the first given) whose GNSS places the "
                               "fused map, e.g. the one recorded with RTK corrections; none: the mean of all drives")


class Config(_Section):
    extraction: ExtractionConfig = ExtractionConfig()
    markings: MarkingsConfig = MarkingsConfig()
    lanes: LanesConfig = LanesConfig()
    export: ExportConfig = ExportConfig()
    evaluation: EvaluationConfig = EvaluationConfig()
    scenario: ScenarioConfig = ScenarioConfig()
    report: ReportConfig = ReportConfig()
    check: CheckConfig = CheckConfig()
    interchange: InterchangeConfig = InterchangeConfig()
    fusion: FusionConfig = FusionConfig()

    @classmethod
    def load(cls, path: str | Path | None) -> Config:
        if path is None:
            return cls()
        path = Path(path)
        if path.is_dir():
            raise InputError(path, "is a folder, not a configuration file")
        try:
            raw = yaml.safe_load(path.read_text(encoding="utf-8"))
        except FileNotFoundError:
            raise InputError(path, "configuration file not found") from None
        except UnicodeDecodeError:
            raise InputError(path, "cannot read configuration: not a text (UTF-8) file") from None
        except (OSError, yaml.YAMLError) as exc:
            raise InputError(path, f"cannot read configuration: {' '.join(str(exc).split())}") from None
        raw = {} if raw is None else raw
        if not isinstance(raw, dict):
            raise InputError(path, f"the configuration must be a mapping of sections, got {type(raw).__name__}")
        try:
            return cls.model_validate(raw)
        except ValidationError as exc:
            err = exc.errors()[0]
            skip = ("function-", "literal[", "constrained-")
            loc = ".".join(str(p) for p in err["loc"] if not str(p).startswith(skip))
            got = f" (got {err['input']!r})" if "input" in err and not isinstance(err["input"], dict) else ""
            raise InputError(path, f"configuration field {loc}: {err['msg']}{got}") from None
