"""Mission files: QGC WPL 110 (.waypoints), GPX, CSV in and out, KML in; the format by
extension; errors that name the line or element; the shipped examples; `x6wd mission` and
`x6wd client load` with every format."""

from __future__ import annotations

import shlex
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest
from hypothesis import given
from hypothesis import strategies as st

from tests.conftest import ROOT
from tests.test_server import LoopThread, RecordingBackend, start_server
from x6wd.app import cli
from x6wd.app.server import ControlServer
from x6wd.core import mission_files
from x6wd.core.errors import ParseError
from x6wd.core.geodesy import great_circle_m
from x6wd.core.mission_files import (
    PARSERS,
    WRITERS,
    Waypoint,
    format_content,
    format_csv,
    format_gpx,
    format_wpl,
    load_file,
    parse_content,
    parse_kml,
    parse_wpl,
    save_file,
)

MISSIONS = ROOT / "missions"
EXAMPLES = sorted(MISSIONS.glob("default.*"))

# As QGroundControl and Mission Planner write it: tabs, CRLF, the home on line 2 (index 0,
# frame 0 = absolute altitude), then the items (frame 3 = relative altitude).
QGC_FILE = (
    "QGC WPL 110\r\n"
    "0\t1\t0\t16\t0\t0\t0\t0\t-35.363262\t149.165237\t584.090000\t1\r\n"
    "1\t0\t3\t16\t0.00000000\t0.00000000\t0.00000000\t0.00000000\t-35.36216720\t149.16345550"
    "\t20.000000\t1\r\n"
    "2\t0\t3\t16\t0.00000000\t0.00000000\t0.00000000\t0.00000000\t-35.36474310\t149.16413190"
    "\t20.000000\t1\r\n"
)


# -- QGC WPL 110 -----------------------------------------------------------------------------


def test_wpl_skips_the_home_line_and_reads_nav_waypoints() -> None:
    assert parse_wpl(QGC_FILE) == [(-35.3621672, 149.1634555), (-35.3647431, 149.1641319)]
    # QGC WPL 120 (QGroundControl's older files) has no home line
    assert parse_wpl(QGC_FILE.replace("110", "120", 1)) == [
        (-35.363262, 149.165237),
        (-35.3621672, 149.1634555),
        (-35.3647431, 149.1641319),
    ]
    # blank lines and spaces instead of tabs (a hand-edited file)
    spaced = QGC_FILE.replace("\t", "  ").replace("\r\n", "\n\n")
    assert parse_wpl(spaced) == parse_wpl(QGC_FILE)


@pytest.mark.parametrize(
    ("line", "message"),
    [
        (
            "3\t0\t3\t178\t0\t2\t-1\t0\t0\t0\t0\t1",
            "line 5: command 178 (DO_CHANGE_SPEED) is not supported: x6wd missions are "
            "NAV_WAYPOINT (16) items only",
        ),
        ("3\t0\t3\t19\t10\t0\t0\t0\t-35.36\t149.16\t20\t1", "line 5: command 19 (NAV_LOITER_TIME)"),
        ("3\t0\t3\t31000\t0\t0\t0\t0\t-35.36\t149.16\t20\t1", "line 5: command 31000 (unknown)"),
        ("3\t0\t1\t16\t0\t0\t0\t0\t5\t7\t0\t1", "line 5: frame 1 is not a global"),
        ("3\t0\t3\t16\t0\t0\t0\t0\t-35.36\t149.16\t20", "line 5: expected 12 tab-separated"),
        ("3\t0\tx\t16\t0\t0\t0\t0\t-35.36\t149.16\t20\t1", "line 5: frame is not an integer"),
        ("3\t0\t3\t16\t0\tfast\t0\t0\t-35.36\t149.16\t20\t1", "line 5: param2 is not a number"),
        ("3\t0\t3\t16\t0\t0\t0\t0\t-95.0\t149.16\t20\t1", "line 5: latitude -95.0 outside"),
        ("3\t0\t3\t16\t0\t0\t0\t0\tnorth\t149.16\t20\t1", "line 5: latitude is not a number"),
    ],
)
def test_wpl_errors_name_the_line_and_the_problem(line: str, message: str) -> None:
    with pytest.raises(ParseError, match="^m.waypoints " + _re(message)):
        parse_wpl(QGC_FILE + line + "\r\n", "m.waypoints")


