"""The control port at the input's end (an outside audit, round 18): a last request without
its newline, from a client that then shuts its sending side (`printf '{"cmd":"stop"}' | nc`),
was dropped in silence while the robot drove on. It is now carried out and answered."""

from __future__ import annotations

import json
import socket

import pytest

from tests.test_server import TOKEN, RecordingBackend, loop_thread, served  # noqa: F401 (fixtures)
from x6wd.app.server import ControlServer


@pytest.mark.parametrize("ending", [b"", b"\n", b"  "], ids=["bare", "newline", "spaces"])
def test_a_stop_at_the_input_s_end_is_carried_out_and_answered(
    served: tuple[ControlServer, RecordingBackend],  # noqa: F811
    ending: bytes,
) -> None:
    srv, backend = served
    with socket.create_connection(("127.0.0.1", srv.port), timeout=5) as s:
        s.sendall(b'{"id":1,"cmd":"stop"}' + ending)
        s.shutdown(socket.SHUT_WR)  # nothing more comes: the request's end is the input's
        with s.makefile("rb") as f:
            lines = [json.loads(raw) for raw in f if raw.strip()]
    replies = [r for r in lines if r.get("id") == 1]
    assert replies and replies[0]["ok"] is True, lines
    assert ("stop", None) in backend.calls, backend.calls


def test_a_cut_request_at_the_input_s_end_gets_an_error_not_silence(
    served: tuple[ControlServer, RecordingBackend],  # noqa: F811
) -> None:
    srv, backend = served
    with socket.create_connection(("127.0.0.1", srv.port), timeout=5) as s:
        s.sendall(b'{"id":2,"cmd":"st')
        s.shutdown(socket.SHUT_WR)
        with s.makefile("rb") as f:
            lines = [json.loads(raw) for raw in f if raw.strip()]
    errors = [r for r in lines if r.get("ok") is False]
    assert errors and errors[0]["error"]["code"] == "bad_request", lines
    assert not backend.calls
    assert TOKEN  # (the fixture's server has a token: stop needs none)


def test_a_stop_without_its_newline_is_not_held_by_the_client_s_back_off(
    loop_thread,  # noqa: F811
) -> None:
    # a review (round 18): after a wrong token the connection waits auth_fail_delay_s before
    # its next line is read; a stop with its newline goes to the motors at once meanwhile,
    # one without (the input's end) waited out the back-off
    import time

    from tests.test_server import start_server

    backend = RecordingBackend()
    srv = start_server(loop_thread, backend, token=TOKEN.encode(), auth_fail_delay_s=2.0)
    try:
        with socket.create_connection(("127.0.0.1", srv.port), timeout=5) as s:
            s.sendall(b'{"id":1,"cmd":"auth","token":"wrong-token"}\n')
            with s.makefile("rb") as f:
                assert json.loads(f.readline())["ok"] is False  # the back-off begins
                t0 = time.monotonic()
                s.sendall(b'{"id":2,"cmd":"stop"}')
                s.shutdown(socket.SHUT_WR)
                while ("stop", None) not in backend.calls and time.monotonic() - t0 < 5.0:
                    time.sleep(0.01)
                took_s = time.monotonic() - t0
                replies = [json.loads(raw) for raw in f if raw.strip()]
        assert ("stop", None) in backend.calls and took_s < 1.0, (took_s, backend.calls)
        assert [r.get("id") for r in replies if r.get("id") == 2], replies  # answered too
    finally:
        loop_thread.run(srv.close())
