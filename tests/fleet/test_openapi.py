"""Property-based requests generated from the server's own OpenAPI schema (schemathesis, bounded): whatever the
body, path or query, the server over real HTTP answers without a 5xx."""

from __future__ import annotations

import pytest

schemathesis = pytest.importorskip("schemathesis")
from hypothesis import HealthCheck, given, settings  # noqa: E402  (hypothesis comes with schemathesis)
from schemathesis.checks import CHECKS, load_all_checks  # noqa: E402

from cae_lcd.fleet.client import FleetClient  # noqa: E402
from cae_lcd.fleet.runner import ServerThread  # noqa: E402
from cae_lcd.fleet.server import create_app  # noqa: E402

ADMIN = "openapi-admin-secret"
EXAMPLES = 120  #: examples per operation (bench.openapi runs many more)
load_all_checks()
ALL_CHECKS = CHECKS.get_all()  #: --checks all


@pytest.fixture(scope="module")
def fuzzed(tmp_path_factory, cae_descriptor):
    """A server on loopback with robot A registered: ``(url, A's token)``."""
    state = tmp_path_factory.mktemp("openapi_state")
    with ServerThread(create_app(state, ADMIN, descriptor=cae_descriptor)) as server:
        admin = FleetClient(server.url, ADMIN)
        token = admin.register("A")
        admin.register("B")  # the admin's routes act on B (A's token stays valid for the others)
        yield server.url, token


ADMIN_ROUTES = ("/robots/{name}/reset", "/robots/{name}/retire", "/robots/{name}/token", "/anchor")


def call(case, url, token):
    """Sends ``case`` with robot A's token (the admin's to register), A's own name in paths half the time (to reach
    the keyframe checks); fails on a 5xx."""
    if case.path_parameters and hash(repr(case.body)) % 2 == 0:
        case.path_parameters["name"] = "A"
    auth = ADMIN if case.path == "/robots" and case.method.upper() == "POST" else token
    response = case.call(base_url=url, headers={"Authorization": f"Bearer {auth}"}, timeout=30)
    case.validate_response(response, checks=ALL_CHECKS)


class TestOpenAPI:
    def test_no_server_error_on_any_operation(self, fuzzed):
        url, token = fuzzed
        schema = schemathesis.openapi.from_url(f"{url}/openapi.json")
        # a schema-valid body can still hold a string that is no image, or pixels beyond the limit: 400 and 413
        # are acceptance too (every refusal is documented, and response_schema_conformance checks its body)
        schema.config.checks.positive_data_acceptance.expected_statuses = ["2xx", "400", "401", "403", "404", "409",
                                                                           "413", "429"]
        operations = [result.ok() for result in schema.get_all_operations()]
        # 6 + GET /robots/{name}/trajectory + the admin's 4 (reset, retire, token, anchor; /map is a page, not in the
        # schema)
        assert len(operations) == 11
        for op in operations:
            @given(case=op.as_strategy())
            @settings(max_examples=EXAMPLES, deadline=None, derandomize=True, database=None,
                      suppress_health_check=list(HealthCheck))
            def run(case):
                call(case, url, token)

            run()

    def test_the_admins_routes_with_the_admin_token(self, fuzzed):
        """Reset, retire, token and anchor fuzzed with the admin's token, on robot B half the time: no 5xx, every
        answer documented."""
        url, _ = fuzzed
        schema = schemathesis.openapi.from_url(f"{url}/openapi.json")
        schema.config.checks.positive_data_acceptance.expected_statuses = ["2xx", "400", "404", "409"]
        operations = [r.ok() for r in schema.get_all_operations() if r.ok().path in ADMIN_ROUTES]
        assert len(operations) == 4
        for op in operations:
            @given(case=op.as_strategy())
            @settings(max_examples=EXAMPLES // 2, deadline=None, derandomize=True, database=None,
                      suppress_health_check=list(HealthCheck))
            def run(case):
                if case.path_parameters and hash(repr(case.body)) % 2 == 0:
                    case.path_parameters["name"] = "B"
                response = case.call(base_url=url, headers={"Authorization": f"Bearer {ADMIN}"}, timeout=30)
                case.validate_response(response, checks=ALL_CHECKS)

            run()
