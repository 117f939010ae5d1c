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
