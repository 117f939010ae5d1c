"""Mission files, round 13's audit: numbers too large for a float, and inputs that are not
regular files.

A .plan (JSON) integer of 400 digits made ``float()`` raise OverflowError: a traceback and
exit 1 from ``x6wd mission``, ``x6wd client load`` and ``x6wd sim``, and a closed WebSocket
in the console's "Load file..." (``mission.parse``). Now every number read from a file goes
through ``to_float`` (a ParseError naming the item) and messages show at most 40 characters
of a field. ``load_file`` reads any input at most 8 MiB + 1 byte (a pipe such as
``<(zcat m.csv.gz)`` is read, ``/dev/zero`` or a 100 MB pipe refused at the limit) and never
waits for a FIFO's writer.
"""

from __future__ import annotations

import asyncio
import json
import os
import re
import subprocess
import sys
import time
from pathlib import Path

import pytest

from tests.conftest import ROOT
from tests.test_console import console_config, daemon_with, ws_to
from x6wd.app import cli
from x6wd.core import mission_files
from x6wd.core.errors import ParseError
from x6wd.core.mission_files import (
    from_pairs,
    load_file,
    parse_content,
    parse_csv,
    parse_gpx,
    parse_kml,
    parse_plan,
    parse_wpl,
)

BIG = int("1" * 400)  # a JSON integer no float holds


def _plan(params: list[object] | None = None, home: list[object] | None = None) -> str:
    item = {
        "type": "SimpleItem", "command": 16, "frame": 3, "autoContinue": True,
        "params": params or [0, 0, 0, None, 51.7521, -1.2578, 0],
    }  # fmt: skip
    mission = {"items": [item], "plannedHomePosition": home or [51.752, -1.258, 60]}
    return json.dumps({"fileType": "Plan", "mission": mission})


@pytest.mark.parametrize(
    ("params", "named"),
    [
        ([0, 0, 0, None, BIG, -1.2578, 0], "mission item 1: latitude is too large"),
        ([0, 0, 0, None, 51.7521, -BIG, 0], "mission item 1: longitude is too large"),
        ([0, BIG, 0, None, 51.7521, -1.2578, 0], "item 1: params[1] (acceptance radius) is too"),
        ([BIG, 0, 0, None, 51.7521, -1.2578, 0], "item 1: params[0] (hold time) is too large"),
    ],
)
def test_a_plan_integer_too_large_for_a_float_is_refused_naming_the_item(
    params: list[object], named: str
) -> None:
    with pytest.raises(
        ParseError, match=r"too large for a number: -?1{39,40}\.\.\. \(400 digits\)"
    ) as e:
        parse_plan(_plan(params), "m.plan")
    assert named in str(e.value) and len(str(e.value)) < 200, e.value


def test_a_plan_home_too_large_for_a_float_is_a_note_as_any_bad_home() -> None:
    m = parse_plan(_plan(home=[BIG, 0, 0]), "m.plan")
    assert len(m) == 1 and m.home is None
    assert any("plannedHomePosition: latitude is too large" in n for n in m.notes), m.notes


@pytest.mark.parametrize(
    ("field", "named"),
    [
        ("51.7521", "mission item 1: latitude is too large for a number"),
        ('"params": [0', "mission item 1: params[0] (hold time) is too large for a number"),
        ('"command": 16', "mission item 1: command is too large for a number"),
    ],
)
def test_a_json_integer_past_pythons_digit_limit_is_too_large_naming_the_item(
    field: str, named: str
) -> None:
    """A 4301-digit integer was "not valid JSON: ... use sys.set_int_max_str_digits() to
    increase the limit" (json.loads' int() refusing it): the file is valid JSON, the advice a
    Python call, no item named (review of c30d4e7, finding 2)."""
    head = field.rstrip("0123456789.")
    text = _plan().replace(field, head + "1" * 4301)
    with pytest.raises(ParseError) as e:
        parse_plan(text, "m.plan")
    assert str(e.value) == f"m.plan {named}: an integer of 4301 digits", e.value


