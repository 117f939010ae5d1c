"""Round 13: the GPS receiver's rate against its line (an outside audit at 2-4 Hz, 4800-115200
baud).

1. 4 Hz on a 4800-baud line: 120 bytes an epoch for RMC + GGA's 152, yet the configuration
   passed, CFG-RATE 250 ms went out and nothing said so (fixes a median 2.08 s late). Now the
   configuration refuses it where the daemon would ask for it (exit 2), a line known only at
   the open is one WARNING, and a full line (a receiver printing more than its baud carries:
   configure_receiver = false, 4 Hz at 9600 with a NEO-5's default sentences) is measured,
   shown in status and warned of.
2. The "fixes arrive too slowly" WARNING named gps.rate_hz when the rate was
   [sim] gps_rate_hz's, and never the line.
3. [sim] gps_baud took 12345 and up to 921600; a configured receiver's url any standard baud.
6. A replay:// GPS said "cycle":1.0 on the gpsd port while playing a 4 Hz log.
"""

from __future__ import annotations

import dataclasses
import logging
import os
import subprocess
import sys
import threading
import time
import tty
from collections.abc import Iterator
from datetime import UTC, datetime, timedelta
from pathlib import Path
from typing import Any

import pytest
import serial

from drivers.gps_io import GpsReader, LineLoad, ReceiverSetup, native_usb_path
from drivers.nmea import checksum
from tests.conftest import ROOT
from tests.test_daemon import hil_config, run_daemon, wait_for
from x6wd.app.client import RemoteClient
from x6wd.app.daemon import Daemon
from x6wd.core.config import GpsConfig, SimConfig, loads
from x6wd.core.errors import ConfigError

__all__ = ["run_daemon"]

CONFIGURED_4HZ = "[gps]\nconfigure_receiver = true\nrate_hz = 4.0\n[safety]\nfix_stale_s = 2.5\n"


def _s(body: str) -> bytes:
    return f"${body}*{checksum(body.encode()):02X}\r\n".encode()


def _epoch(t: datetime, full: bool = True) -> bytes:
    """RMC + GGA at ``t`` (and VTG, GSA, GLL: a NEO-5's defaults, ~330 bytes, if ``full``)."""
    hms = t.strftime("%H%M%S.") + f"{t.microsecond // 10000:02d}"
    dmy = t.strftime("%d%m%y")
    out = _s(f"GPRMC,{hms},A,5140.00000,N,03945.00000,E,0.0,,{dmy},,,A")
    if full:
        out += _s("GPVTG,,T,,M,0.0,N,0.0,K,A")
    out += _s(f"GPGGA,{hms},5140.00000,N,03945.00000,E,1,08,1.0,100.0,M,10.0,M,,")
    if full:
        out += _s("GPGSA,A,3,01,02,03,04,05,06,07,08,,,,,2.0,1.0,1.7")
        out += _s(f"GPGLL,5140.00000,N,03945.00000,E,{hms},A,A")
    return out


# -- 1 and 3: the configuration -------------------------------------------------------------


def test_a_configured_rate_whose_epoch_cannot_carry_rmc_and_gga_is_refused_in_hil() -> None:
    text = CONFIGURED_4HZ + "[sim]\ngps_baud = 4800\n"
    text = text.replace("rate_hz = 4.0\n", 'rate_hz = 4.0\nurl = "sim://"\n', 1)
    with pytest.raises(ConfigError) as exc:
        loads(text)
    msg = str(exc.value)
    assert msg.startswith("gps.rate_hz: 4 Hz on a 4800-baud line (sim.gps_baud = 4800)"), msg
    assert "120 bytes an epoch" in msg and "152" in msg and "3.1 Hz" in msg
    # 3 Hz leaves 160 bytes: accepted; so is 4 Hz at 9600 (240) and a receiver not configured
    loads(text.replace("rate_hz = 4.0", "rate_hz = 3.0"))
    loads(text.replace("4800", "9600"))
    loads(text.replace("configure_receiver = true", "configure_receiver = false"))


@pytest.fixture
def pty_path() -> Iterator[str]:
    master, slave = os.openpty()
    yield os.ttyname(slave)
    os.close(master)
    os.close(slave)


def _preflight(tmp_path: Path, url: str, configure: bool = True, rate_hz: float = 4.0) -> None:
    cfg = hil_config(tmp_path)
    cfg = dataclasses.replace(
        cfg, gps=GpsConfig(url=url, rate_hz=rate_hz, stale_s=2.0, configure_receiver=configure)
    )
    d = Daemon(cfg)
    try:
        d._preflight()
    finally:
        if d.devices is not None:
            d.devices.close()


