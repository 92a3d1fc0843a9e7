"""Generated requests against every operation of the OpenAPI schema, as the admin and as a team: whatever a
user sends gets an answer, never a server error (schemathesis drives hypothesis from the schema)."""

from __future__ import annotations

import schemathesis
from hypothesis import HealthCheck, given, settings
from schemathesis.checks import not_a_server_error
from server_testing import World


def test_no_request_gets_a_server_error(world: World) -> None:
    schema = schemathesis.openapi.from_asgi("/openapi.json", world.client.app)
    operations = [result.ok() for result in schema.get_all_operations()]
    assert len(operations) > 30

    for operation in operations:

        @given(case=operation.as_strategy())
        @settings(max_examples=20, deadline=None, database=None, suppress_health_check=list(HealthCheck))
        def answers(case: schemathesis.Case) -> None:
            for headers in (world.admin_headers(), world.team_headers()):
                case.call_and_validate(headers=headers, checks=[not_a_server_error])

        answers()


# Operations whose answer is not a JSON model: the CSV-or-JSON export (pictures are found by their .png).
NOT_JSON_MODELS = {"/api/v1/admin/export"}


def test_every_json_operation_answers_a_declared_model(world: World) -> None:
    """Each JSON answer is a pydantic model (or a list of them) in the schema, never a bare object."""
    paths = world.client.get("/openapi.json").json()["paths"]
    checked = 0
    for path, operations in paths.items():
        if path in NOT_JSON_MODELS or path.endswith(".png"):
            continue
        for method, operation in operations.items():
            success = next(code for code in operation["responses"] if code.startswith("2"))
            schema = operation["responses"][success]["content"]["application/json"]["schema"]
            model = schema["items"] if schema.get("type") == "array" else schema
            assert set(model) == {"$ref"}, (method, path, schema)
            checked += 1
    assert checked > 30
