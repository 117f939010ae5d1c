"""A newcomer's walkthrough, round 11: what a first user of the README's tour runs into.

1. ``x6wd calibrate gnss --static`` alone wrote a standing receiver's ``re_m`` without a word,
   although pasted into the robot's configuration it makes the EKF worse
   (docs/gnss_calibration.md, "--static alone").
2. ``x6wd client``: a certificate that does not name ``--host`` gave OpenSSL's raw reason
   and nothing more, ``stop`` said "Renew the robot's certificate" whatever the cause, and
   ``start`` without a token did not name ``--token-file``.
3. ``x6wd sim``: a run that ended with the mission PAUSED said "on hold" in its first line.
"""

from __future__ import annotations

import calendar
import collections
import contextlib
import json
import os
import random
import re
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from tests.conftest import require_program, self_signed_cert
from tests.test_calibrate_gnss import (
    loop_track,
    sim_fixes,
    truth_series,
    world,
    write_recording,
    write_truth_csv,
)
from tests.test_server import TOKEN, LoopThread, RecordingBackend
from tests.test_tls_cert_dates import dated_cert
from x6wd.app.server import ControlServer, server_ssl_context
from x6wd.core import config
from x6wd.core.config import ServerConfig

ROOT = Path(__file__).resolve().parent.parent
X6WD = [sys.executable, "-m", "x6wd"]


def _run(argv: list[str], cwd: Path, timeout: float = 240.0) -> subprocess.CompletedProcess[str]:
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    return subprocess.run(
        [*X6WD, *argv], cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout
    )


# ------------------------------------------------------------------ 1. calibrate gnss --static


def test_static_alone_warns_above_re_m_and_on_stderr(tmp_path: Path) -> None:
    # the README's tour: 10 min standing on a known point, then the static calibration
    sim = _run([
        "sim", str(ROOT / "config" / "scenarios" / "open_field.toml"), "--out",
        str(tmp_path / "static"), "--quiet",
    ], tmp_path)  # fmt: skip
    assert sim.returncode == 0, sim.stderr
    out = tmp_path / "gnss.toml"
    r = _run([
        "calibrate", "gnss", "--static", str(tmp_path / "static" / "recording.jsonl"),
        "--ref-lat", "51.752", "--ref-lon", "-1.2577", "--out", str(out),
    ], tmp_path)  # fmt: skip
    assert r.returncode == 0, r.stderr
    warn = [ln for ln in r.stderr.splitlines() if "WARNING" in ln]
    assert len(warn) == 1, r.stderr
    assert warn[0].startswith("x6wd calibrate: WARNING: re_m is a standing receiver's white part")
    for part in ("--drive", "Experiment 3", "do not paste it alone", "re_m (1.0 as shipped)"):
        assert part in warn[0], warn[0]
    lines = out.read_text().splitlines()
    at = next(i for i, ln in enumerate(lines) if ln.startswith("re_m = "))
    # the comment line right above re_m, the same text as on stderr
    assert lines[at - 1] == "# WARNING: " + warn[0].removeprefix("x6wd calibrate: WARNING: ")
    assert lines[at - 2] == "[gnss_noise]"
    # still a fragment the daemon loads (its measured value kept, with the warning over it)
    assert 0.0 < config.loads(out.read_text()).gnss_noise.re_m < 0.5


def test_static_with_drives_writes_no_standing_warning(tmp_path: Path) -> None:
    w_static = world(re=0.8, ase=0.0, grid=[[0.0]])
    n = 600
    static = write_recording(
        tmp_path / "static.jsonl", sim_fixes(w_static, 3, np.arange(n, dtype=float),
                                             np.zeros((n, 3)))
    )  # fmt: skip
    w = world(re=0.8, ase=0.0)
    t, pos = loop_track(laps=2)
    drive = write_recording(tmp_path / "drive.jsonl", sim_fixes(w, 4, t, pos))
    ref = write_truth_csv(tmp_path / "truth.csv", truth_series(w, t, pos))
    o = w_static.origin
    r = _run([
        "calibrate", "gnss", "--static", str(static), "--ref-lat", str(o.lat_deg),
        "--ref-lon", str(o.lon_deg), "--drive", str(drive), "--reference", str(ref),
    ], tmp_path)  # fmt: skip
    assert r.returncode == 0, r.stderr
    assert "standing receiver" not in r.stderr and "standing receiver" not in r.stdout
    assert "[gnss_noise]" in r.stdout


