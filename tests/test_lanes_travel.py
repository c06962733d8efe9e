"""The travel direction of a lane model comes from where the ego drives on the road axis."""

from __future__ import annotations

import numpy as np

from lidar2xodr.config import LanesConfig
from lidar2xodr.lanes.frame import Frame
from lidar2xodr.lanes.tapers import _travel_sign

REACH = LanesConfig().max_normal_length_m


def _axis() -> Frame:
    return Frame(np.stack([np.linspace(0.0, 400.0, 201), np.zeros(201)], axis=1), 1.0)


def _path(*legs: tuple[tuple[float, float], tuple[float, float]]) -> np.ndarray:
    """Straight legs sampled every metre, one after the other."""
    parts = []
    for a, b in legs:
        n = int(np.hypot(b[0] - a[0], b[1] - a[1]))
        parts.append(np.linspace(a, b, n + 1)[:-1])
    return np.vstack(parts)


def test_the_direction_is_that_of_the_ego_on_the_axis_not_on_a_street_beside_it() -> None:
    """Town04: a street 100 m beside the axis, driven against it, then the road itself, driven along it.
    Every point of the street has its foot inside the axis; only the drive on the road counts."""
    ego = _path(((350.0, 100.0), (50.0, 100.0)), ((50.0, 100.0), (20.0, 0.0)), ((20.0, 0.0), (380.0, 0.0)))
    assert _travel_sign(_axis(), ego, REACH) == 1
    assert _travel_sign(_axis(), ego[::-1], REACH) == -1


def test_a_crossing_street_does_not_decide_the_direction() -> None:
    """Crossing the axis nearly at right angles (x falling 10 m on the way) before coming back onto it
    from the side and driving along it."""
    ego = _path(((200.0, -60.0), (190.0, 60.0)), ((190.0, 60.0), (100.0, 60.0)), ((100.0, 60.0), (100.0, 3.0)),
                ((100.0, 3.0), (380.0, 3.0)))
    assert _travel_sign(_axis(), ego, REACH) == 1


def test_the_direction_of_a_drive_along_the_axis_is_its_own() -> None:
    ego = _path(((10.0, -1.8), (390.0, -1.8)))
    assert _travel_sign(_axis(), ego, REACH) == 1
    assert _travel_sign(_axis(), ego[::-1], REACH) == -1
    assert _travel_sign(_axis(), None, REACH) == 1
