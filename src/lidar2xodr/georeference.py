"""From a map's local frame to WGS84 longitude/latitude through its OpenDRIVE geoReference (PROJ string).

Only the horizontal part is used: vertical terms (+geoidgrids, +vunits, +geoid_crs) name grid files
that are not installed offline and are dropped, so heights stay the map's own z. A string without
+proj, as CARLA writes it ('+lat_0=49 +lon_0=8'), is read as a transverse Mercator at that point
(WGS84, scale 1), which is how CARLA itself turns its maps into latitude and longitude.
"""

from __future__ import annotations

import numpy as np
import pyproj
from pyproj.exceptions import CRSError, ProjError

from lidar2xodr.data import GeoOrigin
from lidar2xodr.errors import InputError

LOCAL_PLACEHOLDER = "+proj=tmerc +lat_0=0 +lon_0=0 +k=1 +x_0=0 +y_0=0 +ellps=WGS84 +units=m +no_defs"
"""The frame our exporter writes for a drive without GNSS, and the Lanelet2 exporter's default for a
map without geoReference: a transverse Mercator at 0 N, 0 E (the map lies in the Gulf of Guinea)."""

_VERTICAL = ("+geoidgrids", "+vunits", "+geoid_crs")


def origin_proj(origin: GeoOrigin) -> str | None:
    """PROJ string of a local frame's geodetic placement: its own, or a transverse Mercator at its
    lat/lon (what the exporter writes as geoReference); None when the frame has no placement."""
    if origin.proj:
        return origin.proj
    if origin.lat is not None and origin.lon is not None:
        return (f"+proj=tmerc +lat_0={origin.lat!r} +lon_0={origin.lon!r} +k=1 +x_0=0 +y_0=0 +ellps=WGS84 "
                f"+units=m +no_defs")
    return None


def horizontal(geo: str) -> str:
    """The PROJ string without its vertical terms (a bare lat_0/lon_0 becomes a tmerc there)."""
    toks = [tok for tok in geo.split() if not tok.startswith(_VERTICAL)]
    if not any(tok.startswith("+proj=") for tok in toks) and any(tok.startswith("+lat_0=") for tok in toks):
        toks = ["+proj=tmerc", *toks, "+k=1", "+x_0=0", "+y_0=0", "+ellps=WGS84", "+units=m", "+no_defs"]
    return " ".join(toks)


class ToWgs84:
    """Local map x, y (metres) to WGS84 lon, lat (degrees) and back."""

    def __init__(self, geo: str, where: str) -> None:
        try:
            crs = pyproj.CRS.from_user_input(horizontal(geo))
            self._fwd = pyproj.Transformer.from_crs(crs, "EPSG:4326", always_xy=True)
            self._inv = pyproj.Transformer.from_crs("EPSG:4326", crs, always_xy=True)
            lon, lat = self._fwd.transform(0.0, 0.0, errcheck=True)
        except (CRSError, ProjError) as exc:
            raise InputError(where, f"geoReference {geo[:120]!r} is not a usable PROJ string: {exc}") from None
        if not (np.isfinite(lon) and np.isfinite(lat)):
            raise InputError(where, f"geoReference {geo[:120]!r} does not place the map's origin on the earth")
        self.origin_lon, self.origin_lat = float(lon), float(lat)

    def lonlat(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return _transform(self._fwd, x, y)

    def local(self, lon: np.ndarray, lat: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return _transform(self._inv, lon, lat)


def _transform(tr: pyproj.Transformer, a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Arrays in, arrays out (pyproj takes a one-element array for a point and warns on it)."""
    a, b = np.atleast_1d(np.asarray(a, dtype=float)), np.atleast_1d(np.asarray(b, dtype=float))
    if a.size == 1:
        u, v = tr.transform(float(a[0]), float(b[0]))
        return np.array([u]), np.array([v])
    u, v = tr.transform(a, b)
    return np.asarray(u), np.asarray(v)
