"""Packaging: the robot's install (pyproject.toml's core dependencies) is exactly what the
daemon imports; the other tools' packages are extras, a tool without its extra says which one
to install; `dev` holds every extra; constraints.txt pins everything `.[dev]` installs."""

from __future__ import annotations

import ast
import importlib.metadata as md
import importlib.util
import json
import re
import signal
import socket
import subprocess
import sys
import threading
import time
import tomllib
from collections.abc import Iterator
from pathlib import Path

import pytest
from packaging.requirements import Requirement
from packaging.utils import canonicalize_name

from tests.conftest import ROOT

PYPROJECT = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))
PROJECT = PYPROJECT["project"]
OWN_PACKAGES = ("x6wd", "drivers", "sim_backend")
# what `x6wd run` imports: the command line, then the daemon (cli loads only the chosen module)
DAEMON_ENTRY = ("x6wd.app.cli", "x6wd.app.daemon")
# the packages only extras install; the daemon must run with them unimportable
OPTIONAL = ("scipy", "matplotlib", "dask", "distributed")


def names(reqs: list[str]) -> set[str]:
    return {canonicalize_name(Requirement(r).name) for r in reqs}


def _source(module: str) -> Path | None:
    try:
        spec = importlib.util.find_spec(module)
    except (ImportError, AttributeError, ValueError):
        return None  # `from module import name` where name is not a module
    if spec is None or spec.origin is None or not spec.origin.endswith(".py"):
        return None
    return Path(spec.origin)


