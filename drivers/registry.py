"""Device URLs -> backends. Each backend's module is imported only when its URL is used.

=========  =======================================  ==========================================
kind       URL                                      backend
=========  =======================================  ==========================================
gps        ``serial:///dev/ttyS0?baud=9600``        pyserial ``Serial`` (a UART or a pty)
gps        ``tcp://host:port``                      pyserial ``socket://`` (ser2net, gpsd raw)
gps        ``replay:///path/log.nmea?speed=1``      :class:`x6wd.core.recorder.ReplayPort`
compass    ``i2c://1/0x60``                         ``smbus2.SMBus(1)`` + :class:`Cmps10`
motors     ``serial:///dev/ttyUSB0?baud=115200``    :class:`SerialMotorLink`
motors     ``tcp://host:port``                      :class:`SerialMotorLink` over a socket
motors     ``log://``                               :class:`LogMotorLink`
any        ``sim://``                               the simulator's world, through the
                                                    ``sim_backend.protocol_sim`` handler
=========  =======================================  ==========================================

``replay://`` takes a relative path as ``replay://logs/a.nmea`` and an absolute one as
``replay:///abs/a.nmea``. Unknown schemes and options raise :class:`UrlError` (a
:class:`ConfigError`) listing the valid ones; a device that cannot be opened raises
:class:`DeviceUnavailable`. :func:`check_available` is the daemon's start-up check: the URL is
valid and the local device it names (serial path, I2C bus, replay file) exists, without
opening anything (a missing device node: :class:`NodeMissing`). This module is the only one
that takes device URLs apart (:func:`device_path` tells the gpsd port what device a GPS URL
is).

Plug-in schemes (``sim://``), like pyserial's ``protocol_<scheme>`` modules: the module
``<package>.protocol_<scheme>`` of the first of :data:`PROTOCOL_PACKAGES` that has one is
imported by name when such a URL is used (the simulator is a higher layer than the drivers:
a plug-in, not a dependency). It provides ``url_problem(dev)``, ``check_config(config)``
(what it returns, if not None, is given to ``open_backend`` instead of the configuration:
the world then runs the settings that were checked, each input read once),
``open_backend(config)`` (the object its devices share, e.g. the simulated world, built from
the configuration) and ``open_gps/open_compass/open_motors(dev, backend)``. The devices of a
plug-in scheme are opened through a :class:`Devices` (one configuration's devices), which
builds the backend once and closes it.
"""

from __future__ import annotations

import contextlib
import errno
import importlib
import math
import os
import stat
import threading
from collections.abc import Mapping
from dataclasses import dataclass, field
from types import ModuleType
from typing import TYPE_CHECKING, Any, Protocol
from urllib.parse import parse_qsl, unquote, urlsplit

from x6wd.core.errors import ConfigError, DeviceUnavailable

if TYPE_CHECKING:
    from drivers.cmps10 import Cmps10
    from drivers.motors import MotorLink

KINDS = ("gps", "compass", "motors")
PLUGIN_SCHEMES = ("sim",)  # opened by a protocol_<scheme> handler module, not here
PROTOCOL_PACKAGES = ("sim_backend",)  # where protocol_<scheme> handler modules are looked for
I2C_DEV = "/dev/i2c-{bus}"  # the Linux i2c-dev node that smbus2.SMBus(bus) opens
STANDARD_BAUDS = (1200, 2400, 4800, 9600, 19200, 38400, 57600, 115200, 230400, 460800, 921600)


class PortLike(Protocol):
    """pyserial-compatible byte port: ``read(n)`` honouring ``timeout``, ``in_waiting``,
    ``write``, ``close``."""

    timeout: float | None

    def read(self, size: int = 1) -> bytes: ...

    @property
    def in_waiting(self) -> int: ...

    def write(self, data: bytes) -> int | None: ...

    def close(self) -> None: ...


class UrlError(ConfigError):
    """A device URL that cannot work. ``str()`` is ``"<kind> URL '<url>': <reason>"``;
    ``reason`` alone lets a caller name its own config key instead of the kind."""

    def __init__(self, kind: str, url: str, reason: str) -> None:
        super().__init__(f"{kind} URL {url!r}: {reason}")
        self.kind = kind
        self.url = url
        self.reason = reason