def _re(text: str) -> str:
    import re

    return re.escape(text)


def test_wpl_header_and_empty_files() -> None:
    with pytest.raises(
        ParseError, match=r"line 1: expected the header 'QGC WPL 110', got 'lat,lon'"
    ):
        parse_wpl("lat,lon\n51,-1\n")
    with pytest.raises(ParseError, match="empty file"):
        parse_wpl("\n\n")
    with pytest.raises(ParseError, match="no waypoints"):
        parse_wpl(QGC_FILE.split("1\t0\t3")[0])  # the home line only
    # the home line is checked too, though not driven to
    with pytest.raises(ParseError, match="line 2: expected 12"):
        parse_wpl("QGC WPL 110\n0\t1\t0\t16\n")


def test_wpl_writer_writes_what_qgc_writes() -> None:
    text = format_wpl([Waypoint(51.5, -1.25), Waypoint(51.5001, -1.2501)], home=Waypoint(51, -1))
    lines = text.splitlines()
    assert lines[0] == "QGC WPL 110"
    assert lines[1].split("\t") == [
        "0",
        "1",
        "0",
        "16",
        "0",
        "0",
        "0",
        "0",
        "51.0",
        "-1.0",
        "0",
        "1",
    ]
    assert lines[2].split("\t") == [
        "1",
        "0",
        "3",
        "16",
        "0",
        "0",
        "0",
        "0",
        "51.5",
        "-1.25",
        "0",
        "1",
    ]
    assert lines[3].split("\t")[:4] == ["2", "0", "3", "16"]
    assert all(len(line.split("\t")) == 12 for line in lines[1:])
    # without a home, the first waypoint stands in for it (QGC replaces it on upload)
    assert format_wpl([Waypoint(51.5, -1.25)]).splitlines()[1].split("\t")[8:10] == [
        "51.5",
        "-1.25",
    ]
    assert "e-" not in format_wpl([Waypoint(1e-7, -2e-9)])  # never exponent notation


# -- KML -------------------------------------------------------------------------------------

KML_NS = 'xmlns="http://www.opengis.net/kml/2.2"'


def test_kml_reads_lon_lat_order_linestring_first() -> None:
    points = (
        f"<kml {KML_NS}><Document>"
        "<Placemark><name>A</name><Point><coordinates>-1.25,51.5,10</coordinates></Point></Placemark>"
        "<Folder><Placemark><Point><coordinates> -1.26,51.6 </coordinates></Point></Placemark>"
        "</Folder></Document></kml>"
    )
    assert parse_kml(points) == [(51.5, -1.25), (51.6, -1.26)]
    path = points.replace(
        "</Document>",
        "<Placemark><name>route</name><LineString><coordinates>\n  -1.0,51.0,0\n"
        "  -1.1,51.1,0 -1.2,51.2\n</coordinates></LineString></Placemark></Document>",
    )
    assert parse_kml(path) == [(51.0, -1.0), (51.1, -1.1), (51.2, -1.2)]
    multi = (
        f"<kml {KML_NS}><Placemark><MultiGeometry><Point><coordinates>2,1</coordinates></Point>"
        "<Point><coordinates>4,3</coordinates></Point></MultiGeometry></Placemark></kml>"
    )
    assert parse_kml(multi) == [(1.0, 2.0), (3.0, 4.0)]
    assert parse_content(multi) == [(1.0, 2.0), (3.0, 4.0)]  # sniffed as KML


