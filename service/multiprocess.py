"""Several server processes on one port, each with its own ``SO_REUSEPORT`` socket.

uvicorn's own ``--workers`` mode shares one listening socket among its
processes; the first process to wake takes every connection of a burst, so a
few keep-alive clients (vehicles, a proxy's pool) all end up on one process
while the others idle. Localizations run one at a time per process, so that
wastes cores.

Here each server process gets a listening socket of its own, all bound to the
same address with ``SO_REUSEPORT``: the kernel hashes each new connection to
one of them, which spreads connections evenly over the processes.

Supervision policy
------------------
The parent process only supervises, it serves nothing:

* it binds the sockets itself (a busy port is reported before any process
  starts) and keeps them open, so a socket is never left without a server;
* a process that exits before it has started serving (the application or its
  database cannot start) stops the whole server: the others are terminated and
  :func:`serve` raises :class:`WorkerStartError`. One killed by a signal while
  starting (an out-of-memory kill, an operator's ``kill``) says nothing about
  the application and is started again, up to ``MAX_START_KILLS`` times in a row;
* a process that ends later (a crash, an out-of-memory kill) is logged as an
  error and replaced by a new one on the same socket; connections the kernel
  queued on that socket meanwhile are answered by the new process. If the
  replacement cannot start, the server stops as above;
* SIGTERM or SIGINT to the parent is passed on as SIGTERM to every server
  process (a graceful uvicorn shutdown: running requests finish), which are
  killed if they have not ended after ``shutdown_timeout_s``.
"""

from __future__ import annotations

import logging
import multiprocessing
import multiprocessing.connection
import os
import signal
import socket
import sys
import time
from dataclasses import dataclass, field

import uvicorn

log = logging.getLogger("service.multiprocess")

#: Exit status of a server process whose application did not start (uvicorn's).
STARTUP_FAILURE = 3
#: Times in a row a server process may be killed by a signal before it starts
#: serving before the server gives up (a process killed at every start would
#: otherwise be restarted for ever).
MAX_START_KILLS = 3

_spawn = multiprocessing.get_context("spawn")


class WorkerStartError(RuntimeError):
    """A server process ended before it started serving."""


def reuseport_supported() -> bool:
    """Whether the kernel spreads connections over ``SO_REUSEPORT`` sockets (Linux)."""
    return sys.platform.startswith("linux") and hasattr(socket, "SO_REUSEPORT")


def bind_reuseport(host: str, port: int, count: int, backlog: int = 2048) -> list[socket.socket]:
    """Bind ``count`` listening sockets to ``host:port`` with ``SO_REUSEPORT``.

    Parameters
    ----------
    host : str
        Address to listen on (IPv6 when it contains a colon).
    port : int
        TCP port; 0 picks a free one, which all sockets then share.
    count : int
        Number of sockets, one per server process.
    backlog : int
        Listen queue length of each socket (uvicorn's default).

    Returns
    -------
    list of socket.socket
        Listening, inheritable sockets.

    Raises
    ------
    OSError
        When the address cannot be bound (the port is busy, the address is not local).
    """
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    sockets: list[socket.socket] = []
    try:
        for _ in range(count):
            sock = socket.socket(family, socket.SOCK_STREAM)
            sockets.append(sock)
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEPORT, 1)
            sock.bind((host, port))
            port = sock.getsockname()[1]
            sock.listen(backlog)
            sock.set_inheritable(True)
    except OSError:
        for sock in sockets:
            sock.close()
        raise
    return sockets


class _Server(uvicorn.Server):
    """A uvicorn server that tells its parent once it accepts connections."""

    def __init__(self, config: uvicorn.Config, ready: multiprocessing.connection.Connection) -> None:
        super().__init__(config)
        self._ready = ready

    async def startup(self, sockets: list[socket.socket] | None = None) -> None:
        await super().startup(sockets=sockets)
        if self.started:
            self._ready.send(os.getpid())
            self._ready.close()


def _child(config: uvicorn.Config, sock: socket.socket, ready: multiprocessing.connection.Connection) -> None:
    config.configure_logging()
    server = _Server(config, ready)
    try:
        server.run(sockets=[sock])
    except KeyboardInterrupt:
        pass
    if not server.started:
        sys.exit(STARTUP_FAILURE)


@dataclass
class _Slot:
    index: int
    sock: socket.socket
    process: multiprocessing.process.BaseProcess | None = None
    ready: multiprocessing.connection.Connection | None = None
    started: bool = False
    restarts: int = 0
    start_kills: int = 0
    started_at: float = field(default=0.0)


