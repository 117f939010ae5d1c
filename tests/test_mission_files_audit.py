"""Mission files: the findings of an outside audit of reading them (x6wd mission show/convert).

.waypoints: a file without a home row, the items' indices, hold times and autocontinue, the
acceptance radius, the home row kept on conversion. GPX: only the GPX namespace's elements,
never inside <extensions>. KML: nothing dropped silently (gx:Track, Polygon, Points beside a
path). CSV: a ';' separator or decimal commas named as such.
"""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest

from tests.conftest import ROOT
from x6wd.core.errors import ParseError
from x6wd.core.mission_files import (
    Waypoint,
    format_content,
    load_file,
    parse_csv,
    parse_gpx,
    parse_kml,
    parse_wpl,
)

HOME = "0\t1\t0\t16\t0\t0\t0\t0\t51.752\t-1.2577\t60\t1"


def _item(index: int, lat: float, *, p1: str = "0", p2: str = "0", auto: str = "1") -> str:
    return f"{index}\t0\t3\t16\t{p1}\t{p2}\t0\t0\t{lat}\t-1.2577\t10\t{auto}"


def _wpl(*rows: str) -> str:
    return "QGC WPL 110\n" + "".join(r + "\n" for r in rows)


def x6wd(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "x6wd", *args], capture_output=True, text=True, timeout=60, cwd=ROOT
    )


# -- .waypoints ------------------------------------------------------------------------------


def test_wpl_without_a_home_row_keeps_its_first_waypoint() -> None:
    """The first item was always taken as home: a file starting at index 1 lost its first
    waypoint silently."""
    assert parse_wpl(_wpl(_item(1, 51.7522), _item(2, 51.7524))) == [
        (51.7522, -1.2577),
        (51.7524, -1.2577),
    ]
    with_home = parse_wpl(_wpl(HOME, _item(1, 51.7522), _item(2, 51.7524)))
    assert with_home == [(51.7522, -1.2577), (51.7524, -1.2577)]
    assert with_home.home == (51.752, -1.2577)
    assert parse_wpl(_wpl(_item(1, 51.7522))).home is None


@pytest.mark.parametrize(
    ("rows", "message"),
    [
        ((HOME, _item(2, 51.7524), _item(1, 51.7522)), "line 3: index 2, expected 1"),
        ((HOME, _item(1, 51.7522), _item(1, 51.7524)), "line 4: index 1, expected 2"),
        ((HOME, _item(1, 51.7522), _item(3, 51.7524)), "line 4: index 3, expected 2"),
        ((_item(1, 51.7522), _item(1, 51.7524)), "line 3: index 1, expected 2"),
        ((_item(5, 51.7522),), "line 2: index 5, expected 0 (the home row) or 1"),
    ],
)
def test_wpl_indices_out_of_order_or_repeated_are_refused(
    rows: tuple[str, ...], message: str
) -> None:
    """They were ignored: the items were driven in file order whatever their indices."""
    with pytest.raises(ParseError, match="^m.waypoints " + re.escape(message)):
        parse_wpl(_wpl(*rows), "m.waypoints")


@pytest.mark.parametrize(
    ("item", "message"),
    [
        (
            _item(1, 51.7522, p1="30"),
            "line 3: hold time (param1) 30 s: x6wd does not hold at waypoints",
        ),
        (
            _item(1, 51.7522, auto="0"),
            "line 3: autocontinue (the last column) 0: 0 stops the mission at this waypoint "
            "and x6wd does not hold at waypoints",
        ),
        (_item(1, 51.7522, auto="x"), "line 3: autocontinue is not a number: 'x'"),
    ],
)
def test_wpl_holds_and_stops_at_waypoints_are_refused(item: str, message: str) -> None:
    """A hold time or autocontinue 0 was ignored: the robot drove on where the mission says
    to wait."""
    with pytest.raises(ParseError, match="^m.waypoints " + re.escape(message)):
        parse_wpl(_wpl(HOME, item), "m.waypoints")
    # the home row's settings are not the mission's
    home = HOME.replace("\t0\t0\t0\t0\t51", "\t30\t0\t0\t0\t51")[:-1] + "0"
    assert parse_wpl(_wpl(home, _item(1, 51.7522))) == [(51.7522, -1.2577)]