def test_static_with_drives_too_short_for_the_moving_white_part_still_warns(
    tmp_path: Path,
) -> None:
    # a drive of 45 fixes (< 50 pairs one epoch apart): the drives cannot measure the moving
    # white part, so the re_m written is the static one and the warning must stand
    w_static = world(re=0.07, ase=0.3, grid=[[0.0]])
    n = 600
    static = write_recording(
        tmp_path / "static.jsonl", sim_fixes(w_static, 3, np.arange(n, dtype=float),
                                             np.zeros((n, 3)))
    )  # fmt: skip
    w = world(re=0.8, ase=0.3)
    t, pos = loop_track(laps=1)
    t, pos = t[:45], pos[:45]
    drive = write_recording(tmp_path / "drive.jsonl", sim_fixes(w, 4, t, pos))
    ref = write_truth_csv(tmp_path / "truth.csv", truth_series(w, t, pos))
    o = w_static.origin
    r = _run([
        "calibrate", "gnss", "--static", str(static), "--ref-lat", str(o.lat_deg),
        "--ref-lon", str(o.lon_deg), "--drive", str(drive), "--reference", str(ref),
    ], tmp_path)  # fmt: skip
    assert r.returncode == 0, r.stderr
    re_line = next(ln for ln in r.stdout.splitlines() if ln.startswith("re_m = "))
    assert "static recording" in re_line, re_line  # the standing figure is what is written
    warn = [ln for ln in r.stderr.splitlines() if "WARNING" in ln]
    assert len(warn) == 1, r.stderr
    assert warn[0].startswith("x6wd calibrate: WARNING: re_m is a standing receiver's white part")
    assert "too short to measure it" in warn[0], warn[0]
    lines = r.stdout.splitlines()
    at = lines.index(re_line)
    assert lines[at - 1] == "# WARNING: " + warn[0].removeprefix("x6wd calibrate: WARNING: ")


# ------------------------------------------------------------------ 3. sim summary: paused


@pytest.mark.parametrize("duration", [None, "100.3"])
def test_a_run_ending_paused_says_paused_with_its_start_and_reason(
    tmp_path: Path, duration: str | None
) -> None:
    # the default scenario with a 45 s GPS outage from 20 s and a robot that holds at once
    # without a fix: the failsafe pauses the mission at ~50 s and it stays paused to 400 s
    # (or to a fractional --duration: the pause's end is stored rounded to 3 decimals, the
    # run's end k*dt is not, and the open pause read as one that had ended)
    scenario = tmp_path / "outage.toml"
    scenario.write_text(
        (ROOT / "config" / "scenarios" / "default.toml").read_text()
        + '\n[[effects]]\nname = "outage"\nstart_s = 20.0\nduration_s = 45.0\n'
    )
    robot = (ROOT / "config" / "x6wd.toml").read_text()
    assert "\ngps_outage_max_m = 20.0" in robot
    cfg = tmp_path / "robot.toml"
    cfg.write_text(robot.replace("\ngps_outage_max_m = 20.0", "\ngps_outage_max_m = 0.0"))
    extra = ["--duration", duration] if duration is not None else []
    r = _run(["sim", str(scenario), "--config", str(cfg), "--quiet", "--out",
              str(tmp_path / "out"), *extra], tmp_path)  # fmt: skip
    assert r.returncode == 1, r.stderr  # 1: the mission not completed
    head = next(ln for ln in r.stdout.splitlines() if ln.startswith("scenario "))
    paused = next(ln for ln in r.stdout.splitlines() if ln.strip().startswith("paused "))
    # the detail line: "paused 349.9 s (since 50.1 s: no valid fix for 30 s)"
    since = paused[paused.index("(since ") : paused.rindex(")") + 1]
    assert "no valid fix for 30 s" in since, paused
    end_s = 400 if duration is None else round(float(duration))
    assert head.endswith(f"mission NOT completed: the mission was paused {since} when the run "
                         f"ended at {end_s} s"), head  # fmt: skip
    assert "on hold" not in head