class NodeMissing(UrlError):
    """The device node a URL names (a serial path, ``/dev/i2c-N``) does not exist. Unlike the
    other problems this one can end by itself, with no change to the configuration: a USB
    adapter udev has not enumerated yet at boot, a native-USB board re-enumerating after a
    reset (1-3 s). ``path`` is the node."""

    def __init__(self, kind: str, url: str, path: str) -> None:
        super().__init__(kind, url, f"{path} does not exist")
        self.path = path


class NodeNotReady(UrlError):
    """The device node a URL names is a character device this user may not read and write.
    This too can end by itself: udev creates a node (root's, mode 600 or so) and gives it its
    group (dialout, i2c) a moment later, so a node that was just enumerated, at boot or when a
    native-USB board re-enumerates after a reset, may be seen between the two. ``path`` is the
    node. (A replay file that may not be read stays a plain :class:`UrlError`.)"""

    def __init__(self, kind: str, url: str, path: str, reason: str) -> None:
        super().__init__(kind, url, reason)
        self.path = path


def _float_opt(lo: float, hi: float) -> Any:
    def conv(name: str, text: str) -> float:
        try:
            v = float(text)
        except ValueError:
            raise ConfigError(f"option {name}: expected a number, got {text!r}") from None
        if not (math.isfinite(v) and lo <= v <= hi):
            raise ConfigError(f"option {name}: must be within {lo:g}..{hi:g}, got {text!r}")
        return v

    return conv


def _int_opt(lo: int, hi: int, choices: tuple[int, ...] = ()) -> Any:
    def conv(name: str, text: str) -> int:
        try:
            v = int(text, 0)
        except ValueError:
            raise ConfigError(f"option {name}: expected an integer, got {text!r}") from None
        if choices and v not in choices:
            raise ConfigError(
                f"option {name}: must be one of {', '.join(map(str, choices))}, got {text!r}"
            )
        if not lo <= v <= hi:
            raise ConfigError(f"option {name}: must be within {lo}..{hi}, got {text!r}")
        return v

    return conv


_BAUD = _int_opt(50, 4_000_000, STANDARD_BAUDS)
_TIMEOUT = _float_opt(0.0, 60.0)

# kind -> scheme -> option -> converter
SCHEMES: dict[str, dict[str, dict[str, Any]]] = {
    "gps": {
        "serial": {"baud": _BAUD, "timeout": _TIMEOUT},
        "tcp": {"timeout": _TIMEOUT},
        "replay": {
            "speed": _float_opt(0.0, 1e6),
            "rate": _float_opt(0.01, 100.0),
            "timeout": _TIMEOUT,
        },
        "sim": {},
    },
    "compass": {
        "i2c": {"retries": _int_opt(0, 100), "stale_after": _int_opt(1, 10_000)},
        "sim": {},
    },
    "motors": {
        "serial": {
            "baud": _BAUD,
            "watchdog_ms": _int_opt(50, 60_000),
            "ack_timeout": _float_opt(0.001, 10.0),
            "retries": _int_opt(0, 100),
        },
        "tcp": {
            "watchdog_ms": _int_opt(50, 60_000),
            "ack_timeout": _float_opt(0.001, 10.0),
            "retries": _int_opt(0, 100),
        },
        "log": {},
        "sim": {},
    },
}

DEFAULT_MOTOR_WATCHDOG_MS = 500
"""The board's watchdog period (ms) when neither [motors] watchdog_ms nor the URL sets one."""

DEFAULTS: dict[str, dict[str, dict[str, Any]]] = {
    "gps": {
        "serial": {"baud": 9600, "timeout": 0.1},
        "tcp": {"timeout": 0.1},
        "replay": {"speed": 1.0, "rate": 1.0, "timeout": 0.1},
    },
    "compass": {"i2c": {"retries": 3, "stale_after": 5}},
    "motors": {
        "serial": {
            "baud": 115200,
            "watchdog_ms": DEFAULT_MOTOR_WATCHDOG_MS,
            "ack_timeout": 0.1,
            "retries": 1,
        },
        "tcp": {"watchdog_ms": DEFAULT_MOTOR_WATCHDOG_MS, "ack_timeout": 0.1, "retries": 1},
    },
}