@pytest.mark.parametrize(
    ("kml", "message"),
    [
        (
            "<Placemark><name>gate</name><Point><coordinates>51.5</coordinates></Point></Placemark>",
            "<Placemark> #1 'gate' <Point> coordinate 1: expected lon,lat[,alt], got '51.5'",
        ),
        (
            "<Placemark><LineString><coordinates>1,2 3,x</coordinates></LineString></Placemark>",
            "<Placemark> #1 <LineString> coordinate 2: latitude is not a number: 'x'",
        ),
        (
            "<Placemark><Point><coordinates>-1,95</coordinates></Point></Placemark>",
            "<Point> coordinate 1: latitude 95.0 outside -90..90",
        ),
        ("<Placemark><Point/></Placemark>", "<Placemark> #1 <Point>: no <coordinates>"),
        (
            "<Placemark><Polygon/></Placemark>",
            "<Placemark> #1 <Polygon>: x6wd drives one path (a <LineString> or a <gx:Track>) "
            "or <Point>s, not an area or a model",
        ),
        (
            "<Placemark><Point><coordinates>1,2 3,4</coordinates></Point></Placemark>",
            "<Point>: 2 coordinates, expected one",
        ),
    ],
)
def test_kml_errors_name_the_element(kml: str, message: str) -> None:
    with pytest.raises(
        ParseError, match="^m.kml .*" + _re(message) if "#" in message else _re(message)
    ):
        parse_kml(f"<kml {KML_NS}><Document>{kml}</Document></kml>", "m.kml")


def test_kml_refuses_bad_documents() -> None:
    with pytest.raises(ParseError, match="DTDs and entities are not allowed in KML"):
        parse_kml('<!DOCTYPE kml [<!ENTITY a "b">]><kml/>')
    with pytest.raises(ParseError, match=r"not valid XML: .*line 1"):
        parse_kml("<kml><Placemark>")
    with pytest.raises(ParseError, match="root element is <gpx>, expected <kml>"):
        parse_kml("<gpx/>")


def test_kml_with_several_paths_is_refused_naming_them() -> None:
    """Only the first <LineString> was read, silently (an outside check): a second placemark's
    path, or a MultiGeometry's second part, was dropped."""

    def line(name: str, coords: str) -> str:
        return f"<Placemark><name>{name}</name><LineString><coordinates>{coords}</coordinates>"

    pin = (
        "<Placemark><name>P</name><Point><coordinates>-1.1,51.1,0</coordinates></Point></Placemark>"
    )
    two = (
        f"<kml {KML_NS}><Document>{pin}{line('L1', '-1.3,51.3 -1.4,51.4')}</LineString>"
        f"</Placemark>{line('L2', '-1.5,51.5')}</LineString></Placemark></Document></kml>"
    )
    with pytest.raises(
        ParseError,
        match="^m.kml: "
        + _re(
            "2 <LineString> paths: <Placemark> #2 'L1' (2 points), <Placemark> #3 'L2' (1 point); "
            "x6wd drives one path: delete the others from the file, or join them into one"
        ),
    ):
        parse_kml(two, "m.kml")
    mg = (
        f"<kml {KML_NS}><Placemark><name>MG</name><MultiGeometry><LineString><coordinates>"
        "-1.3,51.3 -1.4,51.4</coordinates></LineString><LineString><coordinates>-1.5,51.5"
        "</coordinates></LineString></MultiGeometry></Placemark></kml>"
    )
    with pytest.raises(
        ParseError,
        match=_re(
            "2 <LineString> paths: <Placemark> #1 'MG' <LineString> #1 (2 points), "
            "<Placemark> #1 'MG' <LineString> #2 (1 point)"
        ),
    ):
        parse_kml(mg)
    # one path with pins beside it is still the path; a path without coordinates is no path
    one = two.replace("-1.5,51.5", " ")
    assert parse_kml(one) == [(51.3, -1.3), (51.4, -1.4)]
    assert parse_kml(one.replace("-1.3,51.3 -1.4,51.4", "")) == [(51.1, -1.1)]


# -- writers and round trips -----------------------------------------------------------------

coordinates = st.builds(
    Waypoint,
    st.floats(-90, 90, allow_nan=False, allow_infinity=False),
    st.floats(-180, 180, allow_nan=False, allow_infinity=False),
).filter(lambda w: (w.lat_deg, w.lon_deg) != (0.0, 0.0))  # ArduPilot's "here" in .waypoints


@given(st.lists(coordinates, min_size=1, max_size=30))
def test_round_trips_are_exact(wps: list[Waypoint]) -> None:
    for fmt in WRITERS:
        assert parse_content(format_content(wps, fmt), fmt) == wps, fmt
        assert parse_content(format_content(wps, fmt)) == wps, fmt  # sniffed from the content