def test_the_protocols_pairs_with_a_huge_integer_are_refused() -> None:
    with pytest.raises(ParseError, match=r"wps\[0\]: latitude is too large for a number"):
        from_pairs([[BIG, 0.0]], "wps")


def test_text_formats_with_1e400_or_huge_digit_strings_are_refused_in_short() -> None:
    huge = "1" * 100_000  # float() reads it as inf: refused as not finite, shown cut
    cases = [
        (parse_csv, f"51.5,-1.2\n{huge},-1.2\n", "line 2: latitude must be finite"),
        (parse_csv, "lat,lon\n51.5,1e400\n", "line 2: longitude must be finite, got '1e400'"),
        (parse_gpx, f'<gpx><wpt lat="{huge}" lon="0"/></gpx>', "<wpt> #1: latitude must be"),
        (
            parse_kml,
            f"<kml><Placemark><Point><coordinates>1e400,{huge}</coordinates></Point></Placemark></kml>",
            "coordinate 1: latitude must be finite",
        ),
        (
            parse_wpl,
            f"QGC WPL 110\n{huge}\t0\t3\t16\t0\t0\t0\t0\t51\t-1\t0\t1\n",
            "index is too large for a number: an integer of 100000 digits",
        ),
        (parse_wpl, f"QGC WPL 110\n1\t0\t3\t16\t{huge}\t0\t0\t0\t51\t-1\t0\t1\n", "hold time"),
        (parse_wpl, "QGC WPL 110\n1\t0\t3\t16\t0\t0\t0\t0\t51\t1e400\t0\t1\n", "must be finite"),
    ]
    for parse, text, named in cases:
        with pytest.raises(ParseError) as e:
            parse(text, "m")
        assert named in str(e.value) and len(str(e.value)) < 300, (parse.__name__, e.value)


