"""`dimslam-router`: the Zenoh router that joins the service's processes across machines.

On one host the processes find each other directly (peer mode, `transport.py`). Across
machines each process runs in client mode and connects to one router on a hub machine; the
router forwards every key between them. This program is that router: a Zenoh session opened in
`mode: "router"`, listening, and doing nothing else until SIGINT/SIGTERM. A real `zenohd`
(same protocol) can replace it where one is installed; the deploy/zenoh/*.json5 files work
with either.

Exit status: 0 after SIGINT/SIGTERM, 2 for a bad configuration file or an endpoint it cannot
listen on (port taken, missing certificate, ...), with one line on stderr saying which.
"""

from __future__ import annotations

import argparse
import json
import logging
import re
import sys
import textwrap
from collections.abc import Sequence
from pathlib import Path

import zenoh

from dimslam.common import entry
from dimslam.common.entry import add_verbosity
from dimslam.common.errors import DimslamError
from dimslam.common.net.transport import SHARED_MEMORY, Stop

log = logging.getLogger("dimslam.router")

ROUTER_PORT = 7450
"""The router's port: not 7447, which zenohd and ROS 2's rmw_zenoh use (zenoh.md trap 9)."""
DEFAULT_LISTEN = f"tcp/0.0.0.0:{ROUTER_PORT}"

# Zenoh's errors end with the Rust source location of every layer ("... at /root/.cargo/
# .../unicast.rs:338."): noise to a user, so it is cut from the one-line message.
_RUST_LOCATION = re.compile(r"\s+at \S+\.rs:\d+\.?")
# A wrong value comes back as a Rust Debug dump; keep its message and, for a file, position.
_SERDE_ERROR = re.compile(
    r'(?:JSON error: |Json5Err\()?Message \{ msg: "(.*)", location: Some\(Location \{ '
    r"line: (\d+), column: (\d+) \}\) \}\)?"
)

DESCRIPTION = (
    "Zenoh router for a dimslam service spread over several machines: the tracker, mapper, "
    "camera and poses processes run in client mode (deploy/zenoh/client-*.json5) and connect "
    "to this router, which forwards their messages. Not needed on a single host, where the "
    "processes connect to each other directly. Runs until SIGINT/SIGTERM; a real zenohd can "
    "take its place."
)
EPILOG = (
    "examples:\n"
    "  dimslam-router                                  # listen on all interfaces, port 7450\n"
    "  dimslam-router --listen tcp/10.0.0.1:7450       # one interface only\n"
    "  dimslam-router --zenoh-config /etc/dimslam/tls-router.json5   # TLS + user/password\n"
    "\n"
    "Zenoh's own logs go to stdout with RUST_LOG=info (or debug). See deploy/README.md."
)


def _zenoh_message(error: Exception, position: bool = True) -> str:
    """Zenoh's error text on one line, without its Rust source locations.

    Args:
        error: what zenoh raised.
        position: keep the line and column of a parse error (meaningful for a file, not for
            a command-line value).
    """
    text = _RUST_LOCATION.sub("", str(error))
    text = _SERDE_ERROR.sub(r"\1 (line \2, column \3)" if position else r"\1", text)
    return " ".join(text.split())


def _is_zenoh_default(value: object, key: str) -> bool:
    """Whether `value` is what zenoh puts at `key` when the file does not set it."""
    return value == json.loads(zenoh.Config().get_json(key))