def test_wpl_acceptance_radius_is_read_with_a_note(tmp_path: Path) -> None:
    """param2 was ignored silently: x6wd arrives by its own window from the config."""
    wps = parse_wpl(_wpl(HOME, _item(1, 51.7522, p2="5"), _item(2, 51.7524)), "m.waypoints")
    assert wps == [(51.7522, -1.2577), (51.7524, -1.2577)]
    assert wps.notes == [
        "m.waypoints line 3: acceptance radius (param2) 5 m not used: x6wd arrives by its own "
        "window from the config ([navigation] delta_x_m, delta_y_m)"
    ]
    assert parse_wpl(_wpl(HOME, _item(1, 51.7522, p2="nan"))).notes == []  # MAVLink's unset
    path = tmp_path / "r.waypoints"
    path.write_text(_wpl(HOME, _item(1, 51.7522, p2="5")))
    r = x6wd("mission", "show", str(path))
    assert r.returncode == 0 and "1 waypoints" in r.stdout
    assert r.stderr.splitlines() == [
        f"x6wd mission: note: {path} line 3: acceptance radius (param2) 5 m not used: x6wd "
        "arrives by its own window from the config ([navigation] delta_x_m, delta_y_m)"
    ]


def test_wpl_to_wpl_keeps_the_home_row(tmp_path: Path) -> None:
    """Converting replaced the source's home row with the first waypoint."""
    src = tmp_path / "in.waypoints"
    src.write_text(_wpl(HOME, _item(1, 51.7522), _item(2, 51.7524)))
    out = tmp_path / "out.waypoints"
    r = x6wd("mission", "convert", str(src), str(out))
    assert r.returncode == 0, r.stderr
    rows = [line.split("\t") for line in out.read_text().splitlines()[1:]]
    assert rows[0][:4] == ["0", "1", "0", "16"] and rows[0][8:10] == ["51.752", "-1.2577"]
    assert [r[8] for r in rows[1:]] == ["51.7522", "51.7524"]
    # without a home row in the source, the first waypoint stands in for it (as before)
    text = format_content(parse_wpl(_wpl(_item(1, 51.7522))), "waypoints")
    assert text.splitlines()[1].split("\t")[8] == "51.7522"
    # other formats have no home: as before
    assert format_content([Waypoint(51.7, -1.2)], "waypoints").splitlines()[1].split("\t")[8] == (
        "51.7"
    )
    assert load_file(out) == [(51.7522, -1.2577), (51.7524, -1.2577)]


# -- GPX -------------------------------------------------------------------------------------

GPX11 = 'xmlns="http://www.topografix.com/GPX/1/1"'
ROUTE = '<rtept lat="51.752" lon="-1.2577"/><rtept lat="51.7522" lon="-1.2577"/>'
PATH = [(51.752, -1.2577), (51.7522, -1.2577)]


def _gpx(body: str, ns: str = GPX11) -> str:
    return f'<?xml version="1.0"?><gpx version="1.1" {ns} xmlns:x="urn:x">{body}</gpx>'


@pytest.mark.parametrize(
    "body",
    [
        # another schema's <rtept> in a route's extensions: read as a point 5,647 km away
        f'<rte><extensions><x:rtept lat="1" lon="1"/></extensions>{ROUTE}</rte>',
        # a GPX-namespace <rtept> inside <extensions> is not the route's either
        f'<rte><extensions><rtept lat="1" lon="1"/></extensions>{ROUTE}</rte>',
        # Garmin's route-point extension (the road between two points)
        '<rte><rtept lat="51.752" lon="-1.2577"><extensions><x:rpt lat="1" lon="1"/>'
        '<x:rtept lat="1" lon="1"/></extensions></rtept><rtept lat="51.7522" lon="-1.2577"/>'
        "</rte>",
        # a track's extensions, and a foreign <trkpt> beside the segments
        '<trk><x:trkpt lat="1" lon="1"/><trkseg><trkpt lat="51.752" lon="-1.2577"/>'
        '<extensions><trkpt lat="1" lon="1"/></extensions></trkseg>'
        '<trkseg><trkpt lat="51.7522" lon="-1.2577"/></trkseg></trk>',
        # waypoints: a foreign <wpt>, and one in the file's extensions
        '<x:wpt lat="1" lon="1"/><extensions><wpt lat="1" lon="1"/></extensions>'
        '<wpt lat="51.752" lon="-1.2577"/><wpt lat="51.7522" lon="-1.2577"/>',
    ],
)
def test_gpx_reads_only_the_gpx_namespaces_elements_where_gpx_puts_them(body: str) -> None:
    assert parse_gpx(_gpx(body)) == PATH