# ------------------------------------------------------------------ 2. client: TLS and auth hints


def _free_port() -> int:
    """A port of 7850-7899 nothing listens on now (127.0.0.1)."""
    ports = list(range(7850, 7900))
    random.shuffle(ports)
    for port in ports:
        with socket.socket() as s, contextlib.suppress(OSError):
            s.bind(("127.0.0.1", port))
            return port
    pytest.skip("no free port in 7850-7899")


@contextlib.contextmanager
def _robot(cert: Path | None = None, key: Path | None = None, now_s: float | None = None,
           ) -> Iterator[int]:  # fmt: skip
    """The real control server on 127.0.0.1 (a token; TLS with ``cert``: its dates judged at
    ``now_s``), its port."""
    lt = LoopThread()
    ctx = server_ssl_context(str(cert), str(key), now_s=now_s) if cert and key else None
    srv = ControlServer(ServerConfig(port=_free_port()), RecordingBackend(),
                        token=TOKEN.encode(), ssl_context=ctx)  # fmt: skip
    try:
        lt.run(srv.start())
        yield srv.port
    finally:
        lt.run(srv.close())
        lt.close()


def _client(port: int, *argv: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [*X6WD, "client", "--port", str(port), "--timeout", "20", *argv],
        capture_output=True, text=True, timeout=60, cwd=ROOT,
    )  # fmt: skip


def _cert_without_the_ip(directory: Path) -> tuple[Path, Path]:
    """A self-signed certificate naming robot.invalid only (not 127.0.0.1), and its key."""
    cert, key = directory / "cert.pem", directory / "key.pem"
    subprocess.run(
        [require_program("openssl"), "req", "-x509", "-newkey", "rsa:2048", "-nodes",
         "-days", "2", "-subj", "/CN=x6wd", "-addext", "subjectAltName=DNS:robot.invalid",
         "-keyout", str(key), "-out", str(cert)],
        check=True, capture_output=True,
    )  # fmt: skip
    key.chmod(0o600)
    return cert, key


NAME_HINT = (
    "the certificate must name this --host (127.0.0.1) in its subjectAltName: connect with a "
    "name or address it lists, or make the robot's certificate with it (docs/install.md, "
    "section 2)"
)


@pytest.mark.integration
def test_a_certificate_without_the_hosts_name_says_what_to_fix(tmp_path: Path) -> None:
    cert, key = _cert_without_the_ip(tmp_path)
    with _robot(cert, key) as port:
        st = _client(port, "--cafile", str(cert), "status")
        stop = _client(port, "--cafile", str(cert), "stop")
    assert st.returncode == 3, st.stderr
    assert "IP address mismatch" in st.stderr, st.stderr
    assert st.stderr.rstrip().endswith(": " + NAME_HINT), st.stderr
    # the stop goes out unverified (exit 4) and names the same fix, not a renewal
    assert stop.returncode == 4, (stop.stdout, stop.stderr)
    assert "To fix it: " + NAME_HINT in stop.stderr, stop.stderr
    assert "renew" not in stop.stderr.lower()


