"""Load test of the fleet server: N robots stream real KITTI 00 frames at once over loopback HTTP to a server in its own
process; keyframes/s, per-request latency (p50, p99) and the server's peak memory.

``python -m bench.fleet [--robots 8] [--keyframes 20] [--out runs/bench/fleet]`` prints a Markdown table and writes
``fleet_load.json``. The robots drive in pairs along consecutive stretches of 00, with their ground-truth poses: robot
``r`` sends every second frame of its pair's stretch (the even robot the even offsets), so a robot's keyframes are two
frames apart, as a real robot's would be, and each pair overlaps along its whole stretch (cross-robot verification
runs, and overlaps are accepted, as in a real fleet; with every robot N frames from its last, 3D points triangulated
from its own neighbouring keyframes were too poor for any overlap edge).
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import secrets
import shutil
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from cae_lcd.core.files import prepare_out_dir, write_text_atomic
from cae_lcd.fleet.client import FleetClient
from cae_lcd.fleet.demo import kitti_stream
from cae_lcd.fleet.recognition import FIXED_POLICY

from .common import REPO, md_table

__all__ = ["load_test", "main", "LOAD_FORMAT_VERSION"]

log = logging.getLogger(__name__)

LOAD_FORMAT_VERSION = 1  #: format of ``fleet_load.json``
_LOOPBACK_RAY = {"RAY_AUTH_MODE": "disabled"}  #: the bench's Ray cluster lives on loopback for one run
_MILVUS = {"places": {"name": "milvus"}}  #: the scale-out run's place memory: one milvus-lite all workers share
#: the robots' detectors run the fixed policy: a robot's 20 keyframes here are within an online warm-up (2 x 50), in
#: which nothing is verified across robots; a long-running fleet, calibrated, verifies as this does
_FIXED = FIXED_POLICY


def _serve(state: str, port: int) -> None:
    """The server process's body (``--serve``): uvicorn on loopback, the admin token from the environment, and the
    store, workers, Ray address and recognition conf (JSON) of a scale-out run (``FLEET_BENCH_STORE``, ``_WORKERS``,
    ``_RAY``, ``_RECOGNITION``) when given."""
    import uvicorn

    from cae_lcd.fleet.server import create_app

    app = create_app(state, os.environ["FLEET_BENCH_TOKEN"], store=os.environ.get("FLEET_BENCH_STORE") or None,
                     workers=int(os.environ.get("FLEET_BENCH_WORKERS", "1")),
                     ray_address=os.environ.get("FLEET_BENCH_RAY") or None,
                     recognition={**_FIXED, **json.loads(os.environ.get("FLEET_BENCH_RECOGNITION") or "{}")})
    uvicorn.run(app, host="127.0.0.1", port=port, log_level="warning")


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _start_server(state: Path, token: str, env: dict[str, str] | None = None) -> tuple[subprocess.Popen, str]:
    port = _free_port()
    proc = subprocess.Popen([sys.executable, "-m", "bench.fleet", "--serve", str(state), str(port)], cwd=REPO,
                            env={**os.environ, "FLEET_BENCH_TOKEN": token, **(env or {})})
    url = f"http://127.0.0.1:{port}"
    for _ in range(1800):
        try:
            FleetClient(url, token, timeout=2).overlaps()
            return proc, url
        except Exception:  # noqa: BLE001 - not listening yet
            if proc.poll() is not None:
                raise RuntimeError("the fleet server process exited at start") from None
            time.sleep(0.1)
    proc.kill()
    raise RuntimeError("the fleet server did not start in 180 s")


def _peak_rss(pid: int) -> int:
    """Peak resident memory of a live process (Linux ``VmHWM``), bytes; 0 when unknown."""
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) * 1024
    except OSError:
        pass
    return 0


def _robot(url: str, token: str, stream: Any, latencies: list[float], interval: float = 0.0,
           start: float = 0.0) -> None:
    """Sends the stream's keyframes: back to back (``interval`` 0), or one every ``interval`` s from ``start`` (an
    open loop: a late answer does not delay the next send's schedule beyond itself)."""
    client = FleetClient(url, token, timeout=600)
    for i, frame in enumerate(stream.frames):
        png = stream.images[i].read_bytes()
        if interval > 0:
            time.sleep(max(0.0, start + i * interval - time.perf_counter()))
        t0 = time.perf_counter()
        client.submit_keyframe(stream.name, frame, float(stream.times[i]), stream.poses[i], png, stream.K)
        latencies.append(time.perf_counter() - t0)


