"""Load test of the fleet server: N robots stream real KITTI 00 frames at once over loopback HTTP to a server in its own
process; keyframes/s, per-request latency (p50, p99) and the server's peak memory.

``python -m bench.fleet [--robots 8] [--keyframes 20] [--out runs/bench/fleet]`` prints a Markdown table and writes
``fleet_load.json``. Robot ``r`` sends frames ``r, r + N, r + 2N, ...`` of 00 with their ground-truth poses (so the
robots overlap and cross-robot verification runs as it would in a real fleet).
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

from core.files import prepare_out_dir, write_text_atomic
from fleet.client import FleetClient
from fleet.demo import kitti_stream

from .common import REPO, md_table

__all__ = ["load_test", "main", "LOAD_FORMAT_VERSION"]

log = logging.getLogger(__name__)

LOAD_FORMAT_VERSION = 1  #: format of ``fleet_load.json``


def _serve(state: str, port: int) -> None:
    """The server process's body (``--serve``): uvicorn on loopback, the admin token from the environment."""
    import uvicorn

    from fleet.server import create_app

    uvicorn.run(create_app(state, os.environ["FLEET_BENCH_TOKEN"]), host="127.0.0.1", port=port, log_level="warning")


def _start_server(state: Path, token: str) -> tuple[subprocess.Popen, str]:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    proc = subprocess.Popen([sys.executable, "-m", "bench.fleet", "--serve", str(state), str(port)], cwd=REPO,
                            env={**os.environ, "FLEET_BENCH_TOKEN": token})
    url = f"http://127.0.0.1:{port}"
    for _ in range(600):
        try:
            FleetClient(url, token, timeout=2).overlaps()
            return proc, url
        except Exception:  # noqa: BLE001 - not listening yet
            if proc.poll() is not None:
                raise RuntimeError("the fleet server process exited at start") from None
            time.sleep(0.1)
    proc.kill()
    raise RuntimeError("the fleet server did not start in 60 s")


def _peak_rss(pid: int) -> int:
    """Peak resident memory of a live process (Linux ``VmHWM``), bytes; 0 when unknown."""
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) * 1024
    except OSError:
        pass
    return 0


def _robot(url: str, token: str, stream: Any, latencies: list[float]) -> None:
    client = FleetClient(url, token, timeout=600)
    for i, frame in enumerate(stream.frames):
        png = stream.images[i].read_bytes()
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


def main(argv: Sequence[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--kitti", type=Path, default=REPO.parent / "shared" / "datasets" / "kitti")
    ap.add_argument("--robots", type=int, default=8)
    ap.add_argument("--keyframes", type=int, default=20, help="keyframes each robot sends")
    ap.add_argument("--out", type=Path, default=REPO / "runs" / "bench" / "fleet")
    ap.add_argument("--serve", nargs=2, metavar=("STATE", "PORT"), help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.serve:
        _serve(args.serve[0], int(args.serve[1]))
        return
    if args.robots * args.keyframes > 200:
        ap.error("--robots x --keyframes must be at most 200 (the frames of KITTI 00 here)")
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    out = prepare_out_dir(args.out)
    state = out / "state"
    if state.exists():
        shutil.rmtree(state)
    r = load_test(args.kitti, state, args.robots, args.keyframes)
    write_text_atomic(out / "fleet_load.json", json.dumps(r, indent=2))
    print(md_table(["robots", "keyframes", "wall s", "keyframes/s", "latency p50 ms", "latency p99 ms",
                    "server peak RSS MB", "overlaps"],
                   [[r["robots"], r["keyframes"], f"{r['wall_s']:.1f}", f"{r['keyframes_per_s']:.2f}",
                     f"{r['latency_ms']['p50']:.0f}", f"{r['latency_ms']['p99']:.0f}",
                     f"{r['server_peak_rss_mb']:.0f}", r["overlaps"]]]))


if __name__ == "__main__":
    main()
