"""Property-based API testing from the OpenAPI contract: no input makes the service answer 5xx,
and every response conforms to the documented schema."""
from __future__ import annotations

import pytest
import schemathesis
from hypothesis import HealthCheck, settings

from service.app import create_app
from service.runtime import Runtime


@pytest.fixture(scope="session")
def api_schema(runtime):
    # Same assets, smaller frame limit so that the generated valid drapes stay cheap.
    small = runtime.settings.model_copy(update={"max_frames": 15})
    app = create_app(small, Runtime(small, runtime.body, runtime.catalog, runtime.clips))
    return schemathesis.openapi.from_asgi("/openapi.json", app)


schema = schemathesis.pytest.from_fixture("api_schema")


@schema.parametrize()
@settings(max_examples=40, deadline=None, derandomize=True, suppress_health_check=list(HealthCheck))
def test_api_never_answers_5xx(case):
    response = case.call()
    assert response.status_code < 500, response.text[:500]
    case.validate_response(response)
