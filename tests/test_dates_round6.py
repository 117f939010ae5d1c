"""Audit 8d, clocks and dates: a receiver past a GPS week rollover (dates 1024 weeks early)
is corrected on the live path (reader -> runner -> WMM declination, gpsd port, recording,
status); a receiver with no date or a garbage one leaves the declination pending, which
status and the client say (0 in use, heading magnetic). The real daemon, its GPS on a pty
fed crafted NMEA."""

from __future__ import annotations

import dataclasses
import json
import logging
import os
import socket
import threading
import time
import tty
from collections.abc import Iterator
from datetime import UTC, datetime, timedelta
from pathlib import Path
from typing import Any

import pytest

from tests.test_daemon import ORIGIN, hil_config, run_daemon, wait_for
from x6wd.app.client import RemoteClient, render_status, render_watch
from x6wd.app.daemon import Daemon
from x6wd.core.config import GpsConfig, GpsdConfig, ServerConfig
from x6wd.core.recorder import decode_record, read_recording_parts
from x6wd.core.records import GpsFix, GpsSky

__all__ = ["run_daemon"]  # the fixture, shared with test_daemon
SERVER_PORT, GPSD_PORT = 9041, 9042
ROLLOVER = timedelta(weeks=1024)  # the legacy GPS week number's span


def _ck(body: str) -> str:
    c = 0
    for ch in body:
        c ^= ord(ch)
    return f"${body}*{c:02X}\r\n"


def _burst(now: datetime, dmy: str | None) -> bytes:
    """GGA + RMC at ORIGIN, dated ``dmy`` (None: ``now``'s date)."""
    hms = now.strftime("%H%M%S.") + f"{now.microsecond // 10000:02d}"
    lat, lon = ORIGIN
    la = f"{int(lat):02d}{(lat - int(lat)) * 60:07.4f}"
    lo = f"{int(-lon):03d}{(-lon - int(-lon)) * 60:07.4f}"
    date = now.strftime("%d%m%y") if dmy is None else dmy
    gga = _ck(f"GPGGA,{hms},{la},N,{lo},W,1,08,0.9,60.0,M,47.0,M,,")
    rmc = _ck(f"GPRMC,{hms},A,{la},N,{lo},W,0.0,,{date},,,A")
    return (rmc + gga).encode()


