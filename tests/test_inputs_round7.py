"""decode / replay / plot on inputs that are not regular files, long lines on stdin, gzip
(outside audit round 7, item 1-3).

Every CLI runs in a subprocess with a timeout: a hang fails the test, it does not block.
"""

from __future__ import annotations

import gzip
import json
import os
import subprocess
import sys
import threading
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
BIG = ROOT / "tests" / "data" / "nmea" / "quectel-l76k-dual.log"  # 196 KB: > a pipe's 64 KB
TIMEOUT = 60


def _x6wd(*args: str, stdin: bytes | None = None, shell: str | None = None):
    """Run ``python -m x6wd ARGS`` (or a bash command line with $X6WD) with a timeout."""
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    if shell is not None:
        env["X6WD"] = f"{sys.executable} -m x6wd"
        cmd: list[str] = ["bash", "-c", shell]
    else:
        cmd = [sys.executable, "-m", "x6wd", *args]
    return subprocess.run(
        cmd, input=stdin, capture_output=True, timeout=TIMEOUT, cwd=ROOT, env=env, check=False
    )


def _fifo_with_writer(tmp_path: Path, data: bytes, name: str = "fifo") -> Path:
    fifo = tmp_path / name
    os.mkfifo(fifo)

    def write() -> None:
        try:
            with open(fifo, "wb") as f:  # blocks until the reader opens it
                f.write(data)
        except OSError:
            pass

    threading.Thread(target=write, daemon=True).start()
    return fifo


def _recording(tmp_path: Path) -> Path:
    """An x6wd recording of BIG's sentences (> 64 KB)."""
    rec = tmp_path / "rec.jsonl"
    lines = [json.dumps({"t_mono": 0.0, "t_utc": "", "type": "event", "data": {"event": "start"}})]
    for k, text in enumerate(BIG.read_bytes().decode("ascii", "replace").splitlines()):
        if text.startswith("$"):
            lines.append(json.dumps({"t_mono": k * 0.01, "type": "nmea", "data": {"text": text}}))
    rec.write_text("\n".join(lines) + "\n")
    assert rec.stat().st_size > 1 << 16
    return rec


# --- item 1: pipes and FIFOs -------------------------------------------------------------


def test_decode_of_a_process_substitution_reads_every_byte() -> None:
    ref = _x6wd("decode", str(BIG))
    assert ref.returncode == 0 and ref.stdout.count(b'"TPV"') > 100
    got = _x6wd(shell=f"$X6WD decode <(cat {BIG})")
    assert got.returncode == 0, got.stderr
    assert got.stdout == ref.stdout  # the first 64 KB were lost


def test_decode_of_a_named_fifo_does_not_hang(tmp_path: Path) -> None:
    ref = _x6wd("decode", str(BIG))
    fifo = _fifo_with_writer(tmp_path, BIG.read_bytes())
    got = _x6wd("decode", str(fifo))
    assert got.returncode == 0, got.stderr
    assert got.stdout == ref.stdout


def test_decode_of_a_recording_through_a_fifo(tmp_path: Path) -> None:
    rec = _recording(tmp_path)
    ref = _x6wd("decode", str(rec))
    assert ref.returncode == 0 and ref.stdout.count(b'"TPV"') > 100
    fifo = _fifo_with_writer(tmp_path, rec.read_bytes())
    got = _x6wd("decode", str(fifo))
    assert got.returncode == 0, got.stderr
    assert got.stdout == ref.stdout


@pytest.mark.parametrize("tool", ["replay", "plot"])
def test_replay_and_plot_refuse_a_pipe_clearly(tool: str, tmp_path: Path) -> None:
    extra = "--speed 0" if tool == "replay" else f"--format html --out {tmp_path / 'p'}"
    got = _x6wd(shell=f"$X6WD {tool} {extra} <(cat {BIG})")
    err = got.stderr.decode()
    assert got.returncode == 2, err
    assert "Traceback" not in err
    assert "not a regular file" in err and "save it to a file first" in err


@pytest.mark.parametrize("tool", ["replay", "plot"])
def test_replay_and_plot_refuse_a_named_fifo_without_opening_it(tool: str, tmp_path: Path) -> None:
    fifo = tmp_path / "fifo"
    os.mkfifo(fifo)  # no writer: opening it would block
    extra = ["--speed", "0"] if tool == "replay" else ["--format", "html", "--out", str(tmp_path)]
    got = _x6wd(tool, *extra, str(fifo))
    assert got.returncode == 2, got.stderr
    assert b"not a regular file (a FIFO)" in got.stderr


@pytest.mark.parametrize("tool", ["replay", "plot"])
def test_replay_and_plot_of_dev_zero_end(tool: str, tmp_path: Path) -> None:
    extra = ["--speed", "0"] if tool == "replay" else ["--format", "html", "--out", str(tmp_path)]
    got = _x6wd(tool, *extra, "/dev/zero")
    assert got.returncode == 2 and b"not a regular file" in got.stderr


def test_decode_of_dev_zero_gives_up(tmp_path: Path) -> None:
    got = _x6wd("decode", "/dev/zero")
    assert got.returncode == 2
    assert b"no NMEA sentence" in got.stderr and b"given up" in got.stderr