def test_gpx_namespaces_1_0_1_1_and_none_are_read_others_refused() -> None:
    for ns in (GPX11, 'xmlns="http://www.topografix.com/GPX/1/0"', ""):
        assert parse_gpx(_gpx(f"<rte>{ROUTE}</rte>", ns)) == PATH
    with pytest.raises(ParseError, match=r"^m\.gpx: <gpx> is in the namespace 'urn:y', not GPX"):
        parse_gpx(_gpx(f"<rte>{ROUTE}</rte>", 'xmlns="urn:y"'), "m.gpx")


@pytest.mark.parametrize(
    "ns",
    [
        "https://www.topografix.com/GPX/1/1",  # OsmAnd 5's format docs
        "http://www.topografix.com/GPX/1/1/",  # a Garmin-style header, Onloc
        "http://www.topografix.com/GPX/1/0/",
    ],
)
def test_gpx_namespaces_as_exporters_write_them_are_read(ns: str) -> None:
    # a second outside audit: these were refused after the namespace check came in, though
    # the reader before it read them; another schema's elements stay out all the same
    body = f'<rte>{ROUTE}<x:rtept xmlns:x="urn:x" lat="10" lon="10"/></rte>'
    assert parse_gpx(_gpx(body, f'xmlns="{ns}"')) == PATH


def test_gpx_waypoints_and_track_beside_the_route_are_named_in_a_note() -> None:
    wps = parse_gpx(
        _gpx(
            f'<wpt lat="51.7" lon="-1.2"/><rte>{ROUTE}</rte>'
            '<trk><trkseg><trkpt lat="51.7" lon="-1.2"/></trkseg></trk>'
        ),
        "m.gpx",
    )
    assert wps == PATH
    assert wps.notes == [
        "m.gpx: the <rte> is driven; beside it, not driven: 1 point as <wpt> and a <trk> of "
        "1 point (a route wins over waypoints and tracks)"
    ]
    assert parse_gpx(_gpx(f"<rte>{ROUTE}</rte>")).notes == []


# -- KML -------------------------------------------------------------------------------------

KML = '<kml xmlns="http://www.opengis.net/kml/2.2" xmlns:gx="http://www.google.com/kml/ext/2.2">'
LINE = "<LineString><coordinates>-1.2577,51.752,0 -1.2577,51.7522,0</coordinates></LineString>"
TRACK = "<gx:Track><gx:coord>-1.2577 51.752 0</gx:coord><gx:coord>-1.2577 51.7522</gx:coord>"
TRACK += "<when>2026-12-01T10:00:00Z</when></gx:Track>"
POINT = "<Point><coordinates>-1.25,51.76</coordinates></Point>"


def _kml(*placemarks: str) -> str:
    return KML + "<Document>" + "".join(placemarks) + "</Document></kml>"


def _pm(name: str, geometry: str) -> str:
    return f"<Placemark><name>{name}</name>{geometry}</Placemark>"


def test_kml_gx_track_is_read_as_its_path() -> None:
    """A gx:Track (Google Earth's recorded path) was dropped: the file read as its Points."""
    assert parse_kml(_kml(_pm("T", TRACK))) == PATH
    assert parse_kml(_kml(_pm("M", f"<gx:MultiTrack>{TRACK}</gx:MultiTrack>"))) == PATH
    with pytest.raises(
        ParseError, match=re.escape("m.kml: 2 paths: <Placemark> #1 'L' <LineString> (2 points)")
    ):
        parse_kml(_kml(_pm("L", LINE), _pm("T", TRACK)), "m.kml")
    bad = TRACK.replace("51.7522</gx", "north</gx")
    with pytest.raises(
        ParseError,
        match=re.escape("<Placemark> #1 'T' <gx:Track> coordinate 2: latitude is not a number"),
    ):
        parse_kml(_kml(_pm("T", bad)), "m.kml")


def test_kml_points_beside_a_path_are_named_in_a_note() -> None:
    """Points beside a LineString were dropped silently; the path wins, as a GPX route over
    its waypoints, and the note says what is not driven."""
    wps = parse_kml(_kml(_pm("P", POINT), _pm("L", LINE), _pm("Q", POINT)), "m.kml")
    assert wps == PATH
    assert wps.notes == [
        "m.kml: the path <Placemark> #2 'L' <LineString> is driven; beside it, not driven: "
        "2 <Point> (<Placemark> #1 'P', <Placemark> #3 'Q') (a path wins over points)"
    ]
    assert parse_kml(_kml(_pm("L", LINE))).notes == []
    assert parse_kml(_kml(_pm("P", POINT), _pm("Q", POINT))) == [(51.76, -1.25)] * 2


