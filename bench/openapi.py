"""Property-based requests against the fleet server's own OpenAPI schema, every schemathesis check (``--checks
all``), with a registered robot's token: a larger run than the test suite's (``tests/fleet/test_openapi.py``).

``python -m bench.openapi [--examples 1000] [--out runs/bench/openapi]`` prints the failures per operation and
writes ``openapi.json``.
"""

from __future__ import annotations

import argparse
import json
import logging
import tempfile
import time
from typing import Any, Sequence

from cae_lcd.core.files import prepare_out_dir, write_text_atomic
from cae_lcd.fleet.client import FleetClient
from cae_lcd.fleet.runner import ServerThread
from cae_lcd.fleet.server import create_app

from .common import REPO, md_table

__all__ = ["fuzz", "main", "OPENAPI_FORMAT_VERSION", "ACCEPTED"]

log = logging.getLogger(__name__)

OPENAPI_FORMAT_VERSION = 1  #: format of ``openapi.json``
#: statuses that count as accepting schema-valid data: a string the schema allows can still be no image (400) or
#: an image over the pixel limit (413); each is a documented refusal
ACCEPTED = ["2xx", "400", "401", "403", "404", "409", "413", "429"]
ADMIN = "bench-openapi-admin"


def fuzz(examples: int = 1000, seed: int = 19) -> dict[str, Any]:
    """Runs ``examples`` generated requests per operation against a fresh server (robot A registered; its own
    name in paths half the time).

    Returns:
        ``{"examples", "operations": {label: {"failures": [one line each]}}, "wall_s"}``.
    """
    import schemathesis
    from hypothesis import HealthCheck, given, settings
    from schemathesis.checks import CHECKS, load_all_checks

    load_all_checks()
    checks = CHECKS.get_all()
    out: dict[str, Any] = {"format_version": OPENAPI_FORMAT_VERSION, "examples": examples, "operations": {}}
    started = time.perf_counter()
    with tempfile.TemporaryDirectory() as state, ServerThread(create_app(state, ADMIN)) as server:
        token = FleetClient(server.url, ADMIN).register("A")
        schema = schemathesis.openapi.from_url(f"{server.url}/openapi.json")
        schema.config.checks.positive_data_acceptance.expected_statuses = ACCEPTED
        for result in schema.get_all_operations():
            op = result.ok()
            failures: list[str] = []

            @given(case=op.as_strategy())
            @settings(max_examples=examples, deadline=None, database=None, suppress_health_check=list(HealthCheck))
            def run(case: Any) -> None:
                if case.path_parameters and hash(repr(case.body)) % 2 == 0:
                    case.path_parameters["name"] = "A"
                auth = ADMIN if case.path == "/robots" and case.method.upper() == "POST" else token
                response = case.call(base_url=server.url, headers={"Authorization": f"Bearer {auth}"}, timeout=60)
                try:
                    case.validate_response(response, checks=checks)
                except Exception as err:  # noqa: BLE001 - every failure is recorded, the run goes on
                    failures.append(str(err).strip().splitlines()[0][:300])

            run()
            out["operations"][op.label] = {"failures": sorted(set(failures))}
            log.info("%s: %d failures", op.label, len(failures))
    out["wall_s"] = time.perf_counter() - started
    return out


def main(argv: Sequence[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--examples", type=int, default=1000, help="generated requests per operation")
    ap.add_argument("--out", default=str(REPO / "runs" / "bench" / "openapi"))
    args = ap.parse_args(argv)
    if args.examples < 1:
        ap.error("--examples must be at least 1")
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    out = prepare_out_dir(args.out)
    r = fuzz(args.examples)
    write_text_atomic(out / "openapi.json", json.dumps(r, indent=2))
    print(md_table(["operation", "examples", "failures"],
                   [[label, r["examples"], len(o["failures"])] for label, o in r["operations"].items()]))


if __name__ == "__main__":
    main()
