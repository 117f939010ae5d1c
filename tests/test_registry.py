"""Device URLs: validation with the valid choices listed, and real backends behind them."""

from __future__ import annotations

import importlib.util
import logging
import os
import socket
import subprocess
import sys
import threading
import tty
from collections.abc import Iterator
from pathlib import Path

import pytest

from drivers.cmps10 import Cmps10
from drivers.motors import LogMotorLink, MotorBoard, SerialMotorLink, serve_board_fd
from drivers.registry import (
    SCHEMES,
    Devices,
    UrlError,
    check_available,
    device_path,
    open_compass,
    open_gps_port,
    open_motors,
    parse_url,
    protocol_handler,
)
from x6wd.core.errors import ConfigError, DeviceUnavailable
from x6wd.core.recorder import ReplayPort

ROOT = Path(__file__).resolve().parent.parent
LEA5H = ROOT / "tests" / "data" / "recorder" / "ublox-lea-5h.log"
HAVE_SIM = importlib.util.find_spec("sim_backend.protocol_sim") is not None


@pytest.mark.parametrize(
    ("url", "kind", "scheme", "target", "options"),
    [
        ("serial:///dev/ttyS0?baud=9600", "gps", "serial", "/dev/ttyS0", {"baud": 9600}),
        ("serial:///dev/ttyAMA0", "gps", "serial", "/dev/ttyAMA0", {"baud": 9600}),
        ("tcp://127.0.0.1:2948?timeout=0.5", "gps", "tcp", "127.0.0.1:2948", {"timeout": 0.5}),
        ("replay://logs/a.nmea?speed=0", "gps", "replay", "logs/a.nmea", {"speed": 0.0}),
        ("replay:///abs/a.nmea?speed=2.5", "gps", "replay", "/abs/a.nmea", {"speed": 2.5}),
        ("i2c://1/0x60", "compass", "i2c", "1/0x60", {"retries": 3}),
        ("i2c://0/97?stale_after=9", "compass", "i2c", "0/0x61", {"stale_after": 9}),
        ("log://", "motors", "log", "", {}),
        ("serial:///dev/ttyUSB0?watchdog_ms=300", "motors", "serial", "/dev/ttyUSB0", {}),
        ("sim://gps?world=default", "gps", "sim", "gps", {"world": "default"}),
    ],
)
def test_parse_valid_urls(
    url: str, kind: str, scheme: str, target: str, options: dict[str, object]
) -> None:
    dev = parse_url(url, kind)
    assert (dev.kind, dev.scheme, dev.target, dev.url) == (kind, scheme, target, url)
    assert options.items() <= dev.options.items()


@pytest.mark.parametrize("kind", list(SCHEMES))
def test_unknown_scheme_lists_the_valid_ones(kind: str) -> None:
    with pytest.raises(ConfigError) as info:
        parse_url("usb://whatever", kind)
    msg = str(info.value)
    assert "unknown scheme 'usb'" in msg
    for scheme in SCHEMES[kind]:
        assert f"{scheme}://" in msg


def test_unknown_option_lists_the_valid_ones() -> None:
    with pytest.raises(ConfigError, match=r"unknown option 'baudrate'.*valid: baud, timeout"):
        parse_url("serial:///dev/ttyS0?baudrate=9600", "gps")
    with pytest.raises(ConfigError, match=r"valid: none"):
        parse_url("log://?verbose=1", "motors")


@pytest.mark.parametrize(
    ("url", "kind", "match"),
    [
        ("serial:///dev/ttyS0?baud=9601", "gps", "baud: must be one of"),
        ("serial:///dev/ttyS0?baud=fast", "gps", "baud: expected an integer"),
        ("serial:///dev/ttyS0?baud=9600&baud=4800", "gps", "given twice"),
        ("serial://ttyS0", "gps", "absolute device path"),
        ("replay://a.nmea?speed=-1", "gps", "speed: must be within"),
        ("replay://a.nmea?speed=nan", "gps", "speed: must be within"),
        ("replay://", "gps", "replay://FILE"),
        ("tcp://localhost", "gps", "HOST:PORT"),
        ("tcp://localhost:0", "gps", "HOST:PORT"),
        ("tcp://localhost:99999", "gps", "HOST:PORT"),
        ("i2c://1/0x80", "compass", r"0x60\.\.0x67"),
        ("i2c://1/0x1e", "compass", r"0x60\.\.0x67"),
        ("i2c://one/0x60", "compass", "i2c://BUS/ADDRESS"),
        ("serial:///dev/ttyUSB0?watchdog_ms=5", "motors", "watchdog_ms: must be within"),
        ("/dev/ttyS0", "gps", "valid schemes: serial://"),
        ("serial:///dev/ttyS0", "lidar", "unknown device kind 'lidar'"),
        ("i2c://1/0x60", "gps", "unknown scheme 'i2c'"),
    ],
)
def test_bad_urls_name_the_problem(url: str, kind: str, match: str) -> None:
    with pytest.raises(ConfigError, match=match):
        parse_url(url, kind)