@pytest.mark.parametrize(
    ("geometry", "kind"),
    [
        (
            "<Polygon><outerBoundaryIs><LinearRing><coordinates>-1.2577,51.752 -1.2577,51.7522 "
            "-1.2575,51.7522 -1.2577,51.752</coordinates></LinearRing></outerBoundaryIs>"
            "</Polygon>",
            "Polygon",
        ),
        (
            "<LinearRing><coordinates>-1.2577,51.752 -1.2577,51.7522</coordinates></LinearRing>",
            "LinearRing",
        ),
        (
            "<Model><Location><longitude>-1.2</longitude><latitude>51.7</latitude></Location></Model>",
            "Model",
        ),
        (f"<MultiGeometry>{LINE}<Polygon/></MultiGeometry>", "Polygon"),
    ],
)
def test_kml_areas_are_refused_naming_them(geometry: str, kind: str) -> None:
    """A Polygon or LinearRing was dropped silently (beside Points, the Points were driven)."""
    with pytest.raises(
        ParseError,
        match=re.escape(
            f"m.kml <Placemark> #2 'A' <{kind}>: x6wd drives one path (a <LineString> or a "
            "<gx:Track>) or <Point>s, not an area or a model: draw the path as a line, or "
            f"delete the <{kind}> from the file"
        ),
    ):
        parse_kml(_kml(_pm("P", POINT), _pm("A", geometry)), "m.kml")
    with pytest.raises(ParseError, match="no <Placemark> with a <Point>, a <LineString> or a"):
        parse_kml(_kml("<Placemark/>"))


# -- CSV -------------------------------------------------------------------------------------

SEPARATOR = "the separator must be a comma, and ';' was found"


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("lat;lon\n51.752;-1.2577\n", f"line 1: {SEPARATOR}"),
        ("\ufefflat;lon\r\n51,752;-1,2577\r\n", f"line 1: {SEPARATOR}"),
        ("51,752;-1,2577\n", f"line 1: {SEPARATOR}"),
        ("lat,lon\n51.752;-1.2577\n", f"line 2: {SEPARATOR}"),
        (
            'lat,lon\n"51,752","-1,2577"\n',
            "line 2: '51,752' has a decimal comma: write a decimal point (51.752)",
        ),
        ("lat\tlon\n51.752\t-1.2577\n", "line 1: the separator must be a comma, and a tab"),
    ],
)
def test_csv_with_another_separator_or_decimal_commas_says_so(text: str, message: str) -> None:
    """A ';'-separated file got 'expected at least 2 columns', naming neither."""
    with pytest.raises(ParseError, match="^m.csv " + re.escape(message)):
        parse_csv(text, "m.csv")
    # a ';' in a column x6wd does not read is no problem
    assert parse_csv("lat,lon,name\n51.752,-1.2577,a;b\n") == [(51.752, -1.2577)]


# -- DTDs wherever the prolog puts them -------------------------------------------------------
_ATTLIST = '<!DOCTYPE {root} [<!ATTLIST wpt lat CDATA "51.7530" lon CDATA "-1.2577">]>'


@pytest.mark.parametrize("pad", ["", " " * 5000, "<!--" + "x" * 5000 + "-->", "\n" * 4100])
def test_a_dtd_is_refused_wherever_the_prolog_puts_it(pad: str) -> None:
    # console audit: 5000 spaces before the DOCTYPE hid it from a search of the first 4 KiB,
    # and its default attributes made two empty <wpt/> into waypoints the file never shows
    gpx = (
        f'<?xml version="1.0"?>{pad}{_ATTLIST.format(root="gpx")}\n'
        '<gpx version="1.1" creator="x"><wpt lat="51.7520" lon="-1.2577"/><wpt/><wpt/></gpx>'
    )
    with pytest.raises(ParseError, match="DTDs and entities are not allowed in GPX"):
        parse_gpx(gpx, "t.gpx")
    kml = (
        f'<?xml version="1.0"?>{pad}<!DOCTYPE kml>\n<kml xmlns="http://www.opengis.net/kml/2.2">'
        "<Placemark><Point><coordinates>-1.2577,51.752</coordinates></Point></Placemark></kml>"
    )
    with pytest.raises(ParseError, match="DTDs and entities are not allowed in KML"):
        parse_kml(kml, "t.kml")