def router_config(config_file: Path | None, listen: Sequence[str]) -> zenoh.Config:
    """The router's Zenoh configuration: the file if given, else defaults; `listen` on top.

    Args:
        config_file: a JSON5 Zenoh configuration (e.g. deploy/zenoh/router.json5), or None.
        listen: endpoints that replace the file's listen endpoints; when empty, the file's own
            are kept, and `DEFAULT_LISTEN` is used if neither names any.

    Returns:
        A configuration in mode "router".

    Raises:
        DimslamError: the file cannot be read or parsed, it configures another mode, or a
            `listen` endpoint is malformed.
    """
    if config_file is None:
        conf = zenoh.Config()
        # Explicit endpoints everywhere: multicast scouting would let any zenoh process on the
        # LAN join the service unasked.
        conf.insert_json5("scouting/multicast/enabled", "false")
        conf.insert_json5("transport/shared_memory/enabled", json.dumps(SHARED_MEMORY))
    else:
        try:
            conf = zenoh.Config.from_file(str(config_file))
        except zenoh.ZError as e:
            raise DimslamError(f"--zenoh-config {config_file}: {_zenoh_message(e)}") from None
        mode = json.loads(conf.get_json("mode"))
        if mode not in (None, "router"):
            # A client's file given to the router by mistake would make it connect to itself
            # and listen nowhere: say so instead.
            raise DimslamError(
                f"--zenoh-config {config_file}: mode is {mode!r}, the router needs 'router' "
                "(client-*.json5 files are for the tracker, mapper, camera and poses)"
            )
    conf.insert_json5("mode", json.dumps("router"))
    if listen:
        try:
            conf.insert_json5("listen/endpoints", json.dumps(list(listen)))
        except zenoh.ZError as e:
            raise DimslamError(f"--listen: {_zenoh_message(e, position=False)}") from None
    elif _is_zenoh_default(json.loads(conf.get_json("listen/endpoints")), "listen/endpoints"):
        # Zenoh's own default is port 7447, taken by zenohd and rmw_zenoh (zenoh.md trap 9).
        conf.insert_json5("listen/endpoints", json.dumps([DEFAULT_LISTEN]))
    return conf


def listen_endpoints(conf: zenoh.Config) -> list[str]:
    """The endpoints a router with configuration `conf` listens on."""
    value = json.loads(conf.get_json("listen/endpoints"))
    if isinstance(value, dict):  # zenoh allows one list per mode
        value = value.get("router") or []
    return list(value)


def _log_link(event: zenoh.LinkEvent) -> None:
    """Log a client connecting or leaving; runs on zenoh's thread, so it stays tiny."""
    link = event.link
    if event.kind == zenoh.SampleKind.PUT:
        log.info("connected: %s (zid %s)", link.dst, link.zid)
    else:
        log.info("disconnected: %s (zid %s)", link.dst, link.zid)


def serve(conf: zenoh.Config, stop: Stop) -> None:
    """Open the router session and keep it open until `stop` is set.

    Raises:
        DimslamError: the session cannot be opened (port taken, missing certificate, ...).
    """
    endpoints = ", ".join(listen_endpoints(conf)) or "no endpoint"
    try:
        session = zenoh.open(conf)
    except zenoh.ZError as e:
        raise DimslamError(f"cannot start the router on {endpoints}: {_zenoh_message(e)}") from None
    with session:
        # Keep a reference: an unreferenced listener is undeclared (zenoh.md trap 4).
        links = session.info.declare_link_events_listener(_log_link)
        log.info("router %s listening on %s", session.info.zid(), endpoints)
        stop.event.wait()
        links.undeclare()
    log.info("router closed")


def build_parser() -> argparse.ArgumentParser:
    """The command line of `dimslam-router`."""
    p = argparse.ArgumentParser(
        prog="dimslam-router",
        # Raw, to keep the examples' layout; so the description is wrapped here.
        description=textwrap.fill(DESCRIPTION, 79),
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument(
        "--listen",
        action="append",
        default=[],
        metavar="ENDPOINT",
        help="endpoint to listen on, e.g. tcp/10.0.0.1:7450 or tls/hub.lab:7450 (repeatable; "
        f"replaces the config file's; default: {DEFAULT_LISTEN})",
    )
    p.add_argument(
        "--zenoh-config",
        type=Path,
        metavar="FILE",
        help="zenoh JSON5 configuration file (TLS, authentication, ...), e.g. "
        "deploy/zenoh/router.json5; --listen is applied on top",
    )
    add_verbosity(p)
    return p


def run(args: argparse.Namespace) -> int:
    """Serve until SIGINT/SIGTERM."""
    zenoh.try_init_log_from_env()
    conf = router_config(args.zenoh_config, args.listen)
    with Stop().on_signals() as stop:
        serve(conf, stop)
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of `dimslam-router`; returns the exit status."""
    return entry.main(build_parser(), run, argv)


if __name__ == "__main__":
    sys.exit(main())