def test_a_configured_rate_the_urls_line_cannot_carry_is_refused_at_start_up(
    tmp_path: Path, pty_path: str
) -> None:
    url = f"serial://{pty_path}?baud=4800"
    with pytest.raises(ConfigError) as exc:
        _preflight(tmp_path, url)
    msg = str(exc.value)
    assert msg.startswith("gps.rate_hz: 4 Hz on a 4800-baud line (gps.url's baud=4800)"), msg
    assert "120 bytes an epoch" in msg and "lower gps.rate_hz to 3.1 Hz" in msg
    _preflight(tmp_path, url, rate_hz=3.0)
    _preflight(tmp_path, url, configure=False)
    _preflight(tmp_path, f"serial://{pty_path}?baud=9600")


def test_a_native_usb_receiver_is_not_refused_for_its_urls_baud(tmp_path: Path) -> None:
    """A CDC-ACM receiver (/dev/ttyACM*) is not paced by the url's baud: 4 Hz with
    baud=4800 is no short line there (start-up goes on to the device node itself)."""
    url = f"serial://{tmp_path / 'ttyACM0'}?baud=4800"
    with pytest.raises(ConfigError) as exc:
        _preflight(tmp_path, url)  # no such node here: refused for that, not for the line
    assert "gps.url" in str(exc.value) and "rate_hz" not in str(exc.value), exc.value


def test_the_cli_stops_with_exit_2_naming_the_rate_and_the_baud(
    tmp_path: Path, pty_path: str
) -> None:
    cfg = tmp_path / "x.toml"
    url = f"serial://{pty_path}?baud=4800"
    cfg.write_text(CONFIGURED_4HZ.replace("rate_hz = 4.0\n", f'rate_hz = 4.0\nurl = "{url}"\n'))
    res = subprocess.run(
        [sys.executable, "-m", "x6wd", "run", "--config", str(cfg)],
        capture_output=True,
        text=True,
        timeout=120,
        cwd=ROOT,
    )
    assert res.returncode == 2, res.stderr
    assert "gps.rate_hz: 4 Hz on a 4800-baud line (gps.url's baud=4800)" in res.stderr
    assert "Traceback" not in res.stderr


@pytest.mark.parametrize("baud", [1200, 2400, 12345, 230400, 921600])
def test_sim_gps_baud_takes_only_a_neo5_rate(baud: int) -> None:
    with pytest.raises(ConfigError, match=rf"sim\.gps_baud: must be one of 4800, .*, got {baud}"):
        loads(f"[sim]\ngps_baud = {baud}\n")


@pytest.mark.parametrize("baud", [4800, 9600, 19200, 38400, 57600, 115200])
def test_sim_gps_baud_takes_the_neo5_rates(baud: int) -> None:
    assert loads(f"[sim]\ngps_baud = {baud}\n").sim.gps_baud == baud


def test_a_configured_receivers_url_baud_is_a_neo5_rate(tmp_path: Path, pty_path: str) -> None:
    url = f"serial://{pty_path}?baud=230400"
    with pytest.raises(ConfigError, match=r"gps\.url: baud=230400 .*NEO-5.*115200"):
        _preflight(tmp_path, url)
    _preflight(tmp_path, url, configure=False)  # another receiver, not configured: any rate


# -- 1: a line known only at the open -------------------------------------------------------


def test_a_line_too_slow_for_rmc_and_gga_at_the_open_is_one_warning(caplog: Any) -> None:
    caplog.set_level(logging.WARNING)
    setup = ReceiverSetup(4.0)
    assert setup.line_short is None  # 9600 until the port says
    setup.use_baud(4800)
    setup.use_baud(4800)  # a reopen: not again
    assert (
        setup.line_short is not None and "4800 baud at 4 Hz carries 120 bytes" in setup.line_short
    )
    assert setup.status()["line_short"] == setup.line_short
    assert len([r for r in caplog.records if "120 bytes an epoch" in r.getMessage()]) == 1
    setup.use_baud(38400)
    assert setup.line_short is None and "line_short" not in setup.status()


# -- 1 and 2: the line's load on a real pty -------------------------------------------------


