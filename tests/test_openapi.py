"""openapi.yaml is the contract: it must equal the app's generated schema."""
import yaml

from service.app import create_app
from service.openapi_export import OPENAPI_PATH


def test_openapi_yaml_equals_app_schema():
    on_disk = yaml.safe_load(OPENAPI_PATH.read_text())
    assert on_disk == create_app().openapi(), "openapi.yaml is stale: run `python -m service.openapi_export`"


def test_every_post_route_has_a_runnable_example():
    schema = create_app().openapi()
    for path, item in schema["paths"].items():
        if "post" in item:
            content = item["post"]["requestBody"]["content"]["application/json"]
            assert content.get("examples") or content.get("example"), f"POST {path} has no example"