class Supervisor:
    """Start, watch and stop the server processes; see the module docstring for the policy.

    Parameters
    ----------
    config : uvicorn.Config
        Configuration of every server process (its ``app`` an import string,
        since it is loaded in each process).
    sockets : list of socket.socket
        One listening socket per server process, from :func:`bind_reuseport`.
    shutdown_timeout_s : float
        How long the processes get to finish after SIGTERM before they are
        killed, seconds.
    """

    def __init__(self, config: uvicorn.Config, sockets: list[socket.socket], shutdown_timeout_s: float = 30.0):
        self.config = config
        self.slots = [_Slot(i, s) for i, s in enumerate(sockets)]
        self.shutdown_timeout_s = shutdown_timeout_s
        self._stop_signal: int | None = None

    def _start(self, slot: _Slot) -> None:
        receive, send = _spawn.Pipe(duplex=False)
        process = _spawn.Process(target=_child, args=(self.config, slot.sock, send),
                                 name=f"lanemap-server-{slot.index}", daemon=False)  # fmt: skip
        process.start()
        send.close()
        slot.process, slot.ready, slot.started, slot.started_at = process, receive, False, time.monotonic()

    def _on_signal(self, signum: int, frame: object) -> None:
        self._stop_signal = signum

    def run(self) -> None:
        """Serve until SIGTERM/SIGINT; raise :class:`WorkerStartError` if a process cannot start."""
        previous = {s: signal.signal(s, self._on_signal) for s in (signal.SIGTERM, signal.SIGINT)}
        log.info("Started parent process [%d]: %d server processes, each with its own SO_REUSEPORT socket",
                 os.getpid(), len(self.slots))  # fmt: skip
        try:
            for slot in self.slots:
                self._start(slot)
            self._watch()
        finally:
            self._stop_all()
            for s, handler in previous.items():
                signal.signal(s, handler)
            for slot in self.slots:
                slot.sock.close()

    def _watch(self) -> None:
        while self._stop_signal is None:
            waitables: list = []
            for slot in self.slots:
                waitables.append(slot.process.sentinel)
                if not slot.started:
                    waitables.append(slot.ready)
            multiprocessing.connection.wait(waitables, timeout=0.5)
            if self._stop_signal is not None:
                break
            for slot in self.slots:
                if not slot.started and slot.ready.poll():
                    try:
                        slot.ready.recv()
                        slot.started, slot.start_kills = True, 0
                    except EOFError:
                        pass  # it ended before it started: handled below
                if slot.process.is_alive():
                    continue
                code = slot.process.exitcode
                if not slot.started and code is not None and code < 0 and slot.start_kills < MAX_START_KILLS:
                    slot.start_kills += 1
                    log.error("server process %d (pid %d) ended with exit code %s before it started serving; "
                              "starting a new one", slot.index, slot.process.pid, code)  # fmt: skip
                    self._start(slot)
                    continue
                if not slot.started:
                    raise WorkerStartError(
                        f"server process {slot.index} (pid {slot.process.pid}) ended with exit code {code} "
                        "before it started serving; its log is above"
                    )
                slot.restarts += 1
                log.error("server process %d (pid %d) ended with exit code %s after %.0f s; starting a new one "
                          "(restart %d)", slot.index, slot.process.pid, code, time.monotonic() - slot.started_at,
                          slot.restarts)  # fmt: skip
                self._start(slot)
        log.info("Received %s: stopping %d server processes", signal.Signals(self._stop_signal).name,
                 len(self.slots))  # fmt: skip

    def _stop_all(self) -> None:
        live = [s.process for s in self.slots if s.process is not None and s.process.is_alive()]
        for process in live:
            try:
                os.kill(process.pid, signal.SIGTERM)
            except ProcessLookupError:
                pass
        deadline = time.monotonic() + self.shutdown_timeout_s
        for process in live:
            process.join(max(0.0, deadline - time.monotonic()))
            if process.is_alive():
                log.warning("server process pid %d did not stop in %.0f s: killing it", process.pid,
                            self.shutdown_timeout_s)  # fmt: skip
                process.kill()
                process.join(5)
        for slot in self.slots:
            if slot.ready is not None:
                slot.ready.close()


def serve(config: uvicorn.Config, sockets: list[socket.socket], shutdown_timeout_s: float = 30.0) -> None:
    """Run one server process per socket under a :class:`Supervisor` until SIGTERM/SIGINT.

    Raises
    ------
    WorkerStartError
        When a server process ends before it started serving.
    """
    Supervisor(config, sockets, shutdown_timeout_s).run()
