"""Folding an appearing outer lane into the section before: same borders, fewer sections, SUMO reads it cleanly."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from lxml import etree

from lidar2xodr.check import check_file, run_netconvert
from lidar2xodr.config import ExportConfig
from lidar2xodr.data import Boundary, LaneModel, LaneSection
from lidar2xodr.export_opendrive import export_opendrive
from lidar2xodr.export_sections import fold_appearing_lanes
from lidar2xodr.opendrive import OpenDriveMap

LANE = 3.5


def _road(appear: tuple[float, float] = (300.0, 80.0)) -> LaneModel:
    """A straight 3-lane carriageway; an exit lane right of it opens from width 0 at `appear` (start, taper)."""
    s = np.arange(0.0, 801.0, 1.0)
    ref = np.stack([s, 0.2 * np.sin(s / 200.0), 0.01 * s], axis=1)
    ts = [1.5 * LANE - i * LANE for i in range(4)]
    bounds = [Boundary(i, np.full(len(s), t), "solid" if i == 0 else "broken", 0.15, 6.0 if i else None,
                       12.0 if i else None) for i, t in enumerate(ts)]
    a, taper = appear
    d = np.clip((s - a) / taper, 0.0, 1.0)
    w = np.where(s >= a, LANE * d * d * (3 - 2 * d), np.nan)
    bounds.append(Boundary(4, ts[3] - w, "solid", 0.3))
    sections = [LaneSection(0.0, a, [0, 1, 2, 3]), LaneSection(a, 800.0, [0, 1, 2, 3, 4])]
    return LaneModel(s=s, reference=ref, boundaries=bounds, sections=sections)


def _write(tmp_path: Path, model: LaneModel, fold: bool, name: str) -> Path:
    path = tmp_path / name
    export_opendrive(model, None, ExportConfig(fold_appearing_lanes=fold), path)
    return path


def _borders(path: Path, s: np.ndarray) -> dict[int, np.ndarray]:
    """t of every right lane's outer border at stations s (NaN where the lane does not exist)."""
    road = OpenDriveMap.load(path).roads["1"]
    return {lid: road.border_t(s, lid) for lid in (-1, -2, -3, -4)}


def test_folded_lane_has_the_same_borders_in_one_section_fewer(tmp_path: Path) -> None:
    model = _road()
    plain, folded = _write(tmp_path, model, False, "plain.xodr"), _write(tmp_path, model, True, "folded.xodr")
    n_plain = len(etree.parse(str(plain)).getroot().findall("road/lanes/laneSection"))
    secs = etree.parse(str(folded)).getroot().findall("road/lanes/laneSection")
    assert (n_plain, len(secs)) == (2, 1)
    new = secs[0].find("right/lane[@id='-4']")
    assert new is not None and new.find("link/predecessor") is None
    assert new.find("roadMark").get("type") == "none"  # the edge line is drawn once before the lane opens
    s = np.arange(0.5, 800.0, 2.0)
    a, b = _borders(plain, s), _borders(folded, s)
    for lid in (-1, -2, -3):
        np.testing.assert_allclose(b[lid], a[lid], atol=1e-6)
    after = s >= 300.0
    np.testing.assert_allclose(b[-4][after], a[-4][after], atol=1e-6)
    np.testing.assert_allclose(b[-4][~after], b[-3][~after], atol=1e-9)  # width 0 before it opens
    assert np.isnan(a[-4][~after]).all()


def test_folded_map_is_valid_and_sumo_reads_it_without_warning(tmp_path: Path) -> None:
    folded = _write(tmp_path, _road(), True, "folded.xodr")
    verdict = check_file(folded)
    assert verdict["ok"] and verdict["asam"]["errors"] == 0, verdict["reasons"]
    assert verdict["asam"]["warnings"] == 0, verdict["asam"]["issues"][:5]
    sumo = verdict["readers"]["netconvert"]
    if not sumo["available"]:
        pytest.skip(sumo["note"])
    assert sumo["ok"] and not sumo["warnings"], sumo["warnings"]
    assert verdict["readers"]["pyxodr"]["ok"], verdict["readers"]["pyxodr"]


def _unfolded_sections(tmp_path: Path) -> tuple[etree._Element, etree._Element, etree._Element]:
    root = etree.parse(str(_write(tmp_path, _road(), False, "plain.xodr"))).getroot()
    first, second = root.findall("road/lanes/laneSection")
    return root, first, second


def test_lane_opening_in_the_middle_or_at_full_width_is_not_folded(tmp_path: Path) -> None:
    root, _, second = _unfolded_sections(tmp_path)
    second.find("right/lane[@id='-4']/width").set("a", "1.0")  # opens at 1 m: not a lane from nothing
    assert fold_appearing_lanes(root) == []
    root, first, second = _unfolded_sections(tmp_path)
    # the new lane is -3, between lanes, and the old -3 continues as -4: ids shift, nothing to fold
    first.find("right/lane[@id='-3']/link/successor").set("id", "-4")
    new, old = second.find("right/lane[@id='-3']"), second.find("right/lane[@id='-4']")
    new.find("link").remove(new.find("link/predecessor"))
    new.find("width").set("a", "0.0")
    old.insert(0, etree.Element("link"))
    etree.SubElement(old.find("link"), "predecessor", id="-3")
    assert fold_appearing_lanes(root) == []
    assert len(root.findall("road/lanes/laneSection")) == 2


def test_truth_map_loses_its_sumo_warning_when_folded(shared_data: Path, tmp_path: Path) -> None:
    """esmini's highway_exit has the same section change; SUMO warns on it as written and not once folded."""
    src = shared_data / "maps" / "esmini" / "highway_exit.xodr"
    before = run_netconvert(src)
    if not before["available"]:
        pytest.skip(before["note"])
    assert any("is not connected from any incoming edge" in w for w in before["warnings"]), before["warnings"]
    root = etree.parse(str(src), etree.XMLParser(remove_blank_text=True)).getroot()
    assert len(fold_appearing_lanes(root)) >= 1
    out = tmp_path / "folded.xodr"
    out.write_bytes(etree.tostring(root, xml_declaration=True, encoding="UTF-8"))
    after = run_netconvert(out)
    assert after["returncode"] == 0 and not after["errors"] and not after["warnings"], after["warnings"]
    assert 0 < after["edges"] < before["edges"]  # one edge per lane section (and taper split) fewer
