"""The ``sim://`` device URLs: the simulator's protocol handler for :mod:`drivers.registry`.

Like pyserial's ``protocol_<scheme>`` modules: the registry imports this module by name when
it meets a ``sim://`` URL (the simulator is a higher layer than the drivers: a plug-in, not a
dependency of theirs). The world the devices live in is explicit, never a module's state:
:func:`open_backend` builds a :class:`sim_backend.hil.HilWorld` from the configuration's
``[sim]`` table, and :class:`drivers.registry.Devices` calls it on the first ``sim://`` open
of a configuration, shares that world between its GPS, compass and motors and closes it; a
caller may also hand its own world to ``Devices(backends={"sim": world})``.

A URL is ``sim://`` (or ``sim:///``): no path and no options, the world is set in ``[sim]``.

- GPS: a pyserial ``Serial`` on the world's receiver pseudo-terminal (the scenario's
  simulated NEO-5 at its baud rate).
- compass: a :class:`drivers.cmps10.Cmps10` on the world's CMPS10 register map.
- motors: the real :class:`drivers.motors.SerialMotorLink` on a new pseudo-terminal served by
  the world's motor board (watchdog ``[motors] watchdog_ms``, else ``[sim]
  motor_watchdog_ms``), reopened after a port error as a ``serial://`` board's is.
"""

from __future__ import annotations

from typing import Any

from drivers.registry import DeviceUrl
from sim_backend.hil import HilParams, HilWorld
from x6wd.core.config import SimConfig
from x6wd.core.errors import DeviceUnavailable

MOTOR_BAUD = 115200  # docs/motors.md default; a pty does not pace it anyway


def url_problem(dev: DeviceUrl) -> str | None:
    """Why ``dev`` is not a valid simulated-device URL, or None when it is."""
    if dev.target not in ("", "/") or dev.options:
        return "sim:// takes no path or options; the world is set in [sim]"
    return None


def _params(config: Any) -> HilParams:
    """The world's parameters from a whole configuration (its ``[sim]``), a ``[sim]`` table
    alone, parameters as they are, or None (the defaults)."""
    if isinstance(config, HilParams):
        return config
    sim = getattr(config, "sim", config)
    return HilParams.from_config(sim if isinstance(sim, SimConfig) else SimConfig())


def check_config(config: Any) -> HilParams:
    """Check the ``[sim]`` settings without building a world (ConfigError naming the key).

    Returns the checked parameters, their scenario loaded: :func:`open_backend` takes them, so
    the world runs what was checked and reads a ``[mission] file`` once."""
    return _params(config)


def open_backend(config: Any) -> HilWorld:
    """A running world built from ``config`` (see :func:`_params`); the caller closes it."""
    return HilWorld(_params(config))


def open_gps(dev: DeviceUrl, world: HilWorld) -> Any:
    """A pyserial port on the world's receiver pseudo-terminal, at the scenario's baud."""
    import serial

    name, baud = world.uart.port_name, world.receiver.baud
    try:
        # exclusive, as a serial:// port is: another program (a second daemon aimed at this
        # pty) is refused "in use" instead of sharing the line (an outside audit)
        return serial.Serial(name, baudrate=baud, timeout=0.1, exclusive=True)
    except (serial.SerialException, OSError) as exc:
        raise DeviceUnavailable(f"cannot open simulated GPS {name}: {exc}") from exc


def open_compass(dev: DeviceUrl, world: HilWorld) -> Any:
    """A CMPS10 driver on the world's register map (not checked on open)."""
    from drivers.cmps10 import Cmps10

    return Cmps10(world.compass_bus())


def open_motors(dev: DeviceUrl, world: HilWorld) -> Any:
    """The real motor driver (:class:`drivers.motors.SerialMotorLink`) on a new
    pseudo-terminal served by the world's motor board. Its watchdog (sent as ``W``) is the
    daemon's ``[motors] watchdog_ms`` (the registry passes it as ``watchdog_ms``), else the
    world's ``motor_watchdog_ms`` (also the board's power-up value).

    It reopens as the ``serial://`` link does (:func:`drivers.registry.open_motors`): after a
    port error that breaks it (the pty hung up, as a USB adapter that went away) the driver
    closes the port and opens the same pty again, with its capped exponential backoff
    (0.2 s doubling to 5 s, reset by a command through); the board serves the pty's far end
    for as long as the world runs, so the link recovers and the mission goes on."""
    import serial

    from drivers.motors import SerialMotorLink

    path = world.plug_motor_board()

    def open_port() -> Any:
        if not world.running:
            raise DeviceUnavailable("the HIL world is closed")
        try:
            return serial.Serial(path, baudrate=MOTOR_BAUD, timeout=0.02, exclusive=True)
        except (serial.SerialException, OSError) as exc:
            raise DeviceUnavailable(f"cannot open simulated motor board {path}: {exc}") from exc

    watchdog_ms = int(dev.options.get("watchdog_ms", world.params.motor_watchdog_ms))
    return SerialMotorLink(open_port(), watchdog_ms=watchdog_ms, reopen=open_port)
