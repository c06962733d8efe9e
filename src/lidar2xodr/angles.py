"""Angles: one wrap into [-pi, pi) for headings and their differences, scalars and arrays alike."""

from __future__ import annotations

import math
from typing import TypeVar

import numpy as np

A = TypeVar("A", float, np.ndarray)


def wrap_angle(a: A) -> A:
    """`a` in [-pi, pi) (radians); numpy arrays element-wise."""
    return (a + math.pi) % (2.0 * math.pi) - math.pi