@dataclass(frozen=True)
class DeviceUrl:
    """A validated device URL.

    ``target`` is the device path (serial, replay), ``host:port`` (tcp), ``bus/address``
    (i2c), or host and path (a plug-in scheme). ``options`` holds the converted query
    options with their defaults filled in (a plug-in scheme: the raw strings, for its
    handler to judge).
    """

    url: str
    kind: str
    scheme: str
    target: str
    options: dict[str, Any] = field(default_factory=dict)


def parse_url(url: str, kind: str) -> DeviceUrl:
    """Validate ``url`` for a device ``kind`` ("gps", "compass" or "motors").

    Raises :class:`ConfigError` for an unknown kind, scheme or option (listing the valid
    ones), a bad option value or a malformed target.
    """
    if kind not in SCHEMES:
        raise ConfigError(f"unknown device kind {kind!r} (valid: {', '.join(KINDS)})")
    if not isinstance(url, str) or "://" not in url:
        raise UrlError(
            kind,
            url,
            f"expected scheme://..., valid schemes: {', '.join(s + '://' for s in SCHEMES[kind])}",
        )
    if "\x00" in unquote(url):  # raw or as %00: no device path or host can hold one
        raise UrlError(kind, url, "contains a NUL character")
    try:
        parts = urlsplit(url)
    except ValueError as exc:  # e.g. an unclosed [IPv6 bracket
        raise UrlError(kind, url, f"malformed URL: {exc}") from None
    scheme = parts.scheme.lower()
    schemes = SCHEMES[kind]
    if scheme not in schemes:
        raise UrlError(
            kind,
            url,
            f"unknown scheme {scheme!r} (valid for {kind}: "
            f"{', '.join(s + '://' for s in schemes)})",
        )
    if parts.fragment:
        raise UrlError(kind, url, f"unexpected fragment #{parts.fragment}")
    if scheme in PLUGIN_SCHEMES:  # its handler judges the target and the options
        raw: dict[str, str] = {}
        for name, value in parse_qsl(parts.query, keep_blank_values=True):
            if name in raw:
                raise UrlError(kind, url, f"option {name!r} given twice")
            raw[name] = value
        return DeviceUrl(url, kind, scheme, parts.netloc + unquote(parts.path), raw)
    valid = schemes[scheme]
    options: dict[str, Any] = dict(DEFAULTS.get(kind, {}).get(scheme, {}))
    try:
        pairs = parse_qsl(parts.query, keep_blank_values=True, strict_parsing=bool(parts.query))
    except ValueError:
        raise UrlError(kind, url, f"malformed query {parts.query!r}") from None
    seen: set[str] = set()
    for name, value in pairs:
        if name not in valid:
            listing = ", ".join(valid) if valid else "none"
            raise UrlError(kind, url, f"unknown option {name!r} for {scheme}:// (valid: {listing})")
        if name in seen:
            raise UrlError(kind, url, f"option {name!r} given twice")
        seen.add(name)
        try:
            options[name] = valid[name](name, value)
        except ConfigError as exc:
            raise UrlError(kind, url, str(exc)) from None
    target = _target(url, kind, scheme, parts.netloc, unquote(parts.path))
    return DeviceUrl(url, kind, scheme, target, options)


def _target(url: str, kind: str, scheme: str, netloc: str, path: str) -> str:
    def bad(reason: str) -> UrlError:
        return UrlError(kind, url, reason)

    if scheme == "serial":
        if netloc or not path.startswith("/") or path == "/":
            raise bad("expected serial:///dev/NAME (an absolute device path)")
        return path
    if scheme == "replay":
        target = netloc + path
        if not target:
            raise bad("expected replay://FILE (relative) or replay:///FILE")
        return target
    if scheme == "tcp":
        host, sep, port = netloc.rpartition(":")
        digits = port.isascii() and port.isdigit()  # not "²", which isdigit() accepts
        if not sep or not host or not digits or not 0 < int(port) < 65536 or path:
            raise bad("expected tcp://HOST:PORT with PORT 1..65535")
        return netloc
    if scheme == "i2c":
        bus, addr = netloc, path.strip("/")
        try:
            bus_n, addr_n = int(bus, 10), int(addr, 0)
        except ValueError:
            raise bad("expected i2c://BUS/ADDRESS, e.g. i2c://1/0x60") from None
        if bus_n < 0 or not 0x60 <= addr_n <= 0x67:
            raise bad("bus must be >= 0 and the address a CMPS10 7-bit address 0x60..0x67")
        return f"{bus_n}/{addr_n:#04x}"
    if scheme == "log":
        if netloc or path not in ("", "/"):
            raise bad("log:// takes no target")
        return ""
    raise AssertionError(scheme)  # pragma: no cover