def test_nmea_file_chunks_reads_a_pipe_in_one_pass() -> None:
    from x6wd.core.recorder import _nmea_lines_timed, nmea_file_chunks

    ref = list(nmea_file_chunks(BIG))
    r, w = os.pipe()

    def write() -> None:
        with open(w, "wb") as f:
            f.write(BIG.read_bytes())

    threading.Thread(target=write, daemon=True).start()
    with open(r, "rb") as f:
        got = list(_nmea_lines_timed(f, 1.0))
    assert got == ref


# --- item 2: one long line on stdin --------------------------------------------------------

# VmHWM, not ru_maxrss: that one keeps the parent's peak from before the exec
_PEAK = (
    "import sys\n"
    "from x6wd.app.cli import main\n"
    "sys.argv = ['x6wd', 'decode', '-']\n"
    "try:\n"
    "    main()\n"
    "except SystemExit:\n"
    "    pass\n"
    "hwm = [ln for ln in open('/proc/self/status') if ln.startswith('VmHWM:')][0]\n"
    "print(hwm.split()[1], file=sys.stderr)\n"
)


def _peak_kb(data: bytes) -> tuple[int, bytes, bytes]:
    p = subprocess.run(
        [sys.executable, "-c", _PEAK],
        input=data,
        capture_output=True,
        timeout=TIMEOUT,
        cwd=ROOT,
        env=dict(os.environ, PYTHONPATH=str(ROOT)),
        check=False,
    )
    return int(p.stderr.splitlines()[-1]), p.stdout, p.stderr


def test_decode_stdin_drops_an_over_long_recording_line_in_bounded_memory() -> None:
    first = b'{"t_mono":0.0,"t_utc":"","type":"event","data":{"event":"sim_start"}}\n'
    gga = b"$GPGGA,120000.00,5100.0000,N,00100.0000,W,1,08,1.0,10.0,M,0.0,M,,*70"
    after = json.dumps({"t_mono": 2.0, "type": "nmea", "data": {"text": gga.decode()}})
    long = b'{"t_mono":1.0,"type":"nmea","data":{"text":"' + b"A" * (80 << 20) + b'"}}\n'
    base, _, _ = _peak_kb(first)
    peak, _out, err = _peak_kb(first + long + after.encode() + b"\n")
    assert b"bad_recording_lines=1" in err and b"sentences=1 " in err, err  # the next: read
    assert peak - base < 40 << 10, (base, peak)  # was 2 x the line


def test_decode_stdin_long_line_without_newline_is_counted() -> None:
    first = b'{"t_mono":0.0,"t_utc":"","type":"event","data":{"event":"sim_start"}}\n'
    cut = b'{"t_mono":1.0,"type":"nmea","data":{"text":"' + b"A" * (3 << 20)
    p = _x6wd("decode", "-", stdin=first + cut)
    assert b"bad_recording_lines=1" in p.stderr, p.stderr


# --- item 3: compressed inputs -------------------------------------------------------------


def test_decode_reads_gzip(tmp_path: Path) -> None:
    ref = _x6wd("decode", str(BIG))
    gz = tmp_path / "log.nmea.gz"
    gz.write_bytes(gzip.compress(BIG.read_bytes()))
    got = _x6wd("decode", str(gz))
    assert got.returncode == 0, got.stderr
    assert got.stdout == ref.stdout
    piped = _x6wd("decode", "-", stdin=gz.read_bytes())
    assert piped.returncode == 0 and piped.stdout == ref.stdout


def test_decode_reads_a_gzipped_recording(tmp_path: Path) -> None:
    rec = _recording(tmp_path)
    ref = _x6wd("decode", str(rec))
    gz = tmp_path / "rec.jsonl.gz"
    gz.write_bytes(gzip.compress(rec.read_bytes()))
    got = _x6wd("decode", str(gz))
    assert got.returncode == 0, got.stderr
    assert got.stdout == ref.stdout


@pytest.mark.parametrize("tool", ["replay", "plot"])
def test_replay_and_plot_name_gzip(tool: str, tmp_path: Path) -> None:
    gz = tmp_path / "log.nmea.gz"
    gz.write_bytes(gzip.compress(BIG.read_bytes()))
    extra = ["--speed", "0"] if tool == "replay" else ["--format", "html", "--out", str(tmp_path)]
    got = _x6wd(tool, *extra, str(gz))
    assert got.returncode == 2
    assert b"compressed (gzip): decompress it first" in got.stderr, got.stderr


def test_decode_says_a_gzip_is_cut_and_refuses_other_compressions(tmp_path: Path) -> None:
    import bz2

    cut = tmp_path / "cut.nmea.gz"
    cut.write_bytes(gzip.compress(BIG.read_bytes())[:30_000])
    got = _x6wd("decode", str(cut))
    assert got.returncode == 2 and got.stdout.count(b'"TPV"') > 0  # what came before
    assert b"compressed (gzip), damaged or cut" in got.stderr
    bz = tmp_path / "log.nmea.bz2"
    bz.write_bytes(bz2.compress(BIG.read_bytes()))
    got = _x6wd("decode", str(bz))
    assert got.returncode == 2
    assert (
        got.stderr.strip() == f"x6wd decode: {bz}: compressed (bzip2): decompress it first".encode()
    )