@pytest.mark.integration
def test_an_expired_or_untrusted_certificate_gets_its_own_fix(tmp_path: Path) -> None:
    # valid for February 2026 (after this release's date: the server takes it at a date
    # within it), expired for the client's clock
    start_s = calendar.timegm(time.strptime("2026-02-01", "%Y-%m-%d"))
    assert time.time() > start_s + 40 * 86400
    (tmp_path / "old").mkdir()
    old, old_key = dated_cert(tmp_path / "old", start_s, start_s + 28 * 86400)
    with _robot(old, old_key, now_s=start_s + 14 * 86400) as port:
        stop = _client(port, "--cafile", str(old), "stop")
        st = _client(port, "--cafile", str(old), "status")
    assert stop.returncode == 4, (stop.stdout, stop.stderr)
    assert "certificate has expired" in stop.stderr
    assert "To fix it: renew the robot's certificate (docs/install.md, section 2)" in stop.stderr
    assert st.returncode == 3 and st.stderr.rstrip().endswith(
        ": renew the robot's certificate (docs/install.md, section 2)"
    ), st.stderr
    # another certificate than the robot's in --cafile: not a name or date matter
    (tmp_path / "robot").mkdir()
    (tmp_path / "other").mkdir()
    cert, key = self_signed_cert(tmp_path / "robot")
    other, _ = self_signed_cert(tmp_path / "other")
    with _robot(cert, key) as port:
        stop = _client(port, "--cafile", str(other), "stop")
        st = _client(port, "--cafile", str(other), "status")
    hint = "give the robot's own certificate with --cafile (copy its cert.pem"
    assert stop.returncode == 4 and "To fix it: " + hint in stop.stderr, stop.stderr
    assert st.returncode == 3 and hint in st.stderr and "subjectAltName" not in st.stderr


@pytest.mark.integration
def test_a_command_refused_for_want_of_a_token_names_token_file(tmp_path: Path) -> None:
    token = tmp_path / "token"
    token.write_text(TOKEN + "\n")
    token.chmod(0o600)
    with _robot() as port:
        bare = _client(port, "start")
        given = _client(port, "--token-file", str(token), "pause")
    assert bare.returncode == 1, bare.stderr
    assert bare.stderr.strip() == (
        "x6wd client: start refused: unauthorized: authenticate first to use 'start'; give "
        "the robot's token with --token-file FILE (docs/install.md, section 4)"
    ), bare.stderr
    assert "--token-file" not in given.stderr  # authenticated: no hint about it


# ------------------------------------------------------------------ 4. docs: 4 Hz at 9600 baud


def test_the_uart_paragraph_gives_what_4_hz_at_9600_baud_gets_through(tmp_path: Path) -> None:
    """docs/simulator.md said RMC, VTG, GGA and GSA get through and nearly all GSV and GLL are
    dropped: GSA lost one epoch in three and GLL got through one in four. Its numbers now
    are the default scenario's at rate_hz = 4, counted here as the doc says: the sentences
    the receiver formatted (gps.nmea) against those that crossed the line (the recording)."""
    text = (ROOT / "config" / "scenarios" / "default.toml").read_text()
    assert "\nrate_hz = 1.0" in text and "\nbaud = 9600" in text
    scenario = tmp_path / "four_hz.toml"
    scenario.write_text(text.replace("\nrate_hz = 1.0", "\nrate_hz = 4.0"))
    r = _run(["sim", str(scenario), "--quiet", "--out", str(tmp_path / "out")], tmp_path)
    assert r.returncode == 0, r.stderr
    made = collections.Counter(
        ln[3:6] for ln in (tmp_path / "out" / "gps.nmea").read_text().splitlines()
        if ln.startswith("$")
    )  # fmt: skip
    sent: collections.Counter[str] = collections.Counter()
    for ln in (tmp_path / "out" / "recording.jsonl").read_text().splitlines():
        rec = json.loads(ln)
        if rec.get("type") == "nmea":
            sent[rec["data"]["text"][3:6]] += 1
    doc = " ".join((ROOT / "docs" / "simulator.md").read_text().split())
    m = re.search(
        r"RMC, VTG and GGA (\d+) of (\d+), GSA (\d+) of (\d+), GLL (\d+) of (\d+), GSV (\d+) of "
        r"(\d+);", doc,
    )  # fmt: skip
    assert m, "docs/simulator.md: the UART paragraph's counts"
    said = [int(g) for g in m.groups()]
    for kind in ("RMC", "VTG", "GGA"):
        assert [sent[kind], made[kind]] == said[0:2], kind
    assert [sent["GSA"], made["GSA"], sent["GLL"], made["GLL"], sent["GSV"], made["GSV"]] == (
        said[2:]
    )
    # and the words around them: GSA about two epochs in three, GLL one in four
    assert 0.55 < sent["GSA"] / made["GSA"] < 0.75 and 0.15 < sent["GLL"] / made["GLL"] < 0.35
    assert "GSA about two epochs in three, GLL one in four and GSV hardly ever" in doc
