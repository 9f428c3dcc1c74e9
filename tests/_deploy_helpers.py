"""Real processes for the deployment and fault tests: a private PostgreSQL cluster,
a Dask scheduler with workers, and small file systems.

Everything here starts processes of its own and ends exactly those (by pid or
process group), so the shared PostgreSQL server and other tests running beside
these are never touched.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

from tests._api_helpers import free_port


def _pg_bin() -> Path:
    """The newest PostgreSQL server binaries installed (Debian keeps them off PATH)."""
    candidates = sorted(Path("/usr/lib/postgresql").glob("*/bin/pg_ctl"), key=lambda p: int(p.parts[-3]))
    if candidates:
        return candidates[-1].parent
    found = shutil.which("pg_ctl")
    if found:
        return Path(found).parent
    raise RuntimeError("PostgreSQL server binaries (initdb, pg_ctl) are not installed")


class PrivatePostgres:
    """A throw-away PostgreSQL cluster on its own port, for tests that stop and start it.

    Run as root, the cluster belongs to the ``postgres`` OS user (PostgreSQL refuses
    to run as root) and commands go through ``runuser``.
    """

    def __init__(self) -> None:
        self.bin = _pg_bin()
        self.root = Path(tempfile.mkdtemp(prefix="lanemap-pg-"))
        self.data = self.root / "data"
        self.log = self.root / "server.log"
        self.port = free_port()
        self.as_root = os.geteuid() == 0
        if self.as_root:
            shutil.chown(self.root, "postgres", "postgres")
        self._run("initdb", "-D", str(self.data), "-U", "postgres", "--auth=trust", "-E", "UTF8",
                  "--no-sync", "--no-instructions")  # fmt: skip

    @property
    def url(self) -> str:
        return f"postgresql://postgres@127.0.0.1:{self.port}/postgres"

    def _run(self, tool: str, *args: str, check: bool = True) -> subprocess.CompletedProcess:
        cmd = [str(self.bin / tool), *args]
        if self.as_root:
            cmd = ["runuser", "-u", "postgres", "--", *cmd]
        out = subprocess.run(cmd, capture_output=True, text=True, timeout=120, cwd=self.root)
        if check and out.returncode != 0:
            raise RuntimeError(f"{tool} failed ({out.returncode}):\n{out.stdout}\n{out.stderr}\n{self.server_log()}")
        return out

    def server_log(self) -> str:
        try:
            return self.log.read_text(errors="replace")[-4000:]
        except OSError:
            return ""

    def start(self) -> None:
        # fsync off: a server killed here loses nothing the OS holds. Commits stay synchronous:
        # with them asynchronous an immediate stop lost a marking committed seconds before, which
        # read as the server's 404 once PostgreSQL was back.
        opts = (f"-p {self.port} -k {self.root} -c listen_addresses=127.0.0.1 -c fsync=off "
                "-c full_page_writes=off -c max_connections=40")  # fmt: skip
        self._run("pg_ctl", "-D", str(self.data), "-l", str(self.log), "-o", opts, "-w", "-t", "60", "start")

    def stop(self, mode: str = "fast") -> None:
        """Stop the server (``fast``: a clean shutdown; ``immediate``: as a crash), and return
        only once it is down: a ``fast`` stop that has not ended within a minute (on a loaded
        machine) is made ``immediate``."""
        out = self._run("pg_ctl", "-D", str(self.data), "-m", mode, "-w", "-t", "60", "stop", check=False)
        if self.running() and mode != "immediate":
            self._run("pg_ctl", "-D", str(self.data), "-m", "immediate", "-w", "-t", "60", "stop", check=False)
        if self.running():
            raise RuntimeError(f"PostgreSQL did not stop ({out.returncode}):\n{out.stdout}\n{out.stderr}\n"
                               f"{self.server_log()}")

    def running(self) -> bool:
        return self._run("pg_ctl", "-D", str(self.data), "status", check=False).returncode == 0

    def destroy(self) -> None:
        if self.data.exists():
            self.stop("immediate")
        shutil.rmtree(self.root, ignore_errors=True)


# ------------------------------------------------------------------------- Dask


def _dask_cli() -> str:
    path = Path(sys.executable).parent / "dask"
    if not path.exists():
        raise RuntimeError(f"the dask command is not installed beside {sys.executable}")
    return str(path)


@dataclass
class DaskProcesses:
    """A ``dask scheduler`` and ``dask worker`` processes, each in its own process group."""

    address: str
    root: Path
    scheduler: subprocess.Popen
    workers: list[subprocess.Popen] = field(default_factory=list)

    def log(self) -> str:
        return "\n".join(f"--- {p.name}\n{p.read_text(errors='replace')[-3000:]}" for p in sorted(self.root.glob("*.log")))

    def n_workers(self) -> int:
        from distributed import Client

        with Client(self.address, timeout="10s") as c:
            return len(c.scheduler_info(n_workers=-1)["workers"])

    def task_counts(self, prefix: str) -> dict[str, int]:
        """How many tasks of function ``prefix`` entered each state on the scheduler so far
        (``processing`` more often than ``memory``: some ran again after a worker was lost)."""
        from distributed import Client

        def count(dask_scheduler, prefix=prefix):
            tp = dask_scheduler.task_prefixes.get(prefix)
            return {} if tp is None else {k: int(v) for k, v in tp.state_counts.items()}

        with Client(self.address, timeout="10s") as c:
            return c.run_on_scheduler(count)

    def tasks_done(self, prefix: str) -> int:
        """How many tasks of function ``prefix`` the cluster has finished so far."""
        return self.task_counts(prefix).get("memory", 0)

    def kill_worker(self, i: int) -> None:
        """SIGKILL worker ``i`` and its nanny, as a crashed machine would go."""
        with contextlib.suppress(ProcessLookupError):
            os.killpg(self.workers[i].pid, signal.SIGKILL)
        self.workers[i].wait(10)

    def stop(self) -> None:
        for p in [*self.workers, self.scheduler]:
            if p.poll() is None:
                with contextlib.suppress(ProcessLookupError):
                    os.killpg(p.pid, signal.SIGTERM)
        deadline = time.monotonic() + 10
        for p in [*self.workers, self.scheduler]:
            try:
                p.wait(max(0.1, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                with contextlib.suppress(ProcessLookupError):
                    os.killpg(p.pid, signal.SIGKILL)
                p.wait(5)


def _spawn(args: list[str], log: Path, env: dict[str, str]) -> subprocess.Popen:
    with open(log, "wb") as fh:
        return subprocess.Popen(args, stdout=fh, stderr=subprocess.STDOUT, env=env, cwd=log.parent,
                                start_new_session=True)  # fmt: skip


def start_dask(root: Path, n_workers: int = 2, timeout: float = 60.0) -> DaskProcesses:
    """Start ``dask scheduler`` and ``n_workers`` single-threaded ``dask worker`` processes.

    The workers import lanemap from this checkout (``PYTHONPATH``), as deployed
    workers import the installed package. Stop them with :meth:`DaskProcesses.stop`.
    """
    root = Path(root)
    root.mkdir(parents=True, exist_ok=True)
    dask = _dask_cli()
    env = dict(os.environ)
    repo = str(Path(__file__).resolve().parents[1])
    env["PYTHONPATH"] = os.pathsep.join(p for p in (repo, env.get("PYTHONPATH", "")) if p)
    env.update(OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1", MKL_NUM_THREADS="1")
    port = free_port()
    address = f"tcp://127.0.0.1:{port}"
    scheduler = _spawn([dask, "scheduler", "--host", "127.0.0.1", "--port", str(port), "--no-dashboard"],
                       root / "scheduler.log", env)  # fmt: skip
    procs = DaskProcesses(address, root, scheduler)
    try:
        for i in range(n_workers):
            procs.workers.append(_spawn(
                [dask, "worker", address, "--nthreads", "1", "--nworkers", "1", "--host", "127.0.0.1",
                 "--no-dashboard", "--local-directory", str(root / f"worker-{i}"), "--name", f"w{i}"],
                root / f"worker-{i}.log", env))  # fmt: skip
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            for p in [scheduler, *procs.workers]:
                if p.poll() is not None:
                    raise RuntimeError(f"a dask process exited with {p.returncode}:\n{procs.log()}")
            try:
                if procs.n_workers() == n_workers:
                    return procs
            except (OSError, TimeoutError):
                pass
            time.sleep(0.3)
        raise RuntimeError(f"the Dask cluster did not come up within {timeout} s:\n{procs.log()}")
    except BaseException:
        procs.stop()
        raise


# ------------------------------------------------------------------------- file systems


def can_sudo() -> bool:
    """Whether this process, not being root, may run commands as root without a password."""
    return bool(shutil.which("sudo")) and subprocess.run(["sudo", "-n", "true"], capture_output=True).returncode == 0


def _as_root(cmd: list[str]) -> list[str]:
    return cmd if os.geteuid() == 0 else ["sudo", "-n", *cmd]


def can_mount() -> bool:
    """Whether this process may mount a tmpfs: as root (with CAP_SYS_ADMIN) or through sudo."""
    if not shutil.which("mount") or (os.geteuid() != 0 and not can_sudo()):
        return False
    probe = Path(tempfile.mkdtemp(prefix="lanemap-mnt-"))
    try:
        ok = subprocess.run(_as_root(["mount", "-t", "tmpfs", "-o", "size=64k", "tmpfs", str(probe)]),
                            capture_output=True).returncode == 0  # fmt: skip
        if ok:
            subprocess.run(_as_root(["umount", str(probe)]), capture_output=True)
        return ok
    finally:
        probe.rmdir()


@contextlib.contextmanager
def tmpfs(path: Path, size_bytes: int, *, read_only: bool = False):
    """Mount a tmpfs of ``size_bytes`` at ``path`` for the block (see :func:`can_mount`).

    The mount belongs to this process's user, so that a server it starts can write there.
    """
    path.mkdir(parents=True, exist_ok=True)
    opts = f"size={size_bytes},uid={os.getuid()},gid={os.getgid()}" + (",ro" if read_only else "")
    subprocess.run(_as_root(["mount", "-t", "tmpfs", "-o", opts, "tmpfs", str(path)]), check=True,
                   capture_output=True)  # fmt: skip
    try:
        yield path
    finally:
        for _ in range(20):
            if subprocess.run(_as_root(["umount", str(path)]), capture_output=True).returncode == 0:
                break
            time.sleep(0.25)


def wait_for(predicate, timeout: float, period: float = 0.2, what: str = "condition"):
    """Poll ``predicate`` until it returns something truthy; returns that value."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        value = predicate()
        if value:
            return value
        time.sleep(period)
    raise AssertionError(f"timed out after {timeout} s waiting for {what}")