def load_test(kitti_root: str | Path, state: str | Path, robots: int = 8, keyframes: int = 20) -> dict[str, Any]:
    """Streams ``robots`` x ``keyframes`` keyframes at once; returns the measurements.

    Returns:
        ``{"robots", "keyframes", "wall_s", "keyframes_per_s", "latency_ms": {"p50", "p99", "max"},
        "server_peak_rss_mb", "overlaps"}``.
    """
    token = secrets.token_urlsafe(24)
    streams = [kitti_stream(f"R{r}", kitti_root, "00", list(range(r, r + robots * keyframes, robots)))
               for r in range(robots)]
    proc, url = _start_server(Path(state), token)
    try:
        admin = FleetClient(url, token)
        tokens = [admin.register(s.name) for s in streams]
        latencies: list[float] = []
        threads = [threading.Thread(target=_robot, args=(url, t, s, latencies)) for t, s in zip(tokens, streams)]
        started = time.perf_counter()
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        wall = time.perf_counter() - started
        overlaps = len(admin.overlaps())
        peak = _peak_rss(proc.pid)
    finally:
        proc.terminate()
        proc.wait(timeout=60)
    ms = np.asarray(latencies) * 1e3
    return {"format_version": LOAD_FORMAT_VERSION, "robots": robots, "keyframes": len(latencies), "wall_s": wall,
            "keyframes_per_s": len(latencies) / wall,
            "latency_ms": {"p50": float(np.percentile(ms, 50)), "p99": float(np.percentile(ms, 99)),
                           "max": float(ms.max())},
            "server_peak_rss_mb": peak / 2**20, "overlaps": overlaps, "cpus": os.cpu_count()}