def test_round_trips_through_files(tmp_path: Path) -> None:
    wps = load_file(MISSIONS / "default.kml")
    for fmt in WRITERS:
        path = tmp_path / f"m.{fmt}"
        assert save_file(path, wps) == fmt
        assert load_file(path) == wps
    # a chain through every format ends where it began
    chain = wps
    for fmt in ("waypoints", "gpx", "csv", "waypoints"):
        save_file(tmp_path / f"c.{fmt}", chain, force=True)  # .waypoints twice
        chain = load_file(tmp_path / f"c.{fmt}")
    assert chain == wps
    assert "<rtept" in format_gpx(wps) and format_csv(wps).startswith("lat,lon\n")


def test_the_format_comes_from_the_extension(tmp_path: Path) -> None:
    # the report: a .waypoints file was read as CSV ("line 1: expected at least 2 columns")
    qgc = tmp_path / "survey.waypoints"
    qgc.write_text(QGC_FILE)
    assert load_file(qgc) == parse_wpl(QGC_FILE)
    csv_named_txt = tmp_path / "m.txt"
    csv_named_txt.write_text("51,-1\n")
    with pytest.raises(ParseError, match=r"m.txt: has an unknown mission format 'txt' \(if it is"):
        load_file(csv_named_txt)
    assert load_file(csv_named_txt, "csv") == [(51.0, -1.0)]  # an explicit format wins
    plan = tmp_path / "m.plan"
    plan.write_text("{}")
    with pytest.raises(ParseError, match=r"m\.plan: not a QGroundControl plan"):
        load_file(plan)  # read since round 7 (QGroundControl cannot save .waypoints)
    with pytest.raises(ParseError, match=r"has no extension; missions are read as \.waypoints, "):
        load_file(tmp_path / "mission")
    with pytest.raises(ParseError, match="is KML, which x6wd reads but does not write"):
        save_file(tmp_path / "m.kml", [Waypoint(1, 2)])
    with pytest.raises(ParseError, match="cannot read: No such file"):
        load_file(tmp_path / "absent.gpx")
    with pytest.raises(ParseError, match=r"m.gpx line 1: expected at least 2 columns"):
        load_file(tmp_path / "m.gpx", "csv") if (tmp_path / "m.gpx").write_text("51\n") else None
    assert set(PARSERS) == {"waypoints", "gpx", "csv", "kml", "plan"}


GPX_NS = 'xmlns="http://www.topografix.com/GPX/1/1"'


def _gpx(body: str) -> str:
    return f'<?xml version="1.0" encoding="UTF-8"?><gpx version="1.1" {GPX_NS}>{body}</gpx>'


def _rte(*lats: float, name: str = "") -> str:
    named = f"<name>{name}</name>" if name else ""
    return f"<rte>{named}" + "".join(f'<rtept lat="{a}" lon="-1.1"/>' for a in lats) + "</rte>"


def _trk(*segments: tuple[float, ...]) -> str:
    segs = "".join(
        "<trkseg>" + "".join(f'<trkpt lat="{a}" lon="-1.1"/>' for a in seg) + "</trkseg>"
        for seg in segments
    )
    return f"<trk>{segs}</trk>"


def test_gpx_routes_and_tracks_without_points_are_skipped() -> None:
    """An empty first <rte> (or <trk>) hid the second's points: 'no <rtept>, <wpt> or <trkpt>
    elements', which was false (an outside check)."""
    assert mission_files.parse_gpx(_gpx("<rte></rte>" + _rte(55.1))) == [(55.1, -1.1)]
    assert mission_files.parse_gpx(_gpx(_trk(()) + _trk((53.1, 53.2)))) == [
        (53.1, -1.1),
        (53.2, -1.1),
    ]
    # an empty route does not hide the waypoints either
    assert mission_files.parse_gpx(_gpx('<wpt lat="51.1" lon="-1.1"/><rte/>')) == [(51.1, -1.1)]