def check_available(url: str, kind: str) -> DeviceUrl:
    """Start-up check of a device URL for ``kind``, opening nothing: the URL is valid
    (:func:`parse_url`; ``sim://`` also by the simulator's own rules) and the local device it
    names is there: a serial path is an existing character device this user may read and
    write, and not a non-terminal (:func:`_check_serial`; whether another process holds it
    is not checked: that is for the opening to report and retry);
    ``i2c://N/..`` has its ``/dev/i2c-N`` node, a replay file exists and is readable.
    ``tcp://`` and ``log://`` have nothing local to check (a remote peer may come later).

    Raises :class:`UrlError`: the daemon stops with a configuration error rather than run
    "disconnected" with a device that cannot appear by retrying. A device node that does not
    exist is :class:`NodeMissing`, a character device this user may not read and write
    :class:`NodeNotReady` (both UrlErrors), which the daemon started by systemd waits for a
    while first.
    """
    dev = parse_url(url, kind)
    if dev.scheme in PLUGIN_SCHEMES:
        try:
            handler = protocol_handler(dev.scheme)
        except DeviceUnavailable as exc:
            raise UrlError(kind, url, str(exc)) from None
        problem = handler.url_problem(dev)
        if problem:
            raise UrlError(kind, url, problem)
    elif dev.scheme == "serial":
        _check_node(dev, dev.target, char=True, hint="is the user in group dialout?")
        _check_serial(dev, dev.target)
    elif dev.scheme == "i2c":
        node = I2C_DEV.format(bus=int(dev.target.split("/")[0]))
        _check_node(dev, node, char=True, hint="is I2C enabled and the user in group i2c?")
    elif dev.scheme == "replay":
        _check_node(dev, dev.target, char=False, hint="")
    return dev


def _check_node(dev: DeviceUrl, path: str, *, char: bool, hint: str) -> None:
    """``path`` exists as a character device (``char``) or a regular file, and is accessible
    (read-write for a device, read for a file); else :class:`UrlError` saying which
    (:class:`NodeMissing`, :class:`NodeNotReady`: a device node missing, not accessible)."""
    try:
        st = os.stat(path)
    except FileNotFoundError:  # (also a dangling link: /dev/serial/by-id/ of a gone device)
        if char:  # a device node may yet appear; a replay file will not
            raise NodeMissing(dev.kind, dev.url, path) from None
        raise UrlError(dev.kind, dev.url, f"{path} does not exist") from None
    except (OSError, ValueError) as exc:  # ValueError: a path the OS cannot take
        raise UrlError(
            dev.kind, dev.url, f"{path}: {getattr(exc, 'strerror', None) or exc}"
        ) from None
    if char and not stat.S_ISCHR(st.st_mode):
        raise UrlError(dev.kind, dev.url, f"{path} is not a character device")
    if not char and not stat.S_ISREG(st.st_mode):
        raise UrlError(dev.kind, dev.url, f"{path} is not a regular file")
    need = os.R_OK | os.W_OK if char else os.R_OK
    if not os.access(path, need):
        rights = "read and write" if char else "read"
        extra = f" ({hint})" if hint else ""
        reason = f"{path}: this user may not {rights} it{extra}"
        if char:  # udev may not have given the node its group yet
            raise NodeNotReady(dev.kind, dev.url, path, reason)
        raise UrlError(dev.kind, dev.url, reason)


SYSFS_CHAR = "/sys/dev/char/{major}:{minor}/subsystem"
"""The kernel's class of a character device (a symlink ending in ``tty``, ``mem`` ...)."""