def test_importing_the_registry_loads_no_backend() -> None:
    code = (
        "import sys, drivers.registry\n"
        "heavy = {'serial', 'smbus2', 'drivers.cmps10', 'drivers.motors', 'x6wd.core.recorder'}\n"
        "print(sorted(heavy & set(sys.modules)))"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, check=True
    )
    assert out.stdout.strip() == "[]"


# --- real backends ----------------------------------------------------------------------------


@pytest.fixture
def pty_pair() -> Iterator[tuple[int, str]]:
    master, slave = os.openpty()
    tty.setraw(slave)
    yield master, os.ttyname(slave)
    os.close(master)
    os.close(slave)


def read_exactly(port: object, n: int) -> bytes:
    got = b""
    for _ in range(200):
        got += port.read(n - len(got))  # type: ignore[attr-defined]
        if len(got) >= n:
            break
    return got


@pytest.mark.integration
def test_gps_serial_url_opens_a_real_tty(pty_pair: tuple[int, str]) -> None:
    master, name = pty_pair
    port = open_gps_port(f"serial://{name}?baud=9600&timeout=0.05")
    try:
        assert port.timeout == 0.05
        sentence = b"$GPGGA,083723.00,5155.55442,N,00434.65873,E,1,06,2.51,-4.0,M,46.0,M,,*70\r\n"
        os.write(master, sentence)
        assert read_exactly(port, len(sentence)) == sentence
    finally:
        port.close()


def test_gps_serial_url_to_a_missing_device() -> None:
    with pytest.raises(DeviceUnavailable, match="ttyNOPE"):
        open_gps_port("serial:///dev/ttyNOPE")


@pytest.mark.integration
def test_gps_tcp_url_reads_from_a_real_socket() -> None:
    payload = LEA5H.read_bytes()
    server = socket.create_server(("127.0.0.1", 0))
    host, port_no = server.getsockname()

    done = threading.Event()

    def serve() -> None:
        conn, _ = server.accept()
        with conn:
            # pyserial's socket:// open() discards bytes that arrived before it returned,
            # so send only once the client says it is open.
            conn.recv(1)
            conn.sendall(payload)
            done.wait(10)  # keep the connection open until the client has read it all

    thread = threading.Thread(target=serve, daemon=True)
    thread.start()
    port = open_gps_port(f"tcp://{host}:{port_no}?timeout=0.2")
    try:
        port.write(b"!")
        assert read_exactly(port, len(payload)) == payload
    finally:
        done.set()
        port.close()
        thread.join(5)
        server.close()


def test_gps_tcp_url_refused() -> None:
    sock = socket.create_server(("127.0.0.1", 0))
    port_no = sock.getsockname()[1]
    sock.close()  # nothing listens there now
    with pytest.raises(DeviceUnavailable, match=str(port_no)):
        open_gps_port(f"tcp://127.0.0.1:{port_no}")


def test_gps_replay_url(tmp_path: Path) -> None:
    port = open_gps_port(f"replay://{LEA5H}?speed=0")
    assert isinstance(port, ReplayPort)
    assert read_exactly(port, 1_000_000) == LEA5H.read_bytes()
    with pytest.raises(DeviceUnavailable, match="missing"):
        open_gps_port(f"replay://{tmp_path}/missing.nmea")


def test_compass_on_a_missing_i2c_bus() -> None:
    with pytest.raises(DeviceUnavailable, match="I2C bus 97"):
        open_compass("i2c://97/0x60")


def test_log_motors_url() -> None:
    link = open_motors("log://")
    assert isinstance(link, LogMotorLink)
    assert link.drive(10, 20)
    link.close()


def test_log_motors_log_a_change_not_each_repeat(caplog: pytest.LogCaptureFixture) -> None:
    # the controller repeats its command at 20 Hz: a log:// robot logged 15 INFO lines a second
    link = LogMotorLink(logger=logging.getLogger("x6wd.test.logmotors"))
    with caplog.at_level(logging.INFO, logger="x6wd.test.logmotors"):
        for _ in range(20):
            link.drive(0, 0, "idle")
        link.drive(30, 30, "straight")
        link.drive(30, 30, "straight")
        link.stop("operator")
    lines = [r.getMessage() for r in caplog.records if r.levelno >= logging.INFO]
    assert lines == ["motors L+0 R+0 idle", "motors L+30 R+30 straight", "motors L+0 R+0 operator"]
    assert len(link.commands) == 23  # every command is still kept