def test_gpx_with_several_routes_or_tracks_is_refused_naming_them(tmp_path: Path) -> None:
    """Only the first route or track was read, silently (an outside check): a robot mission
    must never drop half its waypoints. One track's segments are one path."""
    two = _gpx(_rte(52.1, 52.2, name="Out") + "<rte/>" + _rte(55.1))
    with pytest.raises(
        ParseError,
        match="^m.gpx: "
        + _re(
            "2 routes with points: <rte> #1 'Out' (2 points), <rte> #3 (1 point); x6wd drives "
            "one route: delete the others from the file, or join them into one"
        ),
    ):
        mission_files.parse_gpx(two, "m.gpx")
    with pytest.raises(
        ParseError, match=_re("2 tracks with points: <trk> #1 (3 points), <trk> #2")
    ):
        mission_files.parse_gpx(_gpx(_trk((53.1, 53.2), (53.3,)) + _trk((54.1,))))
    # one track of several segments (the receiver lost its fix): every segment, in order
    assert mission_files.parse_gpx(_gpx(_trk((53.1, 53.2), (), (53.3,)))) == [
        (53.1, -1.1),
        (53.2, -1.1),
        (53.3, -1.1),
    ]
    # the route is the plan: the waypoints it names and a recorded track beside it are not
    # driven, however many tracks there are
    both = _gpx('<wpt lat="51.1" lon="-1.1"/>' + _rte(52.1) + _trk((53.1,)) + _trk((54.1,)))
    assert mission_files.parse_gpx(both) == [(52.1, -1.1)]
    path = tmp_path / "two.gpx"
    path.write_text(two)
    r = x6wd("mission", "show", str(path))
    assert r.returncode == 2 and "Traceback" not in r.stderr
    assert r.stderr.startswith(f"x6wd mission: {path}: 2 routes with points"), r.stderr


def test_xml_files_are_read_in_their_declared_encoding(tmp_path: Path) -> None:
    """A GPX file declaring ISO-8859-1 with a non-ASCII name, and a UTF-16 one, were refused as
    'not UTF-8 text' (an outside check): XML names its own encoding."""
    body = f"<gpx {GPX_NS}>" + _rte(52.1, name="Straße") + "</gpx>"
    files = {
        "latin1.gpx": ('<?xml version="1.0" encoding="ISO-8859-1"?>' + body).encode("latin-1"),
        "cp1252.gpx": ("<?xml version='1.0' encoding='windows-1252'?>" + body).encode("cp1252"),
        "utf16.gpx": ('<?xml version="1.0" encoding="UTF-16"?>' + body).encode("utf-16"),
        "utf16be.gpx": ('<?xml version="1.0" encoding="UTF-16"?>' + body).encode("utf-16-be"),
        "bom.gpx": ('<?xml version="1.0"?>' + body).encode("utf-8-sig"),
        "none.gpx": body.encode(),
        # a string's declaration saved as UTF-8: '<?xml' read one byte a character says so
        "said16.gpx": ('<?xml version="1.0" encoding="utf-16"?>' + body).encode(),
        "latin1.kml": (
            '<?xml version="1.0" encoding="ISO-8859-1"?>'
            f"<kml {KML_NS}><Placemark><name>Straße</name><Point><coordinates>-1.1,52.1"
            "</coordinates></Point></Placemark></kml>"
        ).encode("latin-1"),
    }
    for name, data in files.items():
        (tmp_path / name).write_bytes(data)
        assert load_file(tmp_path / name) == [(52.1, -1.1)], name
    assert mission_files.decode_xml(files["latin1.gpx"]).count("Straße") == 1
    # bytes that are not in the encoding, or an encoding Python does not know: refused
    bad = {
        "bad.gpx": (body.encode("latin-1"), r"bad.gpx: not UTF-8 text \(XML's default\): 'utf-8'"),
        "bad8.gpx": (
            b'<?xml version="1.0" encoding="utf-8"?>' + body.encode("latin-1"),
            r"bad8.gpx: not utf-8 text \(its XML declaration\): 'utf-8' codec can't decode",
        ),
        "odd.kml": (
            b'<?xml version="1.0" encoding="klingon"?><kml/>',
            r"odd.kml: unknown encoding 'klingon' in its XML declaration",
        ),
    }
    for name, (data, message) in bad.items():
        (tmp_path / name).write_bytes(data)
        with pytest.raises(ParseError, match=message):
            load_file(tmp_path / name)
    # a DTD is refused in any encoding
    (tmp_path / "dtd.gpx").write_bytes(
        ('<!DOCTYPE gpx [<!ENTITY a "b">]><gpx><wpt lat="1" lon="2"/></gpx>').encode("utf-16")
    )
    with pytest.raises(ParseError, match="DTDs and entities are not allowed in GPX"):
        load_file(tmp_path / "dtd.gpx")
    # CSV and .waypoints stay UTF-8
    (tmp_path / "m.csv").write_bytes("# Straße\n51,-1\n".encode("latin-1"))
    with pytest.raises(ParseError, match=r"m\.csv: not UTF-8 text"):
        load_file(tmp_path / "m.csv")