class LinePty:
    """A pty whose far end writes NMEA epochs (4 Hz, dated) at ``bytes_per_s`` at most:
    a line at its capacity when the epochs need more."""

    def __init__(self, *args: Any) -> None:
        """A raw pty pair and the writer thread: ``_run(*args)`` writes its far end."""
        self.master, self.slave = os.openpty()
        tty.setraw(self.master)
        tty.setraw(self.slave)
        self.path = os.ttyname(self.slave)
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._run, args=args, daemon=True)
        self.thread.start()

    def _run(self, bytes_per_s: float, full: bool) -> None:
        t = datetime(2026, 6, 1, 12, 0, tzinfo=UTC)
        data = b"".join(_epoch(t + timedelta(seconds=k / 4), full) for k in range(400))
        chunk = max(1, int(bytes_per_s / 100))  # 10 ms of line
        t0 = time.monotonic()
        for i in range(0, len(data), chunk):
            if self.stop.wait(max(0.0, t0 + i / bytes_per_s - time.monotonic())):
                return
            os.write(self.master, data[i : i + chunk])

    def close(self) -> None:
        self.stop.set()
        self.thread.join(5)
        os.close(self.master)
        os.close(self.slave)


@pytest.fixture
def line_pty() -> Iterator[type[LinePty]]:
    made: list[LinePty] = []

    def make(bytes_per_s: float, full: bool) -> LinePty:
        made.append(LinePty(bytes_per_s, full))
        return made[-1]

    yield make  # type: ignore[misc]
    for p in made:
        p.close()


def _read_for(reader: GpsReader, seconds: float) -> None:
    end = time.monotonic() + seconds
    try:
        while time.monotonic() < end:
            reader.poll(0.05)
    finally:
        reader.close()


def test_a_full_line_shows_in_status_and_names_the_keys(line_pty: Any, caplog: Any) -> None:
    # a NEO-5's default sentences at 4 Hz (~1300 bytes/s) on 4800 baud (480): the line runs
    # full, the fixes come at ~1.5 Hz
    caplog.set_level(logging.WARNING)
    pty = line_pty(480.0, True)
    reader = GpsReader(
        lambda: serial.Serial(pty.path, 4800, timeout=0),
        stale_s=5.0,
        expected_rate_hz=4.0,
        expected_rate_key="sim.gps_rate_hz",
        baud_key="sim.gps_baud",
    )
    reader.poll(0.05)  # opens the port
    _read_for(reader, 4.5)
    st = reader.fix_rate.status()
    assert st["line"]["baud"] == 4800 and 0.9 <= st["line"]["load"] <= 1.1, st
    assert (
        "the line is full (" in st["line_full"]
        and "raise the baud rate (sim.gps_baud)" in (st["line_full"])
    )
    assert "lower sim.gps_rate_hz" in st["line_full"]
    # the too-slow complaint names the key that set the rate, and the line as the cause
    slow = st["slow"]
    assert "under sim.gps_rate_hz = 4 Hz" in slow and "gps.rate_hz =" not in slow.replace(
        "sim.gps_rate_hz =", ""
    )
    # 4 Hz at 4800 baud cannot carry RMC + GGA whatever the receiver prints (the full line
    # at 9600: test_slow_fixes_in_hil_name_sim_gps_rate_hz_and_the_full_line)
    assert "the line is the cause: 4800 baud at 4 Hz carries 120 bytes an epoch" in slow, slow
    warnings = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert len([w for w in warnings if "GPS: the line is full" in w]) == 1, warnings
    assert len([w for w in warnings if "under sim.gps_rate_hz" in w]) == 1, warnings
    assert any("the line is the cause" in w for w in warnings), warnings


def test_a_line_at_half_load_is_not_full(line_pty: Any, caplog: Any) -> None:
    caplog.set_level(logging.WARNING)
    pty = line_pty(240.0, False)  # RMC + GGA at 4 Hz would be ~560: ~1.7 Hz of them
    reader = GpsReader(
        lambda: serial.Serial(pty.path, 4800, timeout=0), stale_s=5.0, expected_rate_hz=1.0
    )
    reader.poll(0.05)
    _read_for(reader, 3.5)
    st = reader.fix_rate.status()
    assert 0.4 <= st["line"]["load"] <= 0.6, st
    assert "line_full" not in st and "slow" not in st
    assert not [r for r in caplog.records if "line" in r.getMessage()]


def test_the_load_of_a_socket_is_not_measured() -> None:
    load = LineLoad()
    load.restart(None, 0.0)  # a socket or a replay: its line rate is not known
    load.add(100000, 1.0)
    load.tick(10.0)
    assert load.load is None and load.status() == {}