class PtyGps:
    """A receiver on a pty: bursts at 4 Hz, its clock now + ``offset``, date ``dmy``."""

    def __init__(self, offset: timedelta, dmy: str | None = None) -> None:
        self.master, self.slave = os.openpty()
        tty.setraw(self.master)
        tty.setraw(self.slave)
        self.url = f"serial://{os.ttyname(self.slave)}?baud=115200"
        self.offset, self.dmy = offset, dmy
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self) -> None:
        while not self.stop.is_set():
            now = datetime.now(UTC) + self.offset
            now = now.replace(microsecond=now.microsecond // 250_000 * 250_000)
            try:
                os.write(self.master, _burst(now, self.dmy))
            except OSError:
                return
            self.stop.wait(0.25)

    def close(self) -> None:
        self.stop.set()
        self.thread.join(2)
        os.close(self.master)
        os.close(self.slave)


@pytest.fixture
def pty_gps() -> Iterator[Any]:
    made: list[PtyGps] = []

    def make(offset: timedelta = timedelta(0), dmy: str | None = None) -> PtyGps:
        g = PtyGps(offset, dmy)
        made.append(g)
        return g

    yield make
    for g in made:
        g.close()


def _config(tmp_path: Path, gps: PtyGps) -> Any:
    cfg = hil_config(tmp_path)
    return dataclasses.replace(
        cfg,
        gps=GpsConfig(url=gps.url, rate_hz=4.0, stale_s=2.0),
        motors=dataclasses.replace(cfg.motors, url="log://"),
        server=ServerConfig(port=SERVER_PORT),
        gpsd=GpsdConfig(port=GPSD_PORT),
    )


def _tpv_time() -> str:
    with socket.create_connection(("127.0.0.1", GPSD_PORT), 5) as s:
        s.sendall(b'?WATCH={"enable":true,"json":true};\n')
        f = s.makefile("r")
        deadline = time.monotonic() + 5
        while time.monotonic() < deadline:
            obj = json.loads(f.readline())
            if obj.get("class") == "TPV" and "time" in obj:
                return str(obj["time"])
    raise AssertionError("no TPV with a time")


def test_a_week_rollover_receiver_is_corrected_on_the_live_path(
    tmp_path: Path, run_daemon, pty_gps, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.INFO)
    gps = pty_gps(-ROLLOVER)  # a NEO-5 whose firmware predates 2019-04-07
    today = datetime.now(UTC)
    r = run_daemon(Daemon(_config(tmp_path, gps)))
    with RemoteClient("127.0.0.1", r.port) as c:
        st = wait_for(
            lambda: (
                (d := (s := c.request("status"))["declination"]).get("pending") is None
                and ("deg" in d or "error" in d)
                and s
            ),
            10,
            "the WMM declination",
        )
        decl = st["declination"]
        assert decl["source"] == "wmm" and "error" not in decl and "deg" in decl, decl
        roll = st["gps_week_rollover"]
        assert roll["corrected"] > 0 and roll["weeks_added"] == 1024, roll
        assert roll["receiver_utc"].startswith(str(today.year - 20)) or roll[
            "receiver_utc"
        ].startswith(str(today.year - 19)), roll
        assert roll["corrected_utc"][:10] in (
            today.date().isoformat(),
            (today + timedelta(seconds=30)).date().isoformat(),
        ), roll
        assert roll["floor_utc"] == "2026-01-01"  # this release
        text = render_status(st)
        assert "receiver week rollover" in text and "deg true" in text, text
        assert "deg magnetic" not in text
        assert _tpv_time()[:4] == str(today.year)
    assert r.stop() == 0
    warnings = [
        m.getMessage()
        for m in caplog.records
        if m.levelno == logging.WARNING and "week rollover" in m.getMessage()
    ]
    assert len(warnings) == 1, warnings
    assert roll["receiver_utc"] in warnings[0] and "1024 weeks" in warnings[0]
    assert not [m for m in caplog.records if "World Magnetic Model (" in m.getMessage()]
    fixes = [
        rec
        for path in sorted((tmp_path / "rec").glob("*.jsonl"))
        for rec in map(decode_record, read_recording_parts(path))
        if isinstance(rec, GpsFix) and rec.utc is not None
    ]
    assert fixes and all(f.utc.year == today.year for f in fixes)  # type: ignore[union-attr]


@pytest.mark.parametrize("dmy", ["", "993317"], ids=["no date", "garbage date"])
def test_without_a_dated_fix_status_and_client_say_the_declination_is_pending(
    tmp_path: Path, run_daemon, pty_gps, dmy: str
) -> None:
    gps = pty_gps(dmy=dmy)
    r = run_daemon(Daemon(_config(tmp_path, gps)))
    with RemoteClient("127.0.0.1", r.port) as c:
        wait_for(lambda: r.daemon.first_fix, 10, "first fix")
        time.sleep(0.5)
        st = c.request("status")
    assert r.stop() == 0
    assert st["declination"] == {
        "source": "wmm",
        "deg": 0.0,
        "pending": "no dated fix yet: heading is magnetic",
    }
    text = render_status(st)
    assert "declination +0.00 deg (wmm: no dated fix yet: heading is magnetic)" in text, text
    tel = dict(st["telemetry"] or {}, heading_deg=12.0)
    assert "heading    12.0 deg magnetic" in render_status({**st, "telemetry": tel})
    assert "heading    12.0 deg magnetic" in render_watch(tel, st)
    assert "deg true" not in render_status({**st, "telemetry": tel}).split("bearing")[0]
    assert st["gps_week_rollover"]["corrected"] == 0


def test_the_correction_adds_whole_rollovers_until_the_floor() -> None:
    from drivers.gps_io import GPS_WEEK_ROLLOVER, WeekRolloverCorrection

    assert GPS_WEEK_ROLLOVER == ROLLOVER
    floor = datetime(2026, 1, 1, tzinfo=UTC)
    fix = WeekRolloverCorrection(floor, clock=lambda: datetime(1970, 1, 1, tzinfo=UTC))
    old = datetime(2026, 12, 5, 9, 13, 42, tzinfo=UTC) - 2 * GPS_WEEK_ROLLOVER  # 1987
    recs: list[Any] = [GpsFix(t_s=1.0, utc=old), GpsSky(t_s=1.0, utc=old), GpsFix(t_s=2.0)]
    out: list[Any] = fix.apply(recs)
    assert out[0].utc == out[1].utc == datetime(2026, 12, 5, 9, 13, 42, tzinfo=UTC)
    assert out[2] is recs[2] and fix.corrected == 2 and fix.weeks_added == 2048
    ok: list[Any] = [GpsFix(t_s=3.0, utc=floor)]
    assert fix.apply(ok) is ok  # not before the floor: untouched


def test_a_set_system_clock_keeps_a_date_it_is_nearer_to() -> None:
    """Hardware in the loop runs the simulator's receiver at its scenario's date (2020 in
    config/scenarios/default.toml) on a machine whose clock is set: that is no rollover,
    and 2039 would put the WMM out of its model. A rollover date (2007) next to a 2026
    clock is still corrected, and so is any date before the floor on a 1970 clock."""
    from drivers.gps_io import GPS_WEEK_ROLLOVER, WeekRolloverCorrection

    floor = datetime(2026, 1, 1, tzinfo=UTC)
    now = datetime(2026, 12, 5, 9, 0, 0, tzinfo=UTC)
    fix = WeekRolloverCorrection(floor, clock=lambda: now)
    sim: list[Any] = [GpsFix(t_s=1.0, utc=datetime(2020, 1, 1, 12, tzinfo=UTC))]
    assert fix.apply(sim) is sim and fix.corrected == 0
    rolled: list[Any] = [GpsFix(t_s=2.0, utc=now - GPS_WEEK_ROLLOVER)]
    assert fix.apply(rolled)[0].utc == now and fix.corrected == 1
    booted = WeekRolloverCorrection(floor, clock=lambda: datetime(1970, 1, 1, tzinfo=UTC))
    assert booted.apply(sim)[0].utc == sim[0].utc + GPS_WEEK_ROLLOVER


def test_the_console_labels_the_heading_magnetic_until_the_declination_is_known(
    tmp_path: Path, run_daemon, pty_gps
) -> None:
    """The web console said "true" for a compass heading with no declination applied: it
    follows ``status``'s ``declination`` as the client does (Debian's chromium)."""
    from tests.test_console import chromium, open_page, text
    from x6wd.core.config import ConsoleConfig

    cfg = dataclasses.replace(
        _config(tmp_path, pty_gps(dmy="")), console=ConsoleConfig(enabled=True, port=0)
    )
    r = run_daemon(Daemon(cfg))
    d = chromium(tmp_path)
    try:
        open_page(d, r)
        wait_for(lambda: r.daemon.first_fix, 10, "first fix")
        shown = wait_for(
            lambda: (t := text(d, "tel-heading")) not in ("", "—") and "magnetic" in t and t,
            15,
            "the heading labelled magnetic",
        )
        assert shown.endswith("° magnetic") and "true" not in shown, shown
    finally:
        d.quit()
    assert r.stop() == 0
