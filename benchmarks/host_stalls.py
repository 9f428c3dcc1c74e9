"""How often the host stops a busy process: the floor under the load test's p99.

Starts ``--processes`` processes (default: one per core), each localizing the
load test's frames (:func:`load_localize.make_bodies`) in a loop for
``--seconds``, with no server, no network and no other thread. For every call
it compares the wall-clock time with the CPU time the thread got: a call that
took much longer than its CPU was descheduled, by the kernel or, on a virtual
machine, by the hypervisor. Prints per process the calls, the p50/p99/max wall
time, the calls stalled by more than ``--stall-ms`` and their median stall,
and the share of CPU time the hypervisor took (``steal``, from ``/proc/stat``).

On a machine whose cores are all busy, a request that waits behind a stalled
one waits as long, so stalls of this size set the p99 of
``load_localize.py`` at saturation, whatever the server does.

Usage::

    .venv/bin/python benchmarks/host_stalls.py [--processes 2] [--seconds 12] [--stall-ms 30]
"""

from __future__ import annotations

import argparse
import multiprocessing
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))


def _run(start_at: float, seconds: float, out) -> None:
    from load_localize import load_frames
    from tests._localizer_helpers import karlsruhe

    from localizer import localize

    index, _ = karlsruhe()
    frames = load_frames(200, 7, 1.5, 2.0)
    for obs, prior in frames[:20]:
        localize(index, obs, prior)
    time.sleep(max(0.0, start_at - time.time()))
    wall, cpu = [], []
    end = time.time() + seconds
    i = 0
    while time.time() < end:
        obs, prior = frames[i % len(frames)]
        i += 1
        w, c = time.perf_counter(), time.thread_time()
        localize(index, obs, prior)
        wall.append(time.perf_counter() - w)
        cpu.append(time.thread_time() - c)
    out.put((os.getpid(), np.array(wall) * 1e3, np.array(cpu) * 1e3))


def _cpu_times() -> list[int]:
    with open("/proc/stat") as fh:
        return [int(v) for v in fh.readline().split()[1:]]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--processes", type=int, default=os.cpu_count())
    ap.add_argument("--seconds", type=float, default=12.0)
    ap.add_argument("--stall-ms", type=float, default=30.0, help="wall time beyond CPU time that counts as a stall")
    args = ap.parse_args()
    ctx = multiprocessing.get_context("spawn")
    out = ctx.Queue()
    start_at = time.time() + 30.0  # every process has built its index and warmed up by then
    procs = [ctx.Process(target=_run, args=(start_at, args.seconds, out)) for _ in range(args.processes)]
    for p in procs:
        p.start()
    time.sleep(max(0.0, start_at - time.time()))
    before = _cpu_times()
    results = [out.get() for _ in procs]
    after = _cpu_times()
    for p in procs:
        p.join()
    delta = [b - a for a, b in zip(before, after)]
    steal = 100.0 * delta[7] / max(sum(delta[:8]), 1) if len(delta) > 7 else float("nan")
    print(f"host stalls, {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}, {os.cpu_count()} cores, "
          f"{args.processes} busy processes, {args.seconds:g} s; steal {steal:.1f} % of CPU time")
    for pid, wall, cpu in results:
        extra = wall - cpu
        stalled = extra[extra > args.stall_ms]
        print(f"  process {pid}: {len(wall)} calls, wall p50 {np.median(wall):.1f} ms, p99 "
              f"{np.percentile(wall, 99):.1f} ms, max {wall.max():.1f} ms; {len(stalled)} stalled by more than "
              f"{args.stall_ms:g} ms (median stall {np.median(stalled) if len(stalled) else 0:.0f} ms, "
              f"CPU of those calls {np.median(cpu[extra > args.stall_ms]) if len(stalled) else 0:.1f} ms)")


if __name__ == "__main__":
    main()