def test_slow_fixes_in_hil_name_sim_gps_rate_hz_and_the_full_line(
    tmp_path: Path, run_daemon: Any, caplog: Any
) -> None:
    # the audit's repro_slow_key: [sim] gps_rate_hz = 4 at 9600 baud, gps.rate_hz left at 1
    caplog.set_level(logging.WARNING)
    cfg = hil_config(tmp_path, sim=SimConfig(gps_rate_hz=4.0, gps_baud=9600))
    assert cfg.gps.rate_hz == 1.0 and not cfg.gps.configure_receiver
    r = run_daemon(Daemon(cfg))
    with RemoteClient("127.0.0.1", r.port) as c:
        st = wait_for(
            lambda: (
                (s := c.request("status")["gps_receiver"]).get("slow") and s.get("line_full") and s
            ),
            20,
            "slow fixes and a full line",
        )
    assert r.stop() == 0
    assert st["line"]["baud"] == 9600 and st["line"]["load"] >= 0.9, st
    assert "under sim.gps_rate_hz = 4 Hz" in st["slow"] and "under gps.rate_hz" not in st["slow"]
    assert "lower sim.gps_rate_hz" in st["slow"]
    assert "the line may be the cause: it is full (" in st["slow"]
    assert "raise the baud rate (sim.gps_baud)" in st["line_full"]
    warnings = [m.getMessage() for m in caplog.records if m.levelno == logging.WARNING]
    assert len([w for w in warnings if "under sim.gps_rate_hz = 4 Hz" in w]) == 1, warnings
    assert not [w for w in warnings if "under gps.rate_hz" in w], warnings
    assert len([w for w in warnings if w.startswith("GPS: the line is full")]) == 1, warnings


# -- 6: a replay's cycle on the gpsd port ---------------------------------------------------


def test_a_replayed_4_hz_log_says_cycle_0_25_on_the_gpsd_port(
    tmp_path: Path, run_daemon: Any
) -> None:
    t = datetime(2026, 6, 1, 12, 0, tzinfo=UTC)
    log = tmp_path / "gps.nmea"
    log.write_bytes(b"".join(_epoch(t + timedelta(seconds=k / 4), False) for k in range(240)))
    cfg = hil_config(tmp_path)
    cfg = dataclasses.replace(
        cfg,
        gps=GpsConfig(url=f"replay://{log}", rate_hz=4.0, stale_s=2.0),
        safety=dataclasses.replace(cfg.safety, fix_stale_s=0.75),
    )
    r = run_daemon(Daemon(cfg))
    gpsd = r.daemon.gpsd
    assert gpsd is not None
    wait_for(lambda: r.daemon.first_fix, 10, "a replayed fix")
    assert gpsd.device_path == str(log) and gpsd.cycle_s == 0.25  # was 1.0 (the URL's rate)
    assert r.stop() == 0


# -- review of 60e902d: a line its baud does not pace; the slow text's cause; the setup's keys