# -- the shipped examples --------------------------------------------------------------------


def test_the_examples_are_the_default_scenarios_mission_in_every_format() -> None:
    from sim_backend.world import load_world

    assert {p.suffix for p in EXAMPLES} == {".waypoints", ".gpx", ".csv", ".kml", ".plan"}
    world = load_world(ROOT / "config" / "scenarios" / "default.toml")
    truth = [tuple(map(float, p)) for p in world.waypoints_latlon()]
    for path in EXAMPLES:
        wps = load_file(path)
        assert len(wps) == len(truth), path
        for w, (lat, lon) in zip(wps, truth, strict=True):
            assert great_circle_m(w.lat_deg, w.lon_deg, lat, lon) < 0.02, path
    home = parse_wpl((MISSIONS / "default.waypoints").read_text().replace("110", "120", 1))[0]
    assert great_circle_m(*home, 51.7520, -1.2577) < 0.01  # the home line: the start


def test_documented_commands_parse() -> None:
    """The example commands of config/hil.toml and README.md's tour are valid command lines
    (`x6wd client --wp ... load` was not) and name files that exist."""
    hil = (ROOT / "config" / "hil.toml").read_text().splitlines()
    commands = [
        c.strip() for line in hil if line.startswith("#   x6wd") for c in line[1:].split("&&")
    ]
    readme = (ROOT / "README.md").read_text()
    tour = [line.split("#")[0].strip() for line in readme.splitlines() if "x6wd client" in line]
    commands += [c for c in tour if "load " in c and "|" not in c]
    loads = [c for c in commands if " load " in f"{c} "]
    assert loads, commands
    for command in commands:
        argv = shlex.split(command)[1:]
        args = cli.build_parser(argv).parse_args(argv)  # SystemExit on an argument error
        if getattr(args, "file", None):
            assert (ROOT / args.file).is_file(), command
    assert "missions/default.gpx" in readme


# -- the command lines -----------------------------------------------------------------------


def x6wd(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "x6wd", *args], capture_output=True, text=True, timeout=60, cwd=ROOT
    )


def test_x6wd_mission_show_and_convert(tmp_path: Path) -> None:
    r = x6wd("mission", "show", "missions/default.waypoints")
    assert r.returncode == 0, r.stderr
    assert r.stdout.splitlines()[0].startswith("4 waypoints")
    assert "51.7522247 -1.2577000" in r.stdout and "total 69.8 m" in r.stdout
    out = tmp_path / "from_kml.waypoints"
    r = x6wd("mission", "convert", "missions/default.kml", str(out))
    assert r.returncode == 0 and "4 waypoints written (waypoints)" in r.stderr, r.stderr
    assert load_file(out) == load_file(MISSIONS / "default.kml")
    r = x6wd("mission", "convert", "missions/default.csv", "-", "--to", "gpx")
    assert r.returncode == 0 and parse_content(r.stdout) == load_file(MISSIONS / "default.csv")
    bad = tmp_path / "bad.waypoints"
    bad.write_text(QGC_FILE + "3\t0\t3\t177\t1\t2\t0\t0\t0\t0\t0\t1\n")
    r = x6wd("mission", "convert", str(bad), str(tmp_path / "x.gpx"))
    assert r.returncode == 2 and "Traceback" not in r.stderr
    assert r.stderr.strip().splitlines() == [
        f"x6wd mission: {bad} line 5: command 177 (DO_JUMP) is not supported: x6wd missions are "
        "NAV_WAYPOINT (16) items only"
    ]
    r = x6wd("mission", "convert", "missions/default.gpx", str(tmp_path / "x.kml"))
    assert r.returncode == 2 and "reads but does not write" in r.stderr
    # an existing output is replaced only on request
    before = out.read_bytes()
    r = x6wd("mission", "convert", "missions/default.csv", str(out))
    assert (
        r.returncode == 2
        and r.stderr.strip() == f"x6wd mission: {out}: exists; give --force to replace it"
    )
    assert out.read_bytes() == before
    r = x6wd("mission", "convert", "missions/default.csv", str(out), "--force")
    assert r.returncode == 0 and load_file(out) == load_file(MISSIONS / "default.csv")


