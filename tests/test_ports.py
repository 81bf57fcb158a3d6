"""Ports for the servers the tests and the integration test start: chosen where no
other process's connection can take them, and a server that finds its port taken
anyway starts on another."""

import socket
import subprocess
import sys
from pathlib import Path

import pytest

from minetwin import harness, ports
from minetwin.harness import ServerProcess, prepare_state

MINETWIN = [sys.executable, "-m", "minetwin.cli"]


def test_free_ports_are_distinct_bindable_and_below_the_ephemeral_range():
    low, high = (int(v) for v in Path("/proc/sys/net/ipv4/ip_local_port_range").read_text().split())
    handed_out = [ports.free_port() for _ in range(300)]
    assert len(set(handed_out)) == len(handed_out)
    for port in handed_out[-20:]:
        with socket.socket() as probe:
            probe.bind(("127.0.0.1", port))
    if low - ports.LOWEST_PORT >= 1000:
        assert all(ports.LOWEST_PORT <= port < low for port in handed_out)
    else:  # the kernel's own choice
        assert all(low <= port <= high for port in handed_out)


def _occupied():
    busy = socket.socket()
    busy.bind(("127.0.0.1", ports.free_port()))
    busy.listen()
    return busy


def test_serve_800xa_on_a_taken_port_says_so_in_one_line(tmp_path):
    state = prepare_state(tmp_path / "state")
    with _occupied() as busy:
        port = busy.getsockname()[1]
        done = subprocess.run(MINETWIN + ["serve-800xa", "--host", "127.0.0.1", "--port", str(port),
                                          "--state-dir", str(state["server_state"])],
                              capture_output=True, text=True, timeout=120)
    assert done.returncode == 1
    assert f"cannot serve on 127.0.0.1:{port}" in done.stderr
    assert "address already in use" in done.stderr
    assert "Traceback" not in done.stderr


def test_a_server_whose_free_port_was_taken_starts_on_another(tmp_path, monkeypatch):
    state = prepare_state(tmp_path / "state")
    with _occupied() as busy:
        taken = busy.getsockname()[1]
        choices = iter([taken])
        monkeypatch.setattr(harness, "free_port", lambda: next(choices, None) or ports.free_port())
        server = ServerProcess(tmp_path, state)
        try:
            assert server.port != taken
            assert server.url == f"opc.tcp://127.0.0.1:{server.port}/minetwin/"
            assert server.proc.poll() is None
        finally:
            server.stop()
    log = (tmp_path / "server.log").read_text()
    assert log.count("address already in use") == 1


def test_a_server_asked_for_a_taken_port_does_not_move(tmp_path):
    state = prepare_state(tmp_path / "state")
    with _occupied() as busy:
        taken = busy.getsockname()[1]
        with pytest.raises(RuntimeError, match=f"cannot serve on 127.0.0.1:{taken}"):
            ServerProcess(tmp_path, state, port=taken)