class BurstPty(LinePty):
    """A native-USB receiver's stand-in (CDC-ACM, /dev/ttyACM*: no baud paces it): a pty whose
    far end writes a whole epoch (RMC + GGA and the rest, ``epoch_b`` bytes) at once,
    ``rate_hz`` times a second: ``BurstPty(rate_hz, epoch_b)``."""

    def _run(self, rate_hz: float, epoch_b: int) -> None:
        t = datetime(2026, 6, 1, 12, 0, tzinfo=UTC)
        gsv = _s("GPGSV,4,1,16,01,45,123,42,02,45,123,42,03,45,123,42,04,45,123,42")
        t0 = time.monotonic()
        for k in range(10_000):
            out = _epoch(t + timedelta(seconds=k / rate_hz))
            out += gsv * max(0, (epoch_b - len(out)) // len(gsv))
            if self.stop.wait(max(0.0, t0 + k / rate_hz - time.monotonic())):
                return
            os.write(self.master, out)


def test_a_line_faster_than_its_baud_is_not_paced_and_never_full(caplog: Any) -> None:
    # the review's repro_acm: a u-blox on native USB at 5 Hz x ~560 B, url baud=9600 (2.9 x
    # what 9600 baud carries): it said "the line is full (2905 of the 960 bytes/s ...)"
    caplog.set_level(logging.INFO)
    pty = BurstPty(5.0, 560)
    try:
        reader = GpsReader(
            lambda: serial.Serial(pty.path, 9600, timeout=0), stale_s=5.0, expected_rate_hz=5.0
        )
        full_seen: list[str] = []
        end = time.monotonic() + 9.0
        while time.monotonic() < end:
            reader.poll(0.05)
            if reader.line_load.full is not None:
                full_seen.append(reader.line_load.full)
        st = reader.fix_rate.status()
        reader.close()
    finally:
        pty.close()
    assert not full_seen, full_seen[0]
    assert st["line"]["paced"] is False and "load" not in st["line"], st
    assert 2000 <= st["line"]["bytes_per_s"] <= 3500, st
    assert "line_full" not in st and "slow" not in st, st
    assert st["measured_rate_hz"] == pytest.approx(5.0, abs=0.6)
    msgs = [r.getMessage() for r in caplog.records if r.name == "drivers.gps_io"]
    assert not [m for m in msgs if "line is full" in m], msgs
    told = [m for m in msgs if "not paced by its baud rate" in m]
    assert len(told) == 1 and "more than 9600 baud can (960)" in told[0], msgs


def test_a_ttyacm_port_is_known_not_paced_at_the_open(tmp_path: Path, caplog: Any) -> None:
    link = tmp_path / "usb-u-blox_AG_-_www.u-blox.com_u-blox_5_-_GPS_Receiver-if00"
    link.symlink_to(tmp_path / "ttyACM0")  # a /dev/serial/by-id link to it
    assert native_usb_path(str(link)) and native_usb_path("/dev/ttyACM3")
    assert not native_usb_path("/dev/ttyAMA0") and not native_usb_path("/dev/ttyUSB0")
    caplog.set_level(logging.INFO)
    load = LineLoad()
    load.restart(9600, 0.0, paced=False)  # what the reader does for such a port
    for k in range(1, 100):
        load.add(300, k * 0.1)
        load.tick(k * 0.1)
    assert load.full is None and load.status()["line"] == {
        "baud": 9600,
        "bytes_per_s": 3000,
        "paced": False,
    }
    msgs = [r.getMessage() for r in caplog.records]
    assert len([m for m in msgs if "a native-USB one (CDC-ACM" in m]) == 1, msgs


def test_slow_fixes_on_a_line_not_full_blame_the_receiver_and_add_the_short_line(
    line_pty: Any, caplog: Any
) -> None:
    # the review's repro_cause: the receiver at 1 Hz (~280 B an epoch: 58 % of 4800 baud),
    # gps.rate_hz = 4, not configured: "the line is the cause" was said of a line not full
    caplog.set_level(logging.WARNING)
    pty = line_pty(278.0, True)
    reader = GpsReader(
        lambda: serial.Serial(pty.path, 4800, timeout=0), stale_s=5.0, expected_rate_hz=4.0
    )
    try:
        end = time.monotonic() + 12.0
        while time.monotonic() < end and reader.fix_rate.slow is None:
            reader.poll(0.05)
        st = reader.fix_rate.status()
    finally:
        reader.close()
    assert "line_full" not in st and 0.4 <= st["line"]["load"] <= 0.75, st
    slow = st["slow"]
    assert "the line is the cause" not in slow and "the line may be" not in slow, slow
    assert "the receiver runs slower than gps.rate_hz: set its rate" in slow, slow
    assert "(the line is not full: " in slow, slow
    assert (
        "the line could not carry gps.rate_hz either: 4800 baud at 4 Hz carries 120 bytes an "
        "epoch" in slow
    ), slow
    warnings = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert len([w for w in warnings if "under gps.rate_hz = 4 Hz" in w]) == 1, warnings


def test_a_configured_receiver_on_a_short_line_names_the_baud_key_and_warns_once(
    line_pty: Any, caplog: Any
) -> None:
    # the review's repro_sim_short: configure_receiver = true, 4 Hz, the scenario's [gnss]
    # baud = 4800: the line_short text named no key, the full line advised fewer sentences
    # (configure_receiver = true sends those that fit) and was a second WARNING for it
    caplog.set_level(logging.INFO)
    pty = line_pty(480.0, True)
    key = "the scenario's [gnss] baud, or sim.gps_baud"
    reader = GpsReader(
        lambda: serial.Serial(pty.path, 4800, timeout=0),
        stale_s=5.0,
        setup=ReceiverSetup(4.0, ack_timeout_s=30.0),  # no answer from this pty: not its test
        expected_rate_hz=4.0,
        baud_key=key,
    )
    reader.poll(0.05)
    _read_for(reader, 4.5)
    setup = reader.setup
    assert setup is not None and setup.line_short is not None
    assert setup.line_short.endswith(f"raise the line's baud rate ({key})"), setup.line_short
    st = reader.fix_rate.status()
    full = st["line_full"]
    assert f"raise the baud rate ({key})" in full and "send fewer sentences" not in full, full
    warnings = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert len([w for w in warnings if w.startswith("GPS: 4800 baud at 4 Hz")]) == 1, warnings
    assert not [w for w in warnings if w.startswith("GPS: the line is full")], warnings
    infos = [r.getMessage() for r in caplog.records if r.levelno == logging.INFO]
    assert [m for m in infos if m.startswith("GPS: the line is full")], infos