def _check_serial(dev: DeviceUrl, path: str) -> None:
    """``path`` (an accessible character device) is a serial port, as far as can be told
    without opening it: not e.g. ``/dev/null``, which opens but refuses every serial setting
    ("Inappropriate ioctl for device") for ever. The kernel's class of the device number
    (:data:`SYSFS_CHAR`) says it: every terminal (UART, USB adapter, ACM board) is ``tty``.
    A device sysfs does not list (a pseudo-terminal's ``/dev/pts/N``, or no ``/sys``) is
    left to the device's own opening, which reports and retries a failure.

    Nothing is opened: opening a serial port raises DTR and the close (HUPCL) drops it,
    which resets an Arduino-class motor board. Whether the port is in use is not checked
    either: a port held for a moment at boot (ModemManager probing a ttyACM, gpsd
    hot-plugging) is a runtime condition the device's opening reports and retries (the
    GPS), or a start-up failure systemd restarts (the motors), not a configuration error."""
    try:
        rdev = os.stat(path).st_rdev
        kind = os.path.basename(
            os.readlink(SYSFS_CHAR.format(major=os.major(rdev), minor=os.minor(rdev)))
        )
    except (OSError, ValueError):
        return
    if kind != "tty":
        raise UrlError(
            dev.kind,
            dev.url,
            f"{path} is not a serial port (not a terminal: the kernel's class of it is {kind!r})",
        )


def _in_use(path: str, how: str) -> str:
    return f"{path} is in use: another process holds it ({how}; another x6wd, gpsd?)"


def device_path(url: str) -> tuple[str, int]:
    """What a GPS URL is for gpsd clients (the gpsd port's DEVICES): the device path and baud
    rate (bit/s) of a ``serial://`` URL (``serial:///dev/ttyS0?baud=4800`` ->
    ``("/dev/ttyS0", 4800)``); any other URL as given, at 9600."""
    try:
        dev = parse_url(url, "gps")
    except ConfigError:
        return url, 9600
    if dev.scheme == "serial":
        return dev.target, int(dev.options["baud"])
    return url, 9600


def protocol_handler(scheme: str) -> ModuleType:
    """The handler module of a plug-in scheme: ``<package>.protocol_<scheme>`` of the first of
    :data:`PROTOCOL_PACKAGES` that has one, imported by name at run time.

    Raises :class:`DeviceUnavailable` when no package has it (a build without the simulator).
    """
    for package in PROTOCOL_PACKAGES:
        name = f"{package}.protocol_{scheme}"
        try:
            return importlib.import_module(name)
        except ModuleNotFoundError as exc:
            if exc.name not in (name, package):
                raise  # the handler is there but something it needs is not: a real error
    where = " or ".join(f"{p}.protocol_{scheme}" for p in PROTOCOL_PACKAGES)
    raise DeviceUnavailable(f"{scheme}:// URLs need {where}, which this build does not have")


class Devices:
    """The devices of one configuration (the daemon's): the plug-in schemes' backends.

    The devices of a plug-in scheme share one backend: the simulated GPS, compass and motors
    live in one world. :meth:`backend` has the scheme's handler build it from ``config`` (the
    whole :class:`x6wd.core.config.Config`; None: the defaults) on first use, and builds a new
    one if it stopped running; :meth:`close` closes what was built here. A backend given in
    ``backends`` (scheme -> object) is the caller's: used, never built or closed here.
    """

    def __init__(self, config: Any = None, backends: Mapping[str, Any] | None = None) -> None:
        self.config = config
        self._given = dict(backends or {})
        self._built: dict[str, Any] = {}
        self._checked: dict[str, Any] = {}  # scheme -> what its check_config returned
        self._closed = False
        self._lock = threading.Lock()

    def check(self, url: str, kind: str) -> DeviceUrl:
        """:func:`check_available`, and for a plug-in scheme its part of the configuration
        (once per scheme; :class:`ConfigError` naming the key). Builds nothing."""
        dev = check_available(url, kind)
        scheme = dev.scheme
        if scheme in PLUGIN_SCHEMES and scheme not in self._given and scheme not in self._checked:
            self._checked[scheme] = protocol_handler(scheme).check_config(self.config)
        return dev

    def backend(self, scheme: str) -> Any:
        """The backend the devices of ``scheme`` share (built on first use)."""
        with self._lock:
            if scheme in self._given:
                return self._given[scheme]
            if self._closed:
                raise DeviceUnavailable(f"{scheme}:// devices: the device set is closed")
            backend = self._built.get(scheme)
            if backend is not None and not getattr(backend, "running", True):
                with contextlib.suppress(Exception):
                    backend.close()
                backend = None
            if backend is None:
                # The checked settings when the check returned them: a world built from them
                # reads its inputs once (a scenario's mission.file may be a FIFO).
                checked = self._checked.get(scheme)
                backend = protocol_handler(scheme).open_backend(
                    self.config if checked is None else checked
                )
                self._built[scheme] = backend
            return backend

    def close(self) -> None:
        """Close the backends built here (idempotent); nothing opens afterwards."""
        with self._lock:
            built, self._built = self._built, {}
            self._closed = True
        for backend in built.values():
            with contextlib.suppress(Exception):
                backend.close()