def _cpu_seconds(pid: int) -> float:
    """User + system CPU time a live process has used so far (Linux ``/proc/PID/stat``), seconds."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def _processes() -> dict[int, tuple[int, int, float]]:
    """Every live process: pid -> (parent pid, session id, CPU seconds with its exited and waited-for children)."""
    out = {}
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            f = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:  # exited meanwhile
            continue
        out[int(stat.parent.name)] = (int(f[1]), int(f[3]), sum(int(x) for x in f[11:15]) / os.sysconf("SC_CLK_TCK"))
    return out


def _cpu_of(roots: Sequence[int]) -> float:
    """CPU seconds used so far by the processes ``roots``, their descendants and the other processes of their
    sessions (a daemon's workers: Ray's raylet and workers, PostgreSQL's backends), exited children included."""
    procs, roots_set = _processes(), set(roots)
    sessions = {procs[r][1] for r in roots if r in procs and procs[r][1] == r}  # roots that lead their session

    def counted(pid: int) -> bool:
        for _ in range(64):  # up the parent chain
            if pid in roots_set or procs.get(pid, (0, -1))[1] in sessions:
                return True
            if pid not in procs or procs[pid][0] <= 1:
                return False
            pid = procs[pid][0]
        return False

    return sum(cpu for pid, (_, _, cpu) in procs.items() if counted(pid))


def _streams(kitti_root: str | Path, robots: int, keyframes: int) -> list[Any]:
    """Robot ``r`` sends frames ``s + r % 2, s + r % 2 + 2, ...`` of KITTI 00, ``s`` its pair's stretch
    (``(r // 2) * 2 * keyframes``): robots ``2 i`` and ``2 i + 1`` overlap."""
    return [kitti_stream(f"R{r:02d}", kitti_root, "00",
                         [(r // 2) * 2 * keyframes + r % 2 + 2 * j for j in range(keyframes)]) for r in range(robots)]


def _drive(urls: list[str], token: str, streams: list[Any], interval: float) -> dict[str, Any]:
    """Registers the robots and streams them at once, robot ``r`` through ``urls[r % len(urls)]``; the wall time and
    the latency percentiles (``interval`` > 0: each robot sends one keyframe every ``interval`` s)."""
    admin = FleetClient(urls[0], token)
    tokens = [admin.register(s.name) for s in streams]
    latencies: list[float] = []
    start = time.perf_counter() + 0.5
    threads = [threading.Thread(target=_robot, args=(urls[r % len(urls)], t, s, latencies, interval,
                                                     start + r * interval / max(1, len(streams))))
               for r, (t, s) in enumerate(zip(tokens, streams))]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    wall = time.perf_counter() - start
    ms = np.asarray(latencies) * 1e3
    return {"keyframes": len(latencies), "wall_s": wall, "keyframes_per_s": len(latencies) / wall,
            "latency_ms": {"p50": float(np.percentile(ms, 50)), "p99": float(np.percentile(ms, 99))},
            "overlaps": len(admin.overlaps())}


def _postmaster(pg: Any) -> int:
    """The pid of a ``LocalPostgres``' server (the first line of its ``postmaster.pid``)."""
    return int((pg.data / "postmaster.pid").read_text().split()[0])


def _ray_head(cores: int) -> tuple[subprocess.Popen, str]:
    """A local Ray cluster head with ``cores`` CPUs (``ray start --head --block``; stopped by terminating it)."""
    port = _free_port()
    proc = subprocess.Popen([str(Path(sys.executable).parent / "ray"), "start", "--head", "--block",
                             f"--port={port}", f"--num-cpus={cores}", "--include-dashboard=false"],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True,
                            env={**os.environ, **_LOOPBACK_RAY})
    time.sleep(15)  # the head's start-up; the replicas' ray.init waits for it too
    return proc, f"127.0.0.1:{port}"


def _run_mode(kitti_root: str | Path, state: Path, robots: int, keyframes: int, interval: float,
              replicas: int, env: dict[str, str], engines: Sequence[int] = ()) -> dict[str, Any]:
    """One run on fresh state: ``replicas`` servers, the robots streaming; the servers' CPU time, and that of
    everything serving them (``server_cpu_s`` + the ``engines``' process trees: Ray's head and workers,
    PostgreSQL) as ``all_cpu_s``."""
    if state.exists():
        shutil.rmtree(state)
    token = secrets.token_urlsafe(24)
    servers = [_start_server(state, token, env) for _ in range(replicas)]
    try:
        cpu0 = sum(_cpu_seconds(p.pid) for p, _ in servers)
        all0 = _cpu_of([p.pid for p, _ in servers] + list(engines))
        r = _drive([u for _, u in servers], token, _streams(kitti_root, robots, keyframes), interval)
        r["server_cpu_s"] = sum(_cpu_seconds(p.pid) for p, _ in servers) - cpu0
        r["all_cpu_s"] = _cpu_of([p.pid for p, _ in servers] + list(engines)) - all0
    finally:
        for p, _ in servers:
            p.terminate()
            p.wait(timeout=120)
    return r


def scale_test(kitti_root: str | Path, out: Path, robots: int = 32, keyframes: int = 6, cores: int = 2,
               workers: int = 2, replicas: int = 2) -> dict[str, Any]:
    """Sustained throughput against what the measured CPU cost per keyframe allows on ``cores``, and latency at
    50 % of that load; the same with ``replicas`` front ends on PostgreSQL and ``workers`` Ray workers.

    The CPU cost is the single server's CPU time over the saturated run / keyframes (decode, gate, encode, features,
    search, verification, store, graph: everything a keyframe costs); the capacity ``cores / cost``. The scale-out
    run is held to that capacity, and also to its own: the CPU time of every process it runs on (front ends, Ray's
    head and workers, PostgreSQL) over its saturated run / keyframes.

    Returns:
        ``{"single": {"saturated", "half_load"}, "scale_out": {...}, "cpu_s_per_keyframe", "capacity_per_s", ...}``.
    """
    from cae_lcd.fleet.pg_local import LocalPostgres

    single = {"saturated": _run_mode(kitti_root, out / "state", robots, keyframes, 0.0, 1, {})}
    cost = single["saturated"]["server_cpu_s"] / single["saturated"]["keyframes"]
    capacity = cores / cost
    interval = robots / (0.5 * capacity)  # each robot's period at half the capacity
    single["half_load"] = _run_mode(kitti_root, out / "state", robots, keyframes, interval, 1, {})
    result = {"format_version": LOAD_FORMAT_VERSION, "robots": robots, "keyframes_per_robot": keyframes,
              "cores": cores, "cpu_s_per_keyframe": cost, "capacity_per_s": capacity, "single": single,
              "ratio": single["saturated"]["keyframes_per_s"] / capacity}
    head, address = _ray_head(cores)
    try:
        with LocalPostgres() as pg:
            scale = {}
            for run, period in (("saturated", 0.0), ("half_load", interval)):
                env = {"FLEET_BENCH_STORE": pg.create_database(f"bench_{run}"), "FLEET_BENCH_WORKERS": str(workers),
                       "FLEET_BENCH_RAY": address, "FLEET_BENCH_RECOGNITION": json.dumps(_MILVUS), **_LOOPBACK_RAY}
                scale[run] = _run_mode(kitti_root, out / f"state_{run}", robots, keyframes, period, replicas, env,
                                       [head.pid, _postmaster(pg)])
    finally:
        head.terminate()
        head.wait(timeout=120)
    own_cost = scale["saturated"]["all_cpu_s"] / scale["saturated"]["keyframes"]
    result["scale_out"] = {"replicas": replicas, "workers": workers, "store": "postgresql", "places": "milvus", **scale,
                           "ratio": scale["saturated"]["keyframes_per_s"] / capacity,
                           "cpu_s_per_keyframe": own_cost, "own_capacity_per_s": cores / own_cost,
                           "own_ratio": scale["saturated"]["keyframes_per_s"] * own_cost / cores}
    return result


def _scale_table(r: dict[str, Any]) -> str:
    rows = []
    for mode, label in (("single", "1 server, SQLite + faiss, in process"),
                        ("scale_out", f"{r['scale_out']['replicas']} replicas, PostgreSQL + Milvus, "
                                      f"{r['scale_out']['workers']} Ray workers")):
        m = r[mode]
        cost = m.get("cpu_s_per_keyframe", r["cpu_s_per_keyframe"])
        rows.append([label, f"{m['saturated']['keyframes_per_s']:.2f}", f"{r['capacity_per_s']:.2f}",
                     f"{m['saturated']['keyframes_per_s'] / r['capacity_per_s']:.0%}", f"{cost * 1e3:.0f}",
                     f"{r['cores'] / cost:.2f}", f"{m['saturated']['keyframes_per_s'] * cost / r['cores']:.0%}",
                     f"{m['half_load']['latency_ms']['p50']:.0f}", f"{m['half_load']['latency_ms']['p99']:.0f}",
                     m["saturated"]["overlaps"]])
    return md_table(["front end", "sustained keyframes/s", f"capacity on {r['cores']} cores at the single server's "
                     "CPU cost", "ratio", "its own CPU ms a keyframe (every process it runs on)",
                     "its own capacity", "ratio to its own", "p50 ms at 50 %", "p99 ms at 50 %", "overlaps"], rows)


def main(argv: Sequence[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--kitti", type=Path, default=REPO.parent / "shared" / "datasets" / "kitti")
    ap.add_argument("--robots", type=int, default=8)
    ap.add_argument("--keyframes", type=int, default=20, help="keyframes each robot sends")
    ap.add_argument("--out", type=Path, default=REPO / "runs" / "bench" / "fleet")
    ap.add_argument("--scale", action="store_true",
                    help="throughput vs CPU-cost capacity, latency at 50 %% load, then replicas on PostgreSQL + Ray")
    ap.add_argument("--cores", type=int, default=2, help="cores the capacity is computed for (--scale)")
    ap.add_argument("--serve", nargs=2, metavar=("STATE", "PORT"), help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.serve:
        _serve(args.serve[0], int(args.serve[1]))
        return
    if (args.robots + args.robots % 2) * args.keyframes > 200:
        ap.error("--robots (rounded up to even) x --keyframes must be at most 200 (the frames of KITTI 00 here)")
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    out = prepare_out_dir(args.out)
    state = out / "state"
    if state.exists():
        shutil.rmtree(state)
    if args.scale:
        r = scale_test(args.kitti, out, args.robots, args.keyframes, args.cores)
        write_text_atomic(out / "fleet_scale.json", json.dumps(r, indent=2))
        print(_scale_table(r))
        print(f"CPU per keyframe {r['cpu_s_per_keyframe'] * 1e3:.0f} ms; {r['robots']} robots x "
              f"{r['keyframes_per_robot']} keyframes")
        return
    r = load_test(args.kitti, state, args.robots, args.keyframes)
    write_text_atomic(out / "fleet_load.json", json.dumps(r, indent=2))
    print(md_table(["robots", "keyframes", "wall s", "keyframes/s", "latency p50 ms", "latency p99 ms",
                    "server peak RSS MB", "overlaps"],
                   [[r["robots"], r["keyframes"], f"{r['wall_s']:.1f}", f"{r['keyframes_per_s']:.2f}",
                     f"{r['latency_ms']['p50']:.0f}", f"{r['latency_ms']['p99']:.0f}",
                     f"{r['server_peak_rss_mb']:.0f}", r["overlaps"]]]))


if __name__ == "__main__":
    main()
