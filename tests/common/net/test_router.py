"""`dimslam-router` and the deploy/zenoh configurations, as an operator uses them.

The router runs as a real subprocess; clients are zenoh sessions in this process, built from the
deploy files with their placeholders filled in the way deploy/README.md tells a user to.
"""

from __future__ import annotations

import configparser
import json
import queue
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
import zenoh
from repo import REPO

from dimslam.common.net import router
from dimslam.common.net.launch import loopback_endpoints
from dimslam.common.net.transport import (
    SHARED_MEMORY,
    TransportConfig,
    default_endpoints,
    pose_publisher,
    pose_subscriber,
    zenoh_config,
)

pytestmark = pytest.mark.integration

DEPLOY = REPO / "deploy"
ZENOH_FILES = sorted((DEPLOY / "zenoh").glob("*.json5"))
START_TIMEOUT = 120.0
"""Seconds for the router to start: its imports alone take ~1.5 s on a quiet 2-core machine,
over 20 s under `nice` beside two SLAM runs."""
STOP_TIMEOUT = 60.0
MESSAGE_TIMEOUT = 60.0


class RouterProcess:
    """`python -m dimslam.common.net.router ARGS` with its stderr collected by a reader thread."""

    def __init__(self, *args: str) -> None:
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "dimslam.common.net.router", *args],
            stderr=subprocess.PIPE,
            text=True,
        )
        self.lines: list[str] = []
        self._listening = threading.Event()
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self) -> None:
        for line in self.proc.stderr:
            self.lines.append(line)
            if "listening on" in line:
                self._listening.set()
        self._listening.set()  # EOF: it exited; wait_listening reports why

    def wait_listening(self) -> None:
        """Return once the router says it listens (client sessions need it up: zenoh.md)."""
        assert self._listening.wait(START_TIMEOUT), "router did not start in time"
        assert self.proc.poll() is None, f"router exited early:\n{self.log}"

    def stop(self, sig: int) -> int:
        """Send `sig` and return the exit status."""
        self.proc.send_signal(sig)
        try:
            return self.proc.wait(STOP_TIMEOUT)
        finally:
            self._reader.join(STOP_TIMEOUT)

    @property
    def log(self) -> str:
        return "".join(self.lines)

    def kill(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait()


@pytest.fixture
def start_router():
    started: list[RouterProcess] = []

    def start(*args: str) -> RouterProcess:
        r = RouterProcess(*args)
        started.append(r)
        r.wait_listening()
        return r

    yield start
    for r in started:
        r.kill()


def deploy_config(name: str, replace: dict[str, str]) -> str:
    """The text of deploy/zenoh/`name` with the placeholders a user edits replaced."""
    text = (DEPLOY / "zenoh" / name).read_text()
    for old, new in replace.items():
        assert old in text, f"{name} no longer contains {old!r}"
        text = text.replace(old, new)
    return text


def send_through(sender: zenoh.Session, receiver: zenoh.Session, payload: bytes) -> bytes:
    """Publish `payload` from `sender` once `receiver` subscribes; return what it received."""
    key = "dimslam/test/@v1/through-router"
    received: queue.Queue[bytes] = queue.Queue()
    sub = receiver.declare_subscriber(key, lambda s: received.put(s.payload.to_bytes()))
    pub = sender.declare_publisher(key)
    matched = threading.Event()
    listener = pub.declare_matching_listener(lambda status: status.matching and matched.set())
    # The listener reports changes only: the match may predate it.
    if pub.matching_status.matching:
        matched.set()
    assert matched.wait(MESSAGE_TIMEOUT), "the subscriber never matched through the router"
    pub.put(payload)
    try:
        return received.get(timeout=MESSAGE_TIMEOUT)
    finally:
        listener.undeclare()
        pub.undeclare()
        sub.undeclare()


# -- the configuration files ------------------------------------------------------------------


def test_deploy_has_the_documented_zenoh_files():
    names = {p.name for p in ZENOH_FILES}
    assert names == {
        "one-host.json5",
        "router.json5",
        "client-tracker.json5",
        "client-mapper.json5",
        "tls-router.json5",
        "tls-client.json5",
    }


@pytest.mark.parametrize("path", ZENOH_FILES, ids=lambda p: p.name)
def test_zenoh_file_parses_with_its_intended_mode(path):
    conf = zenoh.Config.from_file(path)  # TLS paths are only checked when a session opens
    mode = json.loads(conf.get_json("mode"))
    expected = "router" if "router" in path.name else "client" if "client" in path.name else "peer"
    assert mode == expected
    assert json.loads(conf.get_json("scouting/multicast/enabled")) is False


def test_one_host_file_matches_the_built_in_defaults():
    conf = zenoh.Config.from_file(DEPLOY / "zenoh" / "one-host.json5")
    _, connect = default_endpoints("camera")  # connects to both tracker and mapper
    assert json.loads(conf.get_json("connect/endpoints")) == connect
    assert json.loads(conf.get_json("listen/endpoints")) == []
    assert json.loads(conf.get_json("transport/shared_memory/enabled")) is SHARED_MEMORY


@pytest.mark.parametrize("path", ZENOH_FILES, ids=lambda p: p.name)
def test_no_config_maps_the_memory_of_another_process(path):
    """Shared memory off in every deploy file and in the built-in defaults: a receiver would
    map the sender's pool, of the sender's size (the fuzzing measured 35-60 MiB of it)."""
    conf = zenoh.Config.from_file(path)
    assert json.loads(conf.get_json("transport/shared_memory/enabled")) is False
    built_in = [zenoh_config(TransportConfig(), "tracker"), router.router_config(None, [])]
    assert all(json.loads(c.get_json("transport/shared_memory/enabled")) is False for c in built_in)


def test_router_config_listens_on_7450_unless_told_otherwise(tmp_path):
    assert router.listen_endpoints(router.router_config(None, [])) == ["tcp/0.0.0.0:7450"]
    bare = tmp_path / "bare.json5"
    bare.write_text('{ mode: "router" }')  # zenoh alone would listen on 7447
    assert router.listen_endpoints(router.router_config(bare, [])) == ["tcp/0.0.0.0:7450"]
    tls = DEPLOY / "zenoh" / "tls-router.json5"
    assert router.listen_endpoints(router.router_config(tls, [])) == ["tls/0.0.0.0:7450"]
    conf = router.router_config(tls, ["tls/127.0.0.1:9", "tcp/127.0.0.1:8"])
    assert router.listen_endpoints(conf) == ["tls/127.0.0.1:9", "tcp/127.0.0.1:8"]
    assert "/etc/dimslam/users.txt" in conf.get_json("transport/auth/usrpwd/dictionary_file")


@pytest.mark.parametrize("role", ["router", "tracker", "mapper"])
def test_systemd_unit_runs_the_right_config_and_stops_cleanly(role):
    unit = configparser.ConfigParser(interpolation=None)
    unit.optionxform = str  # systemd keys are case-sensitive
    unit.read(DEPLOY / "systemd" / f"dimslam-{role}.service")
    service = unit["Service"]
    exec_start = service["ExecStart"].split()
    assert Path(exec_start[0]).name == f"dimslam-{role}"
    config = Path(exec_start[exec_start.index("--zenoh-config") + 1])
    expected = "router.json5" if role == "router" else f"client-{role}.json5"
    assert config.parent == Path("/etc/dimslam") and config.name == expected
    if role != "router":
        assert "--gpu" in exec_start and "--session" in exec_start
    assert service["User"] == "dimslam" and service["Restart"] == "on-failure"
    assert service["KillSignal"] == "SIGTERM" and service["TimeoutStopSec"] == "15"


# -- the router process -----------------------------------------------------------------------


def test_router_joins_two_clients_and_stops_on_sigterm(start_router):
    port = int(loopback_endpoints(1)[0].rsplit(":", 1)[1])
    r = start_router("--listen", f"tcp/127.0.0.1:{port}")
    assert f"listening on tcp/127.0.0.1:{port}" in r.log
    fill = {"ROUTER_HOST:7450": f"127.0.0.1:{port}"}
    tracker = zenoh.Config.from_json5(deploy_config("client-tracker.json5", fill))
    mapper = zenoh.Config.from_json5(deploy_config("client-mapper.json5", fill))
    with zenoh.open(tracker) as a, zenoh.open(mapper) as b:
        assert send_through(a, b, b"pose 42") == b"pose 42"
        assert send_through(b, a, b"map 7") == b"map 7"
    assert r.stop(signal.SIGTERM) == 0, r.log
    assert "router closed" in r.log


def test_poses_sent_while_the_router_was_down_reach_a_client_after(start_router):
    """The pose topic is recoverable (`transport.pose_publisher`): poses the tracker published
    while the router was down reach a client with the next one after both are back, in
    order, none twice."""
    port = int(loopback_endpoints(1)[0].rsplit(":", 1)[1])
    listen = ("--listen", f"tcp/127.0.0.1:{port}")
    r = start_router(*listen)
    fill = {"ROUTER_HOST:7450": f"127.0.0.1:{port}"}
    tracker = zenoh.Config.from_json5(deploy_config("client-tracker.json5", fill))
    client = zenoh.Config.from_json5(deploy_config("client-mapper.json5", fill))
    key = "dimslam/test/@v1/poses"
    received: queue.Queue[bytes] = queue.Queue()
    with zenoh.open(tracker) as a, zenoh.open(client) as b:
        sub = pose_subscriber(b, key, lambda s: received.put(s.payload.to_bytes()))
        pub = pose_publisher(a, key)
        probe = a.declare_publisher(key)  # an advanced publisher has no matching status
        matched = threading.Event()
        listener = probe.declare_matching_listener(lambda st: st.matching and matched.set())
        if probe.matching_status.matching:
            matched.set()
        assert matched.wait(MESSAGE_TIMEOUT), "the client never matched through the router"
        pub.put(b"0")
        assert received.get(timeout=MESSAGE_TIMEOUT) == b"0"
        assert r.stop(signal.SIGKILL) != 0
        for i in range(1, 6):
            pub.put(str(i).encode())  # nobody to route them to
        start_router(*listen)
        # The next pose shows the gap; a subscriber that missed the end of stream would wait.
        # Until the client is back, a pose goes nowhere: send one each second until it comes.
        last = 5
        while received.empty() and last < 5 + MESSAGE_TIMEOUT:
            last += 1
            pub.put(str(last).encode())
            time.sleep(1.0)
        got = [received.get(timeout=MESSAGE_TIMEOUT) for _ in range(last)]
        assert got == [str(i).encode() for i in range(1, last + 1)]
        assert received.empty()
        listener.undeclare()
        for declared in (probe, pub, sub):
            declared.undeclare()


@pytest.mark.parametrize(
    "text, message",
    [
        ('{ mode: "rooter" }', "unknown variant `rooter`"),
        ("{ mode: ", "--zenoh-config"),
        ('{ mode: "client", connect: { endpoints: ["tcp/h:7450"] } }', "the router needs"),
        (None, "No such file"),
    ],
    ids=["bad-value", "bad-syntax", "client-file", "missing"],
)
def test_bad_config_file_exits_2_with_one_line(tmp_path, capsys, text, message):
    path = tmp_path / "router.json5"
    if text is not None:
        path.write_text(text)
    assert router.main(["--zenoh-config", str(path), "-q"]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"error: --zenoh-config {path}") and message in err
    assert err.count("\n") == 1 and ".rs:" not in err


def test_port_taken_exits_2_with_one_line(capsys):
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        assert router.main(["--listen", f"tcp/127.0.0.1:{port}", "-q"]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"error: cannot start the router on tcp/127.0.0.1:{port}")
    assert "Address already in use" in err and err.count("\n") == 1


def test_malformed_listen_endpoint_exits_2_with_one_line(capsys):
    assert router.main(["--listen", "127.0.0.1:7450", "-q"]) == 2  # no protocol
    err = capsys.readouterr().err
    assert err.startswith("error: --listen: Endpoints must be of the form <protocol>/<address>")
    assert err.count("\n") == 1 and ".rs:" not in err


def test_script_reports_a_bad_config_file(tmp_path):
    path = tmp_path / "router.json5"
    path.write_text("{ listen: ")
    exe = Path(sys.executable).parent / "dimslam-router"
    done = subprocess.run(
        [str(exe), "--zenoh-config", str(path)], capture_output=True, text=True, timeout=60
    )
    assert done.returncode == 2
    assert done.stderr.startswith("error: --zenoh-config")


# -- TLS + user/password, with certificates from deploy/make-certs.sh -------------------------


@pytest.fixture(scope="module")
def certs(tmp_path_factory) -> Path:
    if shutil.which("openssl") is None:
        pytest.skip("openssl is not installed")
    out = tmp_path_factory.mktemp("tls")
    subprocess.run(
        ["bash", str(DEPLOY / "make-certs.sh"), str(out), "localhost"],
        check=True,
        capture_output=True,
        timeout=60,
    )
    return out


def test_tls_router_accepts_only_listed_users(start_router, certs, tmp_path):
    users = tmp_path / "users.txt"
    users.write_text("tracker:s3cret\nmapper:an0ther\n")
    router_file = tmp_path / "tls-router.json5"
    router_file.write_text(
        deploy_config(
            "tls-router.json5",
            {"/etc/dimslam/tls": str(certs), "/etc/dimslam/users.txt": str(users)},
        )
    )
    port = int(loopback_endpoints(1)[0].rsplit(":", 1)[1])
    r = start_router("--zenoh-config", str(router_file), "--listen", f"tls/127.0.0.1:{port}")

    def client(user: str, password: str) -> zenoh.Config:
        text = deploy_config(
            "tls-client.json5",
            {
                # The certificate names localhost (make-certs.sh argument); the client checks it.
                "ROUTER_HOST:7450": f"localhost:{port}",
                "/etc/dimslam/tls": str(certs),
                '"dimslam"': json.dumps(user),
                "CHANGE-ME": password,
            },
        )
        conf = zenoh.Config.from_json5(text)
        conf.insert_json5("connect/timeout_ms", "0")  # a refusal must fail now, not in 30 s
        return conf

    with zenoh.open(client("tracker", "s3cret")) as a, zenoh.open(client("mapper", "an0ther")) as b:
        assert send_through(a, b, b"over tls") == b"over tls"
    with pytest.raises(zenoh.ZError):
        zenoh.open(client("tracker", "wrong")).close()
    assert r.stop(signal.SIGINT) == 0, r.log
