"""A ``replay://`` log played to its end: the GPS device's stale reason in ``status`` names the
replay's end, and so does the runner's "no valid fix" (its log line, the degraded reason),
not the line's wiring (a closing note's item left since round 13). So is a silent stretch
within the log, its receiver having sent nothing then."""

from __future__ import annotations

import dataclasses
import functools
from pathlib import Path

import pytest

from tests.test_daemon import hil_config, run_daemon, wait_for  # noqa: F401 (fixture)
from x6wd.app.client import RemoteClient
from x6wd.app.daemon import Daemon
from x6wd.core.config import GpsConfig, SafetyConfig

ORIGIN = (51.7123, 19.4876)


def _nmea(body: str) -> str:
    checksum = functools.reduce(lambda acc, ch: acc ^ ord(ch), body, 0)
    return f"${body}*{checksum:02X}\r\n"


def _fixes(n_s: int, start_s: int = 0) -> str:
    """``n_s`` seconds of valid GGA + RMC at the origin, 1 Hz, from 12:00:``start_s``."""
    out = []
    for i in range(start_s, start_s + n_s):
        t = f"1200{i:02d}.00"
        out.append(_nmea(f"GPGGA,{t},5142.738,N,01929.256,E,1,08,0.9,100.0,M,34.0,M,,"))
        out.append(_nmea(f"GPRMC,{t},A,5142.738,N,01929.256,E,0.0,0.0,010124,,,A"))
    return "".join(out)


@pytest.mark.parametrize("content", ["fixes", "empty", "garbage"])
def test_a_replay_at_its_end_is_named_not_the_wiring(
    tmp_path: Path,
    run_daemon,  # noqa: F811 (the fixture)
    content: str,
) -> None:
    log = tmp_path / "short.nmea"
    garbage = "".join(f"$GPGGA,{'x' * 40}{i}*00\r\n" for i in range(4))  # every line bad
    log.write_text({"fixes": _fixes(3), "empty": "", "garbage": garbage}[content])
    cfg = dataclasses.replace(
        hil_config(tmp_path),
        gps=GpsConfig(url=f"replay://{log}?speed=1"),
        safety=SafetyConfig(geofence_radius_m=100.0, fix_stale_s=2.5),
    )
    r = run_daemon(Daemon(cfg))
    # a log of bad lines is said as such (the wrong log, or the wrong format), then its end
    end = "the replayed log has none" if content == "empty" else "the replayed log has ended"
    with RemoteClient("127.0.0.1", r.port) as c:
        st = wait_for(
            lambda: (
                (s := c.request("status"))["devices"]["gps"]["state"] == "stale"
                and end in s["devices"]["gps"]["reason"]
                and s
            ),
            20,
            f"the gps stale, naming {end!r}",
        )
    reason = st["devices"]["gps"]["reason"]
    assert "wiring" not in reason, reason
    assert ("4 lines with bad checksums" in reason) == (content == "garbage"), reason
    runner = r.daemon.runner
    quiet = runner.gps_line_quiet(runner.clock() + 10.0)  # the runner's words (log, status)
    said = "the replayed log has ended" if content == "fixes" else "the replayed log has none"
    assert said in quiet and "wiring" not in quiet, quiet  # none that decodes: empty or bad


def test_a_replay_s_silent_stretch_is_named_not_the_wiring(tmp_path: Path, run_daemon) -> None:  # noqa: F811
    log = tmp_path / "gap.nmea"
    log.write_text(_fixes(3) + _fixes(3, start_s=15))  # 12 s in which its receiver said nothing
    cfg = dataclasses.replace(
        hil_config(tmp_path),
        gps=GpsConfig(url=f"replay://{log}?speed=1"),
        safety=SafetyConfig(geofence_radius_m=100.0, fix_stale_s=2.5),
    )
    r = run_daemon(Daemon(cfg))
    silent = "the replayed log is silent here"
    with RemoteClient("127.0.0.1", r.port) as c:
        st = wait_for(
            lambda: (s := c.request("status"))["devices"]["gps"]["state"] == "stale" and s,
            20,
            "the gps stale in the log's silent stretch",
        )
        reason = st["devices"]["gps"]["reason"]
        assert silent in reason and "wiring" not in reason and "ended" not in reason, reason
        runner = r.daemon.runner
        quiet = runner.gps_line_quiet(runner.clock() + 2.0)
        assert silent in quiet and "wiring" not in quiet, quiet
        # the log speaks again, then ends: said so, not "silent"
        end = wait_for(
            lambda: (
                "the replayed log has ended"
                in (s := c.request("status"))["devices"]["gps"]["reason"]
                and s
            ),
            30,
            "the log's end",
        )
    assert silent not in end["devices"]["gps"]["reason"], end