def test_x6wd_mission_show_of_a_huge_integer_plan_is_one_line_and_exit_2(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = tmp_path / "big.plan"
    path.write_text(_plan([0, 0, 0, None, 51.7521, BIG, 0]))
    assert cli.main(["mission", "show", str(path)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "big.plan mission item 1: longitude is too large" in err


@pytest.mark.integration
def test_the_consoles_mission_parse_of_a_huge_integer_replies_and_keeps_the_link(
    tmp_path: Path,
) -> None:
    async def program(r) -> None:  # type: ignore[no-untyped-def]
        async with ws_to(r) as w:
            text = _plan([0, 0, 0, None, 51.7521, BIG, 0])
            reply = await w.request("mission.parse", content=text, format="plan", name="b.plan")
            assert not reply["ok"] and reply["error"]["reason"] == "bad_mission", reply
            assert "b.plan mission item 1: longitude is too large" in reply["error"]["message"]
            assert (await w.request("status"))["ok"]  # the same link still answers

    with daemon_with(console_config(tmp_path)) as r:
        asyncio.run(program(r))


@pytest.mark.integration
def test_the_consoles_mission_parse_survives_a_reader_that_raises(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Defence in depth: any exception from a reader is an error reply, not a closed link
    (the reader here is made to raise what the .plan reader raised before round 13)."""

    def broken(text: str, source: str) -> mission_files.Mission:
        raise OverflowError("int too large to convert to float")

    monkeypatch.setitem(mission_files.PARSERS, "csv", broken)

    async def program(r) -> None:  # type: ignore[no-untyped-def]
        async with ws_to(r) as w:
            reply = await w.request("mission.parse", content="51,-1\n", format="csv", name="m")
            assert (
                reply["error"]["message"] == "m: cannot be read: int too large to convert to float"
            )
            assert (await w.request("status"))["ok"]

    with daemon_with(console_config(tmp_path)) as r:
        asyncio.run(program(r))


# -- inputs that are not regular files ---------------------------------------------------------


def test_a_fifo_without_a_writer_is_refused_at_once(tmp_path: Path) -> None:
    fifo = tmp_path / "m.csv"
    os.mkfifo(fifo)
    t0 = time.monotonic()
    r = subprocess.run(
        [sys.executable, "-m", "x6wd", "mission", "show", str(fifo)],
        capture_output=True, text=True, timeout=30, cwd=ROOT,
    )  # fmt: skip
    assert r.returncode == 2 and "no writer has it open" in r.stderr, r.stderr
    assert r.stderr.count("\n") == 1 and time.monotonic() - t0 < 20


def test_a_fifo_whose_writer_waits_is_read(tmp_path: Path) -> None:
    fifo = tmp_path / "m.csv"
    os.mkfifo(fifo)
    writer = subprocess.Popen(["sh", "-c", f"printf '51.5,-1.2\\n51.6,-1.2\\n' > '{fifo}'"])
    try:
        time.sleep(0.3)  # the writer is in open(), waiting for a reader
        assert load_file(fifo) == [(51.5, -1.2), (51.6, -1.2)]
    finally:
        writer.wait(10)


def _pipe_of(data_bytes: int) -> subprocess.Popen[bytes]:
    """A writer of ``data_bytes`` of CSV rows into a pipe (its read end: ``.stdout``)."""
    rows = f"(b'51.5,-1.2\\n' * {data_bytes // 10 + 1})[:{data_bytes}]"
    code = f"import sys; sys.stdout.buffer.write({rows})"
    return subprocess.Popen(
        [sys.executable, "-c", code], stdout=subprocess.PIPE, stderr=subprocess.DEVNULL
    )


def test_a_pipe_is_read_and_capped_at_the_limit() -> None:
    small = _pipe_of(40)
    try:  # as <(printf ...) or /dev/stdin: read once
        assert len(load_file(f"/dev/fd/{small.stdout.fileno()}", "csv")) == 4  # type: ignore[union-attr]
    finally:
        small.stdout.close()  # type: ignore[union-attr]
        small.wait(10)
    big = _pipe_of(20 * 1024 * 1024)  # before: read whole (a 100 MB one took 3.8 GB)
    try:
        with pytest.raises(ParseError, match=r"/dev/fd/\d+: larger than 8388608 bytes"):
            load_file(f"/dev/fd/{big.stdout.fileno()}", "csv")  # type: ignore[union-attr]
    finally:
        big.stdout.close()  # type: ignore[union-attr]
        big.wait(10)


def test_a_regular_file_over_the_limit_is_refused_and_under_it_read(tmp_path: Path) -> None:
    path = tmp_path / "m.csv"
    path.write_text("51.5,-1.2\n" * 10)
    assert len(load_file(path, max_bytes=100)) == 10
    with pytest.raises(ParseError, match=r"m\.csv: larger than 99 bytes"):
        load_file(path, max_bytes=99)
    assert parse_content("51.5,-1.2\n") == [(51.5, -1.2)]


@pytest.mark.parametrize(
    "shell",
    [
        "$X mission show --from csv <(zcat /nonexistent/m.csv.gz)",  # the writer failed
        ": | $X mission show --from csv /dev/stdin",  # wrote nothing and closed, at once
        "(sleep 0.5) | $X mission show --from csv /dev/stdin",  # ... after a while
    ],
)
def test_an_empty_anonymous_pipe_is_empty_not_a_fifo_without_a_writer(shell: str) -> None:
    """An anonymous pipe whose writer ran and wrote nothing was "a pipe or FIFO with nothing
    to read: no writer has it open (... start the writer first)" when its end of file came
    at once, "no waypoints" when it came late (review of c30d4e7, finding 4). Now both say
    the input is empty; "no writer" is left to named FIFOs (the test above)."""
    x6wd = f"{sys.executable} -m x6wd"
    r = subprocess.run(
        ["bash", "-c", shell.replace("$X", x6wd)],
        capture_output=True, text=True, timeout=60, cwd=ROOT,
    )  # fmt: skip
    assert r.returncode == 2, r.stderr
    assert "empty: no waypoints" in r.stderr and "writer" not in r.stderr, r.stderr


def test_an_empty_file_is_said_empty_in_every_format(tmp_path: Path) -> None:
    for ext in mission_files.PARSERS:
        path = tmp_path / f"m.{ext}"
        path.write_bytes(b"")
        with pytest.raises(ParseError, match=rf"^{path}: empty: no waypoints$"):
            load_file(path)


_X = "x" * 100_000
_RTE = f'<rte><name>{_X}</name><rtept lat="1" lon="1"/></rte>'
_WPL_ROW = "QGC WPL 110\n1\t0\t3\t16\t{hold}\t{radius}\t0\t0\t51\t-1\t0\t{cont}\n"


@pytest.mark.parametrize(
    ("name", "content", "says"),
    [
        ("f.plan", '{"fileType":"' + _X + '","mission":{}}', "got 'xxx"),
        ("t.plan", '{"fileType":"Plan","mission":{"items":[{"type":"' + _X + '"}]}}', "type 'x"),
        (
            "a.plan",
            _plan().replace('"autoContinue": true', '"autoContinue": "' + _X + '"'),
            "mission item 1: autoContinue 'xxx",
        ),
        (
            "n.kml",
            "<kml><Placemark><name>" + _X + "</name><Polygon/></Placemark></kml>",
            "n.kml <Placemark> #1 'xxx",
        ),
        ("ns.gpx", '<gpx xmlns="urn:' + _X + '"><wpt lat="1" lon="1"/></gpx>', "namespace 'urn:x"),
        ("r.gpx", "<" + _X + "/>", "root element is <xxx"),
        ("r.kml", "<" + _X + "/>", "root element is <xxx"),
        ("d.csv", 'lat,lon\n"51,' + "7" * 100_000 + '",-1.2\n', "has a decimal comma"),
        ("h.waypoints", _WPL_ROW.format(hold="1" * 400, radius=0, cont=1), "hold time (param1)"),
        ("c.waypoints", _WPL_ROW.format(hold=0, radius=0, cont="1" * 400), "autocontinue"),
        ("g.gpx", f'<gpx><rte><rtept lat="1" lon="1"/></rte>{_RTE}</gpx>', "2 routes"),
    ],
)
def test_every_message_quoting_a_field_is_capped(
    tmp_path: Path, name: str, content: str, says: str
) -> None:
    """A 100 kB field was quoted whole (100-200 kB messages, which the console passes to the
    page): .plan fileType, item type and autoContinue, a KML Placemark's name, a GPX namespace,
    a root tag, a CSV decimal-comma field (twice); .waypoints cut a 400-digit value to 40
    digits with no "...", another number (review of c30d4e7, finding 2). Now each shows at
    most 40 characters, "...", and the field's own size."""
    path = tmp_path / name
    path.write_text(content, encoding="utf-8")
    with pytest.raises(ParseError) as e:
        load_file(path)
    msg = str(e.value)
    assert says in msg and len(msg) < 400, msg[:500]
    size = "100000" if "7" * 1000 not in content else "100003"
    if name.endswith(".waypoints"):
        assert "1" * 40 + "... (400 characters)" in msg, msg
    elif name == "ns.gpx":
        assert "... (100004 characters)" in msg, msg
    else:
        assert f"... ({size} characters)" in msg, msg


def test_the_module_quotes_input_through_one_capping_helper() -> None:
    """The class of finding 2: no f-string field of the module quotes a value with !r or cuts
    it with :.N (no "...", no size) but the module's own constants; _shown does it."""
    source = Path(mission_files.__file__).read_text(encoding="utf-8")
    bare = re.findall(r"\{([^{}]+?)(?:!r|!s|:\.\d+)[^{}]*\}", source)
    assert "WPL_HEADER" in bare  # the pattern finds such fields at all
    assert set(bare) <= {"WPL_HEADER", "_GPX_NAMESPACES[0]"}, bare
