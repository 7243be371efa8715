"""Command-line options shared by the service processes (tracker, mapper, camera, poses).

The processes exchange frames, poses and map snapshots over Zenoh; every one of them takes
the same session and transport options so a deployment is described the same way everywhere.
"""

from __future__ import annotations

import argparse
import ctypes
import logging
import math
import threading
from collections.abc import Callable, Sequence
from functools import partial
from pathlib import Path
from typing import Protocol

import torch
import zenoh

from dimslam.common import entry
from dimslam.common.config import PRESETS, SlamConfig, device_for
from dimslam.common.entry import add_verbosity
from dimslam.common.errors import DimslamError
from dimslam.common.net.transport import Keys, Stop, TransportConfig, open_session
from dimslam.common.options import add_config_arguments, apply_overrides, overrides_from_args

log = logging.getLogger(__name__)

DEFAULT_SESSION = "default"


def add_transport_options(p: argparse.ArgumentParser) -> None:
    """Session namespace and Zenoh endpoints (design.md section 1, zenoh.md)."""
    g = p.add_argument_group("transport")
    g.add_argument(
        "--session",
        default=DEFAULT_SESSION,
        help="namespace of every key (dimslam/<session>/...) so several runs can share a network "
        f"(default: {DEFAULT_SESSION})",
    )
    g.add_argument(
        "--connect",
        action="append",
        default=[],
        metavar="ENDPOINT",
        help="zenoh endpoint to connect to, e.g. tcp/10.0.0.2:7450 (repeatable)",
    )
    g.add_argument(
        "--listen",
        action="append",
        default=[],
        metavar="ENDPOINT",
        help="zenoh endpoint to listen on (repeatable; default: loopback only)",
    )
    g.add_argument(
        "--zenoh-config",
        type=Path,
        metavar="FILE",
        help="zenoh JSON5 configuration file; --connect/--listen are applied on top",
    )
    add_verbosity(p)


def map_lag_rounds(text: str) -> int:
    """`--map-lag ROUNDS`: mapping rounds the tracker may run ahead of the map, 0 or more."""
    value = int(text)
    if value < 0:
        raise argparse.ArgumentTypeError(f"must be 0 or more, got {text}")
    return value


# ---------------------------------------------------------------------------------------------
# synth


HEAP_TRIM_S = 10.0
"""How often a tracker or mapper gives the free memory of glibc's heaps back (`trim_heap`)."""
TICK_S = 0.25
"""Longest a client's wait lasts before the stop event is checked again (how fast a signal is
noticed)."""


def positive_int(text: str) -> int:
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be at least 1, got {text}")
    return value


def positive_rate(text: str) -> float:
    """A frame rate: a positive number of frames per second."""
    value = float(text)
    if not (math.isfinite(value) and value > 0):
        raise argparse.ArgumentTypeError(f"must be a positive frame rate, got {text}")
    return value


def positive_seconds(text: str) -> float:
    value = float(text)
    if not (math.isfinite(value) and value > 0):
        raise argparse.ArgumentTypeError(f"must be a positive number of seconds, got {text}")
    return value


def log_peer(role: str, alive: bool) -> None:
    if role in ("tracker", "mapper"):
        log.info("%s %s", role, "is up" if alive else "went away")


def add_compute_options(p: argparse.ArgumentParser) -> None:
    """Where a process computes: one GPU, or the CPU with its own thread budget."""
    g = p.add_argument_group("compute")
    g.add_argument(
        "--gpu",
        type=int,
        default=None,
        metavar="N",
        help="run on cuda:N; without CUDA the process says so once and uses the CPU",
    )
    g.add_argument(
        "--threads",
        type=int,
        default=None,
        help="CPU threads for this process (default: torch's choice), so two processes "
        "on one machine do not fight over cores",
    )


def add_slam_options(p: argparse.ArgumentParser, default_preset: str = "cpu") -> None:
    """`--preset` plus one `--section.field` override per setting."""
    p.add_argument(
        "--preset",
        choices=sorted(PRESETS),
        default=default_preset,
        help=f"settings (default: {default_preset}); tracker and mapper must use the same",
    )
    add_config_arguments(p, SlamConfig(), "settings")


