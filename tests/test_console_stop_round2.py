"""A second outside audit of the console: ``[console] hostnames`` entries with ``_`` (as
``socket.gethostname()`` may say) were accepted by the configuration but every request with
that Host got HTTP 421. The real daemon (``sim://`` devices) with its console on 127.0.0.1."""

from __future__ import annotations

import asyncio
from collections.abc import Iterator
from pathlib import Path

import aiohttp
import pytest

from tests.test_console import console_config, daemon_with, has_fix
from tests.test_daemon import Running, wait_for
from x6wd.app.console.server import allowed_host
from x6wd.core.config import ConsoleConfig
from x6wd.core.errors import ConfigError


@pytest.fixture(scope="module")
def robot(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Running]:
    cfg = console_config(tmp_path_factory.mktemp("round2"), hostnames=("my_robot",))
    with daemon_with(cfg) as r:
        wait_for(lambda: has_fix(r), 30, "a fix")
        yield r


# -- 4: host names with "_" -----------------------------------------------------------------------
def test_a_host_name_with_an_underscore_is_a_host_name() -> None:
    names = frozenset({"localhost", "my_robot"})
    for host in ("my_robot", "MY_ROBOT:18602", "my_robot.local_net"):
        assert allowed_host(host, names | {"my_robot.local_net"}), host
    assert not allowed_host("other_robot", names)
    for bad in ("my robot", "robot.lan:80", "http://robot", "robot.lan.", "-robot", ""):
        with pytest.raises(ConfigError, match=r"console\.hostnames") as err:
            ConsoleConfig(hostnames=(bad,))
        assert repr(bad) in str(err.value)
    ConsoleConfig(hostnames=("my_robot", "robot.lan", "10.0.0.7"))


@pytest.mark.integration
def test_the_console_answers_a_configured_name_with_an_underscore(robot: Running) -> None:
    console = robot.daemon.console
    assert console is not None

    async def program() -> None:
        async with aiohttp.ClientSession() as s:
            for host in ("my_robot", f"my_robot:{console.port}"):
                async with s.get(console.url, headers={"Host": host}) as resp:
                    assert resp.status == 200, host

    asyncio.run(program())


@pytest.mark.integration
def test_a_malformed_host_name_in_the_config_is_exit_2_naming_the_key(tmp_path: Path) -> None:
    from tests.test_tls_required import run_x6wd, write_config

    config = write_config(tmp_path, console={"enabled": True, "hostnames": ["robot lan"]})
    proc = run_x6wd(config)
    assert proc.returncode == 2, proc.stderr
    line = proc.stderr.strip()
    assert "\n" not in line and "console.hostnames: 'robot lan' is not a host name" in line