def _plugin(dev: DeviceUrl, devices: Devices | None) -> tuple[ModuleType, Any]:
    """The handler of ``dev``'s plug-in scheme, having judged the URL, and the backend."""
    handler = protocol_handler(dev.scheme)
    problem = handler.url_problem(dev)
    if problem:
        raise UrlError(dev.kind, dev.url, problem)
    if devices is None:
        raise UrlError(
            dev.kind,
            dev.url,
            f"{dev.scheme}:// devices share one backend built from the configuration: "
            "open them through a registry.Devices",
        )
    return handler, devices.backend(dev.scheme)


MOTOR_WRITE_TIMEOUT_S = 1.0
"""The least time (s) a motor command's write may take before the port counts as stalled: a
few bytes go into the driver's buffer at once, so only a line that stopped takes longer
(after the board's own watchdog, 0.5 s by default, has stopped the wheels)."""


def _serial_port(dev: DeviceUrl, timeout_s: float, write_timeout_s: float | None = None) -> Any:
    """Open ``dev``'s serial (or TCP) port with read timeout ``timeout_s`` (s).
    ``write_timeout_s`` (s, None: a write may block for ever): a write that cannot finish in
    time (a stuck USB adapter, a flow-controlled line, a TCP peer that stopped reading)
    raises ``SerialTimeoutException`` instead of holding the writer."""
    import serial  # lazily: pyserial is only needed for real ports

    try:
        if dev.scheme == "tcp":
            return serial.serial_for_url(
                f"socket://{dev.target}", timeout=timeout_s, write_timeout=write_timeout_s
            )
        # exclusive: pyserial takes a non-blocking flock; a port held by another process
        # (another x6wd, gpsd) fails to open instead of sharing, and splitting, its bytes
        return serial.Serial(
            dev.target,
            baudrate=dev.options["baud"],
            timeout=timeout_s,
            write_timeout=write_timeout_s,
            exclusive=True,
        )
    except (serial.SerialException, OSError, ValueError) as exc:
        code = getattr(exc, "errno", None)
        if code in (errno.EAGAIN, errno.EWOULDBLOCK):  # pyserial's flock (another x6wd)
            raise DeviceUnavailable(
                f"cannot open {dev.url}: {_in_use(dev.target, 'locked')}"
            ) from exc
        if code == errno.EBUSY:  # TIOCEXCL (gpsd, ModemManager): refused at the open itself
            why = _in_use(dev.target, "opened exclusively")
            raise DeviceUnavailable(f"cannot open {dev.url}: {why}") from exc
        raise DeviceUnavailable(f"cannot open {dev.url}: {exc}") from exc


def open_gps_port(url: str, devices: Devices | None = None) -> PortLike:
    """Open the GPS byte stream named by ``url`` (serial, tcp, replay, sim; a plug-in
    scheme through ``devices``)."""
    dev = parse_url(url, "gps")
    if dev.scheme in PLUGIN_SCHEMES:
        handler, backend = _plugin(dev, devices)
        port: PortLike = handler.open_gps(dev, backend)
        return port
    if dev.scheme == "replay":
        from x6wd.core.recorder import ReplayPort

        return ReplayPort(
            dev.target,
            dev.options["speed"],
            rate_hz=dev.options["rate"],
            timeout=dev.options["timeout"],
        )
    port = _serial_port(dev, dev.options["timeout"])
    return port


def open_compass(url: str, devices: Devices | None = None) -> Cmps10:
    """Open the CMPS10 named by ``url`` (i2c, sim; a plug-in scheme through ``devices``) and
    check that it answers (the simulated one is not checked on open).

    Raises :class:`DeviceUnavailable` if the bus cannot be opened or no CMPS10 answers.
    """
    dev = parse_url(url, "compass")
    if dev.scheme in PLUGIN_SCHEMES:
        handler, backend = _plugin(dev, devices)
        compass: Cmps10 = handler.open_compass(dev, backend)
        return compass
    from drivers.cmps10 import Cmps10

    bus_s, addr_s = dev.target.split("/")
    try:
        import smbus2

        bus = smbus2.SMBus(int(bus_s))
    except (OSError, ImportError) as exc:
        raise DeviceUnavailable(f"cannot open I2C bus {bus_s} for {url}: {exc}") from exc
    compass = Cmps10(
        bus,
        int(addr_s, 0),
        retries=dev.options["retries"],
        stale_after=dev.options["stale_after"],
    )
    try:
        compass.check_version()
    except DeviceUnavailable:
        bus.close()
        raise
    return compass


