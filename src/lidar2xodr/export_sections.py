"""Lane sections of a written OpenDRIVE road: fold an outer lane that opens from zero width into the section before.

Why: the lanes stage gives an exit lane (or any lane that widens from nothing at the carriageway's
edge) a lane section of its own that starts where the lane appears, at width 0 and, as ASAM rule
`road.lane.link.new_lane_appear` demands, without a predecessor. That is valid OpenDRIVE, but SUMO's
netconvert turns every lane section into an edge and then warns "Lane ... is not connected from any
incoming edge", for the shared truth maps (esmini highway_exit, multi_lanesections) as much as for
ours. Linking the appearing lane to a lane before it is an ASAM error (zero-width lanes shall have no
predecessor), so the warning cannot be silenced by links.

What: OpenDRIVE lets a lane keep width 0 for part of its section. When the section after a change
holds the same lanes as the one before plus lanes that (a) are outermost on their side (no lane id
shifts), (b) start at width 0 and (c) have no predecessor, and every other lane continues under its
own id, the later section is merged into the earlier one: the new lanes exist from the earlier
section's start at width 0 (road mark "none" there, so the edge line is drawn once) and the later
section's width, road-mark and other s-records follow, shifted by the distance between the two
sections. The lane count of a station is unchanged for every reader that counts lanes of non-zero
width (our `compare` counts lanes of at least `lane_count_min_width_m`), the geometry of every border
is identical, and netconvert (1.15) reads the result without a warning. A lane that ends at width 0
keeps its section change: SUMO accepts a lane without successor.
"""

from __future__ import annotations

import copy

from lxml import etree

_ZERO_TOL = 1e-6
_ORDER = ("link", "border", "width", "roadMark", "material", "speed", "access", "height", "rule", "userData")


def _lanes(section: etree._Element) -> dict[int, etree._Element]:
    parts = ("left", "center", "right")
    return {int(lane.get("id")): lane for part in parts for lane in section.findall(f"{part}/lane")}


def _link(lane: etree._Element, kind: str) -> int | None:
    el = lane.find(f"link/{kind}")
    return None if el is None else int(el.get("id"))


def _start_width(lane: etree._Element) -> float | None:
    first = lane.find("width")
    if first is None or abs(float(first.get("sOffset", "0"))) > _ZERO_TOL:
        return None
    return float(first.get("a"))


def _foldable(before: etree._Element, after: etree._Element) -> list[int] | None:
    """Ids of the lanes that appear at `after`'s start, when `after` may be merged into `before`; else None."""
    old, new = _lanes(before), _lanes(after)
    if not set(old) <= set(new) or set(old) == set(new):
        return None
    for lid in old:
        if lid != 0 and (_link(old[lid], "successor") != lid or _link(new[lid], "predecessor") != lid):
            return None
    added = sorted(set(new) - set(old))
    left = [i for i in old if i > 0]
    right = [i for i in old if i < 0]
    for lid in added:
        beyond = lid > max(left, default=0) if lid > 0 else lid < min(right, default=0)
        width = _start_width(new[lid])
        if not beyond or width is None or abs(width) > _ZERO_TOL or _link(new[lid], "predecessor") is not None:
            return None
    return added


def _shifted(record: etree._Element, ds: float) -> etree._Element:
    rec = copy.deepcopy(record)
    rec.set("sOffset", repr(float(rec.get("sOffset", "0")) + ds))
    return rec


def _same_mark(a: etree._Element, b: etree._Element) -> bool:
    """Two road-mark records that differ only in where they start (the later one is redundant)."""
    strip = ("sOffset",)
    same_attrs = {k: v for k, v in a.attrib.items() if k not in strip} == {k: v for k, v in b.attrib.items()
                                                                          if k not in strip}
    return same_attrs and [etree.tostring(c) for c in a] == [etree.tostring(c) for c in b]


def _append_records(target: etree._Element, source: etree._Element, ds: float) -> None:
    """Append `source`'s s-records (all but link) to `target`, shifted by ds, keeping the schema's child order."""
    for tag in _ORDER[1:]:
        recs = [_shifted(r, ds) for r in source.findall(tag)]
        mine = target.findall(tag)
        if tag == "roadMark" and recs and mine and _same_mark(mine[-1], recs[0]):
            recs = recs[1:]
        if not recs:
            continue
        if mine:
            anchor = mine[-1]
            for rec in recs:
                anchor.addnext(rec)
                anchor = rec
            continue
        later = [c for c in target if c.tag in _ORDER[_ORDER.index(tag) + 1:]]
        for rec in recs:
            if later:
                later[0].addprevious(rec)
            else:
                target.append(rec)


def _set_successor(lane: etree._Element, target: int | None) -> None:
    link = lane.find("link")
    if link is None:
        if target is None:
            return
        link = etree.Element("link")
        lane.insert(0, link)
    for old in link.findall("successor"):
        link.remove(old)
    if target is not None:
        link.append(etree.Element("successor", id=str(target)))
    if len(link) == 0:
        lane.remove(link)


def _fold(before: etree._Element, after: etree._Element, added: list[int]) -> None:
    ds = float(after.get("s")) - float(before.get("s"))
    old, new = _lanes(before), _lanes(after)
    for lid, lane in old.items():
        _append_records(lane, new[lid], ds)
        if lid != 0:
            _set_successor(lane, _link(new[lid], "successor"))
    for lid in added:
        src = new[lid]
        lane = etree.Element("lane", dict(src.attrib))
        succ = _link(src, "successor")
        if succ is not None:
            link = etree.SubElement(lane, "link")
            etree.SubElement(link, "successor", id=str(succ))
        etree.SubElement(lane, "width", sOffset="0.0", a="0.0", b="0.0", c="0.0", d="0.0")
        etree.SubElement(lane, "roadMark", sOffset="0.0", type="none", weight="standard", color="standard",
                         laneChange="none")
        _append_records(lane, src, ds)
        part = before.find("left" if lid > 0 else "right")
        if part is None:
            part = etree.SubElement(before, "left" if lid > 0 else "right")
        part.append(lane)
    for part in before:
        lanes = sorted(part.findall("lane"), key=lambda el: -int(el.get("id")))
        for lane in lanes:
            part.remove(lane)
            part.append(lane)
    parts = [el for el in (before.find(tag) for tag in ("left", "center", "right")) if el is not None]
    for el in parts:
        before.remove(el)
    for idx, el in enumerate(parts):
        before.insert(idx, el)
    after.getparent().remove(after)


def fold_appearing_lanes(root: etree._Element) -> list[etree._Element]:
    """Merge each lane section that only adds outer lanes opening from width 0 into the one before.

    Returns the roads changed, once per fold; their records at the old section start may now repeat
    each other, which the caller merges (the ASAM checker flags redundant records).
    """
    changed = []
    for road in root.findall("road"):
        secs = road.findall("lanes/laneSection")
        i = 0
        while i + 1 < len(secs):
            added = _foldable(secs[i], secs[i + 1])
            if added is None:
                i += 1
                continue
            _fold(secs[i], secs[i + 1], added)
            changed.append(road)
            secs = road.findall("lanes/laneSection")
    return changed
