"""CPU of the fleet's place memory per keyframe: a search of the other robots' top-k and an insert, on each kind:
``local`` (faiss fp16, in process), ``milvus`` served by this process (milvus-lite in its own threads: what each Ray
worker ran before the shared index, one private collection each) and ``milvus`` served by another process (the shared
index: every worker a client of one server); the CPU of every process involved, read from ``/proc``.

``python -m bench.fleet_places [--rows 200] [--queries 100] [--k 64] [--workers 2]`` prints a Markdown table and
writes ``fleet_places.json`` under ``--out``. Entries are random unit 4096-d vectors of 32 robots (the CPU does not
depend on what they show). A keyframe on ``--workers`` workers costs one search and ``workers`` inserts with a private
milvus-lite per worker (every worker inserted every robot's keyframe), one search and one insert with the shared one.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from cae_lcd.core.files import prepare_out_dir, write_text_atomic
from cae_lcd.fleet.places import FleetPlaces, create_fleet_places, resolve_places
from retrieval.descriptors import create_descriptor
from retrieval.detector import resolve_conf

from .common import REPO, md_table
from .fleet import _cpu_seconds

__all__ = ["place_costs", "main"]

_SERVE = "import sys; from retrieval.milvus_index import serve_lite; print(serve_lite(sys.argv[1]), flush=True); " \
         "sys.stdin.read()"  #: a milvus-lite server process, until its standard input closes


def _measure(places: FleetPlaces, pids: list[int], codes: np.ndarray, rows: int, queries: int,
             k: int) -> dict[str, list[float]]:
    """CPU ms per search and per insert of each process in ``pids``, after ``rows`` entries of 32 robots."""
    robot = [f"R{i % 32:02d}" for i in range(len(codes))]
    for i in range(rows):
        places.add(robot[i], [i], codes[i:i + 1])
    c0 = [_cpu_seconds(p) for p in pids]
    for i in range(rows, rows + queries):
        places.search(robot[i], codes[i], k)
    c1 = [_cpu_seconds(p) for p in pids]
    for i in range(rows, rows + queries):
        places.add(robot[i], [i], codes[i:i + 1])
    c2 = [_cpu_seconds(p) for p in pids]
    return {"search_ms": [(b - a) * 1e3 / queries for a, b in zip(c0, c1)],
            "insert_ms": [(b - a) * 1e3 / queries for a, b in zip(c1, c2)]}


def place_costs(rows: int = 200, queries: int = 100, k: int = 64) -> dict[str, Any]:
    """Search and insert CPU of each kind (``{"kinds": {label: {"search_ms", "insert_ms"}}, ...}``: lists with one
    number per process, this one first)."""
    descriptor = create_descriptor({"name": "cae"})
    codes = np.random.default_rng(0).normal(size=(rows + queries, descriptor.dim)).astype(np.float32)
    codes /= np.linalg.norm(codes, axis=1, keepdims=True)
    out: dict[str, Any] = {"rows": rows, "queries": queries, "k": k, "dim": descriptor.dim, "kinds": {}}
    with tempfile.TemporaryDirectory() as tmp:
        server = subprocess.Popen([sys.executable, "-c", _SERVE, str(Path(tmp) / "served.db")], cwd=REPO,
                                  stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
        try:
            uri = server.stdout.readline().strip() if server.stdout else ""
            for label, conf, pids in (("local (faiss fp16, in process)", {"name": "local"}, [os.getpid()]),
                                      ("milvus-lite served by this process", {"name": "milvus", "uri": ""},
                                       [os.getpid()]),
                                      ("milvus-lite served by another process", {"name": "milvus", "uri": uri},
                                       [os.getpid(), server.pid])):
                places = create_fleet_places(descriptor, None, resolve_conf(), resolve_places(conf),
                                             Path(tmp) / label.split()[0] / str(len(out["kinds"])))
                out["kinds"][label] = _measure(places, pids, codes, rows, queries, k)
                places.close()
        finally:
            if server.stdin:
                server.stdin.close()
            server.wait(timeout=60)
    return out


def _table(r: dict[str, Any], workers: int) -> str:
    rows = []
    private, shared = (r["kinds"][f"milvus-lite served by {w}"] for w in ("this process", "another process"))
    for label, m in r["kinds"].items():
        rows.append([label, " + ".join(f"{x:.1f}" for x in m["search_ms"]),
                     " + ".join(f"{x:.1f}" for x in m["insert_ms"])])
    per_private = sum(private["search_ms"]) + workers * sum(private["insert_ms"])
    per_shared = sum(shared["search_ms"]) + sum(shared["insert_ms"])
    note = (f"\nA keyframe on {workers} workers: a private milvus-lite per worker {per_private:.1f} ms of CPU "
            f"(1 search + {workers} inserts), the shared one {per_shared:.1f} ms (1 search + 1 insert).")
    return md_table(["place memory", f"search of the top {r['k']} CPU ms (client + server)",
                     "insert CPU ms (client + server)"], rows) + note


def main(argv: Sequence[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--rows", type=int, default=200, help="entries in the memory before the measured calls")
    ap.add_argument("--queries", type=int, default=100, help="searches and inserts measured")
    ap.add_argument("--k", type=int, default=64, help="hits a search returns (recognition.cross.search_k)")
    ap.add_argument("--workers", type=int, default=2, help="workers a keyframe was inserted on before (the note)")
    ap.add_argument("--out", type=Path, default=REPO / "runs" / "bench" / "fleet_places")
    args = ap.parse_args(argv)
    out = prepare_out_dir(args.out)
    r = place_costs(args.rows, args.queries, args.k)
    write_text_atomic(out / "fleet_places.json", json.dumps(r, indent=2))
    print(_table(r, args.workers))


if __name__ == "__main__":
    main()
