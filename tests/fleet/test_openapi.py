"""Property-based requests generated from the server's own OpenAPI schema (schemathesis, bounded): whatever the
body, path or query, the server over real HTTP answers without a 5xx."""

from __future__ import annotations

import pytest

schemathesis = pytest.importorskip("schemathesis")
from hypothesis import HealthCheck, given, settings  # noqa: E402  (hypothesis comes with schemathesis)
from schemathesis.checks import not_a_server_error  # noqa: E402

from fleet.client import FleetClient  # noqa: E402
from fleet.runner import ServerThread  # noqa: E402
from fleet.server import create_app  # noqa: E402

ADMIN = "openapi-admin-secret"


@pytest.fixture(scope="module")
def fuzzed(tmp_path_factory, cae_descriptor):
    """A server on loopback with robot A registered: ``(url, A's token)``."""
    state = tmp_path_factory.mktemp("openapi_state")
    with ServerThread(create_app(state, ADMIN, descriptor=cae_descriptor)) as server:
        yield server.url, FleetClient(server.url, ADMIN).register("A")


def call(case, url, token):
    """Sends ``case`` with robot A's token (the admin's to register), A's own name in paths half the time (to reach
    the keyframe checks); fails on a 5xx."""
    if case.path_parameters and hash(repr(case.body)) % 2 == 0:
        case.path_parameters["name"] = "A"
    auth = ADMIN if case.path == "/robots" and case.method.upper() == "POST" else token
    response = case.call(base_url=url, headers={"Authorization": f"Bearer {auth}"}, timeout=30)
    case.validate_response(response, checks=[not_a_server_error])


class TestOpenAPI:
    def test_no_server_error_on_any_operation(self, fuzzed):
        url, token = fuzzed
        schema = schemathesis.openapi.from_url(f"{url}/openapi.json")
        operations = [result.ok() for result in schema.get_all_operations()]
        assert len(operations) == 7  # 6 + GET /robots/{name}/trajectory (/map is a page, not in the schema)
        for op in operations:
            @given(case=op.as_strategy())
            @settings(max_examples=25, deadline=None, derandomize=True, database=None,
                      suppress_health_check=list(HealthCheck))
            def run(case):
                call(case, url, token)

            run()
