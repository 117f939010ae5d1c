"""A stop signal that arrives during start-up, after the preflight and the ports' binding but
before the devices are opened (an outside audit: SIGTERM ~1 s after launch was logged, then
start-up went on to open the motor port, start a recording and log "ready" before it
stopped). Now nothing more is opened: on a robot, opening the motor port can reset its board
on the way out."""

from __future__ import annotations

import asyncio
import logging
import signal
from pathlib import Path

import pytest

from tests.test_daemon import hil_config
from x6wd.app.daemon import Daemon


@pytest.mark.parametrize("signum", [signal.SIGTERM, signal.SIGINT])
def test_a_stop_signal_during_start_up_opens_no_device(
    tmp_path: Path, caplog: pytest.LogCaptureFixture, signum: int
) -> None:
    cfg = hil_config(tmp_path)
    daemon = Daemon(cfg)
    bind = daemon._bind_servers

    async def bind_then_signal() -> None:  # the signal lands just after the ports are bound
        await bind()
        daemon.stop_on_signal(signum, 0)

    daemon._bind_servers = bind_then_signal  # type: ignore[method-assign]
    ready: list[Daemon] = []
    with caplog.at_level(logging.INFO):
        code = asyncio.run(daemon.run(ready=ready.append))
    assert code == 0
    assert not ready and daemon.motors is None  # never opened, never ready
    rec = Path(cfg.recorder.dir)
    assert not rec.exists() or not any(rec.iterdir()), list(rec.iterdir())
    text = caplog.text
    assert "received: stopping the motors" in text
    assert "stopped during start-up" in text and " ready" not in text, text


def test_a_stop_signal_while_the_devices_open_starts_no_recording(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    # a review (round 22): a signal that lands while the devices open (a motor board that
    # resets on open takes a while) went on to start a recording and log "ready"
    cfg = hil_config(tmp_path)
    daemon = Daemon(cfg)
    open_devices = daemon._open_devices

    async def open_then_signal() -> None:
        await open_devices()
        daemon.stop_on_signal(signal.SIGTERM, 0)

    daemon._open_devices = open_then_signal  # type: ignore[method-assign]
    ready: list[Daemon] = []
    with caplog.at_level(logging.INFO):
        code = asyncio.run(daemon.run(ready=ready.append))
    assert code == 0 and not ready
    assert daemon.motors is not None  # opened, then closed with the motors stopped
    rec = Path(cfg.recorder.dir)
    assert not rec.exists() or not any(rec.iterdir()), list(rec.iterdir())
    assert " ready" not in caplog.text, caplog.text