def check_motor_watchdog(url: str, watchdog_ms: int) -> None:
    """ConfigError naming both when ``[motors] watchdog_ms`` (ms; its default aside) and the
    motor ``url``'s own ``watchdog_ms`` differ (the daemon checks it before binding a port,
    with the other settings). No error for a URL without that option or a bad URL (that is
    :func:`parse_url`'s to name)."""
    try:
        dev = parse_url(url, "motors")
    except UrlError:
        return
    if "watchdog_ms" not in dev.options or "watchdog_ms" not in dict(
        parse_qsl(urlsplit(url).query)
    ):
        return
    if watchdog_ms not in (DEFAULT_MOTOR_WATCHDOG_MS, dev.options["watchdog_ms"]):
        raise ConfigError(
            f"motors.watchdog_ms: {watchdog_ms} ms, but motors.url says"
            f" watchdog_ms={dev.options['watchdog_ms']}: set one of them"
        )


def open_motors(
    url: str,
    devices: Devices | None = None,
    *,
    watchdog_ms: int | None = None,
    max_counts_per_s: float | None = None,
) -> MotorLink:
    """Open the motor link named by ``url`` (serial, tcp, log, sim; a plug-in scheme through
    ``devices``). ``watchdog_ms`` ([motors] watchdog_ms): the board's watchdog period (ms)
    unless the URL names its own ``watchdog_ms``; the two differing, the default aside, is a
    ConfigError naming both. ``max_counts_per_s``: the encoders' distance bound of a serial
    or TCP link (:func:`drivers.motors.encoder_rate_bound` of the robot's ``[odometry]`` and
    ``[navigation] full_speed_mps``; None: :data:`drivers.motors.ENC_MAX_COUNTS_PER_S`)."""
    dev = parse_url(url, "motors")
    if watchdog_ms is not None and "watchdog_ms" in dev.options:
        check_motor_watchdog(url, watchdog_ms)
        if "watchdog_ms" not in dict(parse_qsl(urlsplit(url).query)):
            dev.options["watchdog_ms"] = int(watchdog_ms)
    if dev.scheme in PLUGIN_SCHEMES:
        handler, backend = _plugin(dev, devices)  # (judges the URL's own options)
        if watchdog_ms is not None:  # the daemon's setting, as for a real board
            dev.options.setdefault("watchdog_ms", str(int(watchdog_ms)))
        link: MotorLink = handler.open_motors(dev, backend)
        return link
    from drivers.motors import ENC_MAX_COUNTS_PER_S, LogMotorLink, SerialMotorLink

    if dev.scheme == "log":
        return LogMotorLink()
    timeout_s = min(dev.options["ack_timeout"], 0.02)
    # A write that cannot finish in MOTOR_WRITE_TIMEOUT_S (or the acknowledgement's time, if
    # longer) is a port fault the link handles (lost, the port closed and reopened with
    # backoff; the board's watchdog stops the motors), never a writer blocked for ever under
    # the control lock. Not the 0.1 s acknowledgement time itself: pyserial times the whole
    # os.write call, so a write the tty took at once but whose thread then waited for the
    # GIL behind a long C call read as a timeout (2 of 10 in a review) and cut the link.
    write_timeout_s = max(dev.options["ack_timeout"], MOTOR_WRITE_TIMEOUT_S)
    port = _serial_port(dev, timeout_s, write_timeout_s)
    return SerialMotorLink(
        port,
        ack_timeout_s=dev.options["ack_timeout"],
        watchdog_ms=dev.options["watchdog_ms"],
        retries=dev.options["retries"],
        # a board that dropped the link
        reopen=lambda: _serial_port(dev, timeout_s, write_timeout_s),
        max_counts_per_s=ENC_MAX_COUNTS_PER_S if max_counts_per_s is None else max_counts_per_s,
    )