def slam_config(args: argparse.Namespace) -> SlamConfig:
    """The preset named by `--preset` with the user's per-field overrides applied."""
    try:
        return apply_overrides(PRESETS[args.preset], overrides_from_args(args))
    except ValueError as e:
        raise DimslamError(str(e)) from None


def transport_config(args: argparse.Namespace) -> TransportConfig:
    """The transport options parsed by `add_transport_options`."""
    return TransportConfig(
        session=args.session,
        connect=tuple(args.connect),
        listen=tuple(args.listen),
        zenoh_config=args.zenoh_config,
    )


def compute_device(args: argparse.Namespace) -> torch.device:
    """`--gpu N` as `cuda:N` (the CPU, said once, without CUDA); `--threads` applied."""
    if args.threads:
        torch.set_num_threads(args.threads)
    return device_for(f"cuda:{args.gpu}" if args.gpu is not None else "cpu")


class Service(Protocol):
    """A process loop: `run()` until the stream ends or a stop signal, then `close()`."""

    def run(self) -> int: ...

    def close(self) -> None: ...


def add_process_options(p: argparse.ArgumentParser) -> None:
    """What every SLAM process takes besides its own options: compute, transport, settings."""
    add_compute_options(p)
    add_transport_options(p)
    add_slam_options(p)


Build = Callable[[argparse.Namespace, SlamConfig, torch.device, zenoh.Session, Keys, Stop], Service]
"""Builds a process's loop from its arguments, settings, device, session, keys and stop event."""


def trim_heap() -> bool:
    """Give the free pages of glibc's heaps back to the system (`malloc_trim`): True if some
    were; False also where the C library is not glibc.

    Every dimslam process keeps freed blocks in the heap (`dimslam.common`: the mapper's
    gradients are not page-faulted in again each iteration), and messages arrive on zenoh's
    threads, each allocating from a heap of its own: under 100 000 hostile messages per key a
    tracker's private memory grew 240-270 MiB (docs/reliability.md). Trimmed every
    `HEAP_TRIM_S`, a mapper faults its gradients in again once per period, not per
    iteration; giving up the heap setting instead cost mapping iterations 30-75 %."""
    try:
        return bool(ctypes.CDLL("libc.so.6").malloc_trim(0))
    except (OSError, AttributeError):
        return False


def _trim_heap_until(stop: Stop) -> None:
    """`trim_heap` every `HEAP_TRIM_S` on a thread of its own, until the stop event."""

    def loop() -> None:
        while not stop.event.wait(HEAP_TRIM_S):
            trim_heap()

    threading.Thread(target=loop, name="trim-heap", daemon=True).start()


def run_service(
    args: argparse.Namespace,
    role: str,
    build: Build,
    flush: Callable[[argparse.Namespace, Service], None],
) -> int:
    """Open the session, build the process's loop, run it, flush its outputs, exit cleanly.

    SIGINT/SIGTERM set the stop event: the loop finishes its current step, `flush` writes the
    outputs, the liveliness token is undeclared and the `with` block closes the session, so
    the process exits within a few seconds and never hangs (zenoh.md trap 1).
    """
    cfg = slam_config(args)
    device = compute_device(args)
    transport = transport_config(args)
    stop = Stop()
    _trim_heap_until(stop)
    with stop.on_signals(), open_session(transport, role) as session:
        service = build(args, cfg, device, session, Keys(transport.session), stop)
        log.info("%s up in session %r on %s", role, transport.session, device)
        try:
            return service.run()
        finally:
            flush(args, service)
            service.close()


def service_main(
    parser: argparse.ArgumentParser,
    role: str,
    build: Build,
    flush: Callable[[argparse.Namespace, Service], None],
    argv: Sequence[str] | None = None,
) -> int:
    """Entry point of a SLAM process: parse `argv` (`parser` has `add_process_options`), then
    `run_service`; user errors print one line and exit 2."""
    return entry.main(parser, partial(run_service, role=role, build=build, flush=flush), argv)