def test_a_waypoint_at_0_0_is_refused_in_waypoints_files() -> None:
    """ArduPilot and QGroundControl read a NAV_WAYPOINT at 0, 0 as the vehicle's current
    position: taken literally it is a point in the Gulf of Guinea."""
    zero = QGC_FILE + "3\t0\t3\t16\t0\t0\t0\t0\t0.0\t0\t0\t1\n"
    with pytest.raises(ParseError, match=r"line 5: latitude and longitude are 0, 0"):
        parse_wpl(zero)
    with pytest.raises(ParseError, match="waypoint 2 is at 0, 0"):
        format_content([Waypoint(51.0, -1.0), Waypoint(0.0, 0.0)], "waypoints")
    assert parse_wpl(QGC_FILE + "3\t0\t3\t16\t0\t0\t0\t0\t0.0\t1e-7\t0\t1\n")[-1] == (0.0, 1e-7)


@pytest.fixture
def served() -> Iterator[tuple[LoopThread, ControlServer, RecordingBackend]]:
    lt = LoopThread()
    backend = RecordingBackend()
    srv = start_server(lt, backend)  # loopback, no token
    yield lt, srv, backend
    lt.run(srv.close())
    lt.close()


def test_client_loads_every_format(served, tmp_path: Path) -> None:
    _, srv, backend = served
    for path in EXAMPLES:
        r = x6wd("client", "--port", str(srv.port), "load", str(path.relative_to(ROOT)))
        assert r.returncode == 0 and "load: ok" in r.stdout, r.stderr
    loads = [arg for name, arg in backend.calls if name == "load_mission"]
    assert len(loads) == len(EXAMPLES)
    assert all(wps == loads[0] for wps in loads) and len(loads[0]) == 4
    bad = tmp_path / "m.waypoints"
    bad.write_text(
        "QGC WPL 110\n0\t1\t0\t16\t0\t0\t0\t0\t1\t2\t0\t1\n1\t0\t3\t21\t0\t0\t0\t0\t1\t2\t0\t1\n"
    )
    r = x6wd("client", "--port", str(srv.port), "load", str(bad))
    assert r.returncode == 2 and "line 3: command 21 (NAV_LAND) is not supported" in r.stderr
    assert "Traceback" not in r.stderr


def test_a_csv_field_over_the_csv_modules_limit_is_a_parse_error() -> None:
    # csv.Error escaped as a traceback (an outside check)
    with pytest.raises(ParseError, match=r"big\.csv: line 2: field larger than field limit"):
        mission_files.parse_csv("lat,lon\n" + "5" * 200_000 + ",1\n", "big.csv")
    rows = "".join(f"{51 + i * 1e-5},-1\n" for i in range(mission_files.MAX_WAYPOINTS + 500))
    with pytest.raises(ParseError, match=r"more than 10000 waypoints"):
        mission_files.parse_csv(rows, "huge.csv")


def test_gpx_waypoints_beside_a_track_without_a_route_are_refused() -> None:
    """A handheld's export (the day's track and a mark) was read as the mark alone, the track
    dropped silently (a second outside check): without a route, which is the path is the
    user's to say."""
    marked = _gpx('<wpt lat="51.753" lon="-1.258"><name>001</name></wpt>' + _trk((53.1, 53.2)))
    with pytest.raises(
        ParseError,
        match="^w.gpx: "
        + _re("1 point as <wpt> and a <trk> of 2 points, no <rte>: x6wd drives one path"),
    ):
        mission_files.parse_gpx(marked, "w.gpx")
    # an empty track beside the marks is no path: the marks are read
    assert mission_files.parse_gpx(_gpx('<wpt lat="51.1" lon="-1.1"/>' + _trk(()))) == [
        (51.1, -1.1)
    ]