@pytest.mark.integration
def test_serial_motors_url_drives_a_board_on_a_pty(pty_pair: tuple[int, str]) -> None:
    master, name = pty_pair
    board, stop = MotorBoard(), threading.Event()
    thread = threading.Thread(target=serve_board_fd, args=(master, board, stop), daemon=True)
    thread.start()
    try:
        link = open_motors(f"serial://{name}?baud=115200&watchdog_ms=750&ack_timeout=0.5")
        assert isinstance(link, SerialMotorLink)
        assert link.healthy and board.watchdog_ms == 750
        assert link.drive(-25, 25)
        assert (board.left_pct, board.right_pct) == (-25, 25)
        link.close()
        assert (board.left_pct, board.right_pct) == (0, 0)
    finally:
        stop.set()
        thread.join(5)


@pytest.mark.parametrize(
    ("opener", "kind"), [(open_gps_port, "gps"), (open_compass, "compass"), (open_motors, "motors")]
)
def test_sim_urls_without_the_simulator(
    monkeypatch: pytest.MonkeyPatch, opener: object, kind: str
) -> None:
    # a build without the sim:// handler: the import itself fails, as it would for real
    monkeypatch.setitem(sys.modules, "sim_backend.protocol_sim", None)
    with pytest.raises(DeviceUnavailable, match=r"sim_backend\.protocol_sim"):
        opener(f"sim://{kind}", Devices())  # type: ignore[operator]
    with pytest.raises(UrlError, match=r"sim_backend\.protocol_sim"):
        check_available("sim://", kind)


@pytest.mark.skipif(not HAVE_SIM, reason="sim_backend.protocol_sim not in this build")
def test_sim_handler_is_imported_by_name_at_run_time() -> None:
    # the simulator is a higher layer: a plug-in found by name, never imported statically
    handler = protocol_handler("sim")
    assert handler.__name__ == "sim_backend.protocol_sim"
    registry_src = (ROOT / "drivers" / "registry.py").read_text()
    assert "import sim_backend" not in registry_src and "from sim_backend" not in registry_src
    with pytest.raises(DeviceUnavailable, match="protocol_bogus"):
        protocol_handler("bogus")


@pytest.mark.integration
@pytest.mark.skipif(not HAVE_SIM, reason="sim_backend.protocol_sim not in this build")
def test_sim_devices_of_one_configuration_share_one_world() -> None:
    from sim_backend.hil import HilWorld
    from x6wd.core.config import Config, SimConfig

    devices = Devices(Config(sim=SimConfig(gps_rate_hz=4.0, gps_baud=115200)))
    try:
        compass = open_compass("sim://", devices)
        assert isinstance(compass, Cmps10)
        att = compass.read(0.0)
        assert att.valid and 0.0 <= att.bearing_deg < 360.0
        world = devices.backend("sim")
        assert isinstance(world, HilWorld) and world.running
        assert world.receiver.baud == 115200  # built from [sim]
        port = open_gps_port("sim:///", devices)
        assert port.baudrate == 115200 and port.port == world.uart.port_name
        port.close()
        link = open_motors("sim://", devices)
        assert isinstance(link, SerialMotorLink) and devices.backend("sim") is world
        link.close()
    finally:
        devices.close()
    assert not world.running  # the device set built it, the device set closed it
    with pytest.raises(DeviceUnavailable, match="closed"):
        open_compass("sim://", devices)


@pytest.mark.skipif(not HAVE_SIM, reason="sim_backend.protocol_sim not in this build")
def test_sim_devices_need_a_device_set_and_a_plain_url() -> None:
    with pytest.raises(UrlError, match=r"registry\.Devices"):
        open_compass("sim://")
    with pytest.raises(UrlError, match="takes no path or options"):
        open_gps_port("sim://?seed=3", Devices())
    with pytest.raises(UrlError, match="unexpected fragment"):
        open_gps_port("sim://#x", Devices())
    given = object()  # a caller's own backend is used as it is, and not closed
    devices = Devices(backends={"sim": given})
    assert devices.backend("sim") is given
    devices.close()
    assert devices.backend("sim") is given


@pytest.mark.skipif(not HAVE_SIM, reason="sim_backend.protocol_sim not in this build")
def test_device_set_checks_the_sim_settings_without_building_a_world(tmp_path: Path) -> None:
    from x6wd.core.config import Config, SimConfig

    devices = Devices(Config(sim=SimConfig(scenario=str(tmp_path / "missing.toml"))))
    assert devices.check("log://", "motors").scheme == "log"  # no [sim] needed
    with pytest.raises(ConfigError, match=r"sim\.scenario"):
        devices.check("sim://", "gps")
    assert Devices(Config()).check("sim://", "compass").scheme == "sim"