def _imports(tree: ast.Module, module: str, is_package: bool) -> Iterator[str]:
    """Every module an import statement names, at any depth (functions import lazily),
    except under ``if TYPE_CHECKING:``."""
    skip: set[int] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test):
            skip.update(id(n) for stmt in node.body for n in ast.walk(stmt))
    for node in ast.walk(tree):
        if id(node) in skip:
            continue
        if isinstance(node, ast.Import):
            yield from (a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = module.split(".")
                base = base[: len(base) - node.level + (1 if is_package else 0)]
                name = ".".join(base + ([node.module] if node.module else []))
            else:
                name = node.module or ""
            yield name
            for a in node.names:  # `from pkg import module`
                yield f"{name}.{a.name}"


def daemon_imports() -> tuple[set[str], set[str]]:
    """(own modules, external top-level modules) that the daemon's code imports, following
    every import statement of its own modules, lazy ones included."""
    seen: set[str] = set()
    external: set[str] = set()
    todo = list(DAEMON_ENTRY)
    while todo:
        mod = todo.pop()
        if mod in seen:
            continue
        path = _source(mod)
        if path is None:
            continue  # `from pkg import name` where name is not a module
        seen.add(mod)
        tree = ast.parse(path.read_text(encoding="utf-8"), str(path))
        for name in _imports(tree, mod, path.name == "__init__.py"):
            top = name.split(".")[0]
            if top in OWN_PACKAGES:
                parts = name.split(".")
                todo += [".".join(parts[: i + 1]) for i in range(len(parts))]
            elif top and top not in sys.stdlib_module_names and top != "__future__":
                external.add(top)
    return seen, external


def distributions_of(modules: set[str]) -> set[str]:
    pd = md.packages_distributions()
    missing = sorted(m for m in modules if m not in pd)
    assert not missing, f"imported but not installed by any distribution: {missing}"
    return {canonicalize_name(d) for m in modules for d in pd[m]}


def test_core_dependencies_are_exactly_what_the_daemon_imports() -> None:
    own, external = daemon_imports()
    assert "x6wd.app.daemon" in own and "drivers.registry" in own
    # the simulator is loaded by name for sim:// URLs only (drivers.registry.protocol_handler)
    assert not [m for m in own if m.startswith("sim_backend")], sorted(own)
    assert not [m for m in own if m.startswith(("x6wd.gap", "x6wd.calibrate"))], sorted(own)
    assert not set(OPTIONAL) & external, external
    assert distributions_of(external) == names(PROJECT["dependencies"]), (
        f"the daemon imports {sorted(external)}; pyproject.toml's [project] dependencies must "
        "be exactly their distributions (the rest goes to an extra)"
    )


def test_every_extra_is_in_dev_and_the_extras_cover_the_tools() -> None:
    extras = PROJECT["optional-dependencies"]
    assert set(extras) >= {"sim", "gap", "plot", "sweep", "dev"}
    dev = names(extras["dev"])
    for extra, reqs in extras.items():
        assert names(reqs) <= dev, f"dev lacks {extra}'s {sorted(names(reqs) - dev)}"
    assert names(extras["sim"]) >= {"scipy", "matplotlib"}
    assert names(extras["gap"]) >= {"scipy", "matplotlib"}
    assert names(extras["plot"]) >= {"matplotlib"}
    assert names(extras["sweep"]) >= {"dask", "scipy", "matplotlib"}
    assert not names(PROJECT["dependencies"]) & {"scipy", "matplotlib", "dask"}


def _closure(reqs: list[str], extras: tuple[str, ...] = ()) -> set[str]:
    """The distributions ``reqs`` bring in, from the installed metadata (markers evaluated)."""
    out: set[str] = set()
    todo = [(Requirement(r), extras) for r in reqs]
    while todo:
        req, parent_extras = todo.pop()
        env_ok = req.marker is None or any(
            req.marker.evaluate({"extra": e}) for e in (parent_extras or ("",))
        )
        if not env_ok:
            continue
        name = canonicalize_name(req.name)
        key = name + "[" + ",".join(sorted(req.extras)) + "]"
        if key in out:
            continue
        out.add(key)
        dist = md.distribution(req.name)
        for r in dist.requires or []:
            todo.append((Requirement(r), tuple(sorted(req.extras))))
    return {k.split("[")[0] for k in out}


def test_constraints_pin_everything_dev_installs() -> None:
    pins: dict[str, str] = {}
    for line in (ROOT / "constraints.txt").read_text(encoding="utf-8").splitlines():
        line = line.split("#")[0].strip()
        if line:
            name, _, version = line.partition("==")
            assert version, f"constraints.txt: {line!r} is not pinned with =="
            pins[canonicalize_name(name)] = version.strip()
    reqs = PROJECT["dependencies"] + PROJECT["optional-dependencies"]["dev"]
    for extra in PROJECT["optional-dependencies"].values():
        reqs = reqs + extra
    needed = _closure(reqs)
    assert not needed - set(pins), f"not pinned in constraints.txt: {sorted(needed - set(pins))}"


# -- the daemon with the optional packages unimportable --------------------------------------

# A CMPS10 answering on a bus that this machine does not have (register 0: the version, 2-3:
# the bearing in tenths of a degree, 4-5: pitch, roll), for the real driver to read.
RUN_WITHOUT_EXTRAS = """
import json, sys
for name in {optional!r}:
    sys.modules[name] = None  # `import scipy` raises ModuleNotFoundError
import smbus2
import drivers.registry

class Cmps10Bus:
    def __init__(self, bus): pass
    def read_byte_data(self, addr, reg): return 15 if reg == 0 else 64
    # registers 0-5: version 15, bearing 90.0 deg (coarse 64/256 of a turn, fine 900), level
    def read_i2c_block_data(self, addr, reg, n):
        return ([15, 64, 3, 132, 0, 0] + [0] * 32)[reg:reg + n]
    def write_byte_data(self, addr, reg, value): pass
    def close(self): pass

smbus2.SMBus = Cmps10Bus
drivers.registry.I2C_DEV = "/dev/null"  # the start-up check wants a character device
from x6wd.app.cli import main
rc = main(sys.argv[1:])
import importlib.metadata as md
pd = md.packages_distributions()
loaded = sorted(n for n, m in list(sys.modules.items()) if m is not None and "." not in n)
print(json.dumps({{"rc": rc, "modules": [n for n in loaded if n in pd]}}))
"""


def redated(nmea: bytes, ddmmyy: str) -> bytes:
    """The log with every RMC's date replaced (and its checksum recomputed)."""
    out = []
    for line in nmea.splitlines(keepends=True):
        if line[3:6] == b"RMC" and b"*" in line:
            body = line[1 : line.index(b"*")].decode("ascii").split(",")
            body[9] = ddmmyy
            text = ",".join(body).encode("ascii")
            check = 0
            for b in text:
                check ^= b
            line = b"$" + text + b"*%02X\r\n" % check
        out.append(line)
    return b"".join(out)


def _serve_nmea(sock: socket.socket, data: bytes, stop: threading.Event) -> None:
    sock.settimeout(10.0)
    try:
        conn, _ = sock.accept()
    except OSError:
        return
    with conn:
        lines = data.splitlines(keepends=True)
        while not stop.is_set():
            for line in lines:
                if stop.is_set():
                    return
                try:
                    conn.sendall(line)
                except OSError:
                    return
                time.sleep(0.005)


@pytest.mark.integration
def test_the_daemon_runs_without_scipy_matplotlib_or_dask(tmp_path: Path) -> None:
    """`x6wd run` with a robot configuration (a GPS on TCP, the compass on I2C, logged
    motors): starts, decodes fixes, stops cleanly on SIGTERM, and imports only the core
    dependencies, with every optional package unimportable."""
    # a real receiver's bytes, dated inside the WMM's validity so that the daemon evaluates
    # the declination (wmm-calculator) at the first dated fix
    nmea = redated((ROOT / "tests" / "data" / "nmea" / "ublox-lea-5h.log").read_bytes(), "150626")
    listener = socket.create_server(("127.0.0.1", 0))
    port = listener.getsockname()[1]
    stop = threading.Event()
    server = threading.Thread(target=_serve_nmea, args=(listener, nmea, stop), daemon=True)
    server.start()
    config = tmp_path / "robot.toml"
    config.write_text(
        f'[gps]\nurl = "tcp://127.0.0.1:{port}"\n'
        '[compass]\nurl = "i2c://1/0x60"\n'
        '[motors]\nurl = "log://"\n'
        "[server]\nport = 0\n[gpsd]\nport = 0\n"
        f'[recorder]\ndir = "{tmp_path / "rec"}"\n',
        encoding="utf-8",
    )
    script = RUN_WITHOUT_EXTRAS.format(optional=OPTIONAL)
    proc = subprocess.Popen(
        [sys.executable, "-c", script, "run", "--config", str(config)],
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        deadline = time.monotonic() + 60.0
        while time.monotonic() < deadline and proc.poll() is None:
            rec = list((tmp_path / "rec").glob("*"))
            if rec and sum(p.stat().st_size for p in rec if p.is_file()) > 20_000:
                break  # fixes recorded
            time.sleep(0.2)
        assert proc.poll() is None, proc.communicate()[1]
        time.sleep(1.0)
        proc.send_signal(signal.SIGTERM)
        out, err = proc.communicate(timeout=30)
    finally:
        stop.set()
        listener.close()
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert "Traceback" not in err and "ModuleNotFoundError" not in err, err
    assert re.search(r"\bready\b", err), err
    result = json.loads(out.strip().splitlines()[-1])
    assert result["rc"] == 0, err
    modules = set(result["modules"])
    assert {"numpy", "serial", "smbus2", "wmm"} <= modules, modules
    assert not modules & set(OPTIONAL)
    # (setuptools' _distutils_hack is loaded by a .pth file into every process of the venv)
    core = _closure(PROJECT["dependencies"]) | {"setuptools"}
    assert distributions_of(modules) <= core, sorted(distributions_of(modules) - core)
    # the compass on its (stand-in) bus was read: valid samples at its 90.0 deg
    bearings = [
        rec["data"].get("bearing_deg")
        for path in sorted((tmp_path / "rec").glob("*.jsonl"))
        for line in path.read_text().splitlines()
        if (rec := json.loads(line))["type"] == "attitude" and rec["data"].get("valid")
    ]
    assert bearings and all(b == 90.0 for b in bearings), bearings[:5]


def _without_extras(*args: str, timeout_s: float = 60.0) -> subprocess.CompletedProcess[str]:
    script = (
        "import sys\n"
        f"for name in {OPTIONAL!r}:\n"
        "    sys.modules[name] = None\n"
        "from x6wd.app.cli import main\n"
        "sys.exit(main(sys.argv[1:]))\n"
    )
    return subprocess.run(
        [sys.executable, "-c", script, *args],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=timeout_s,
    )


@pytest.mark.integration
@pytest.mark.parametrize(
    ("args", "extra"),
    [
        (("sim", "config/scenarios/default.toml", "--out", "{tmp}/out"), "sim"),
        (("run", "--config", "config/hil.toml"), "sim"),
        (("gap", "--real", "x.nmea", "--scenario", "config/scenarios/default.toml"), "gap"),
        (("sweep", "config/sweeps/position_source.toml", "--out", "{tmp}/sweep"), "sweep"),
    ],
)
def test_a_tool_without_its_extra_names_the_extra(
    tmp_path: Path, args: tuple[str, ...], extra: str
) -> None:
    proc = _without_extras(*(a.format(tmp=tmp_path) for a in args))
    assert proc.returncode == 2, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in proc.stderr, proc.stderr
    assert lines[0].startswith(f"x6wd {args[0]}:"), lines[0]
    assert f"pip install 'x6wd[{extra}]'" in lines[0], lines[0]


@pytest.mark.integration
def test_the_tools_that_need_no_extra_run_without_them(tmp_path: Path) -> None:
    log = ROOT / "tests" / "data" / "nmea" / "ublox-lea-5h.log"
    proc = _without_extras("decode", str(log))
    assert proc.returncode == 0 and '"class":"TPV"' in proc.stdout, proc.stderr
    out = tmp_path / "m.waypoints"
    proc = _without_extras("mission", "convert", str(ROOT / "missions" / "default.kml"), str(out))
    assert proc.returncode == 0 and out.read_text().startswith("QGC WPL 110"), proc.stderr


def test_the_message_names_the_commands_extra() -> None:
    from x6wd.app.cli import missing_extra

    def msg(command: str, module: str) -> str | None:
        return missing_extra(
            command, ModuleNotFoundError(f"No module named {module!r}", name=module)
        )

    assert "pip install 'x6wd[plot]'" in (msg("calibrate", "matplotlib") or "")
    assert "pip install 'x6wd[gap]'" in (msg("gap", "matplotlib.pyplot") or "")
    assert "pip install 'x6wd[sim]'" in (msg("sim", "matplotlib") or "")
    assert "pip install 'x6wd[sweep]'" in (msg("sweep", "distributed") or "")
    assert msg("sim", "yaml") is None  # not an extra's: the real error stands