def test_gpsd_device_path_from_url() -> None:
    assert device_path("serial:///dev/ttyAMA0?baud=4800") == ("/dev/ttyAMA0", 4800)
    assert device_path("serial:///dev/ttyS0") == ("/dev/ttyS0", 9600)
    assert device_path("sim://") == ("sim://", 9600)
    assert device_path("tcp://gps.local:2948") == ("tcp://gps.local:2948", 9600)
    assert device_path("not a url") == ("not a url", 9600)


# Files that take other addresses apart, never device URLs: the console (a page's Origin,
# a tile URL), the configuration (console.tile_url's check), the sweep executor (a Dask
# scheduler's tcp:// address).
WEB_ADDRESSES = {"x6wd/app/console/server.py", "x6wd/core/config.py", "sim_backend/executor.py"}


def test_only_the_registry_takes_device_urls_apart() -> None:
    offenders = []
    for pkg in ("x6wd", "drivers", "sim_backend"):
        for path in (ROOT / pkg).rglob("*.py"):
            if path.name == "registry.py" or str(path.relative_to(ROOT)) in WEB_ADDRESSES:
                continue
            text = path.read_text()
            if any(w in text for w in ("urlsplit", "urlparse", "parse_qsl", 'startswith("sim://')):
                offenders.append(str(path.relative_to(ROOT)))
    assert offenders == []


def test_url_errors_carry_the_reason_alone() -> None:
    with pytest.raises(UrlError) as info:
        parse_url("bogus://x", "gps")
    err = info.value
    assert (err.kind, err.url) == ("gps", "bogus://x")
    assert (
        err.reason == "unknown scheme 'bogus' (valid for gps: serial://, tcp://, replay://, sim://)"
    )
    assert str(err) == f"gps URL 'bogus://x': {err.reason}"
    with pytest.raises(UrlError) as info:
        parse_url("serial:///dev/ttyS0?baud=7", "motors")
    assert info.value.reason.startswith("option baud: must be one of")


def test_check_available_names_the_problem(tmp_path: Path) -> None:
    assert check_available("log://", "motors").scheme == "log"
    assert check_available(f"replay://{LEA5H}", "gps").target == str(LEA5H)
    assert check_available("tcp://192.0.2.1:9", "gps").scheme == "tcp"  # not probed
    with pytest.raises(UrlError, match=r"^.*: /dev/null is not a serial port"):
        check_available("serial:///dev/null", "gps")  # a character device, not a terminal
    with pytest.raises(UrlError) as info:
        check_available("serial:///dev/ttyNOPE", "motors")
    assert info.value.reason == "/dev/ttyNOPE does not exist"
    assert info.value.kind == "motors" and info.value.url == "serial:///dev/ttyNOPE"
    with pytest.raises(UrlError, match="is not a regular file"):
        check_available(f"replay://{tmp_path}", "gps")
    with pytest.raises(UrlError, match="sim:// takes no path"):
        check_available("sim://x/y", "compass")
    with pytest.raises(UrlError, match="/dev/i2c-97 does not exist"):
        check_available("i2c://97/0x60", "compass")


@pytest.mark.skipif(os.geteuid() == 0, reason="root may read and write any device")
def test_check_available_refuses_a_device_this_user_may_not_use(tmp_path: Path) -> None:
    with pytest.raises(UrlError, match="may not read and write"):
        check_available("serial:///dev/mem", "gps")


@pytest.mark.integration
def test_the_configured_watchdog_is_the_boards_unless_the_url_sets_one(
    pty_pair: tuple[int, str],
) -> None:
    master, name = pty_pair
    board, stop = MotorBoard(), threading.Event()
    thread = threading.Thread(target=serve_board_fd, args=(master, board, stop), daemon=True)
    thread.start()
    try:
        for url, config_ms, board_ms in (
            (f"serial://{name}", 2000, 2000),  # [motors] watchdog_ms reaches the board
            (f"serial://{name}?watchdog_ms=750", 500, 750),  # the URL's, over the default
            (f"serial://{name}?watchdog_ms=750", 750, 750),
        ):
            link = open_motors(url, watchdog_ms=config_ms)
            assert isinstance(link, SerialMotorLink) and board.watchdog_ms == board_ms
            link.close()
        with pytest.raises(ConfigError, match=r"^motors.watchdog_ms: 100 ms, but motors.url"):
            open_motors(f"serial://{name}?watchdog_ms=750", watchdog_ms=100)
    finally:
        stop.set()
        thread.join(5)
