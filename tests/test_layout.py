"""The layout's rules, read from the source: ``service/`` does no array maths (imports no numpy),
``inference/`` never imports torch or ``training``, and what ``inference/`` and ``service/``
import from outside the standard library is in the runtime dependencies of pyproject.toml."""
from __future__ import annotations

import ast
import sys
import tomllib

from tests.conftest import REPO_ROOT

# import name -> distribution name, where they differ
DISTRIBUTIONS = {"yaml": "pyyaml", "igl": "libigl", "prometheus_client": "prometheus-client", "pydantic_settings": "pydantic-settings",
                 "onnxruntime": "onnxruntime", "swagger_ui_bundle": "swagger-ui-bundle", "annotated_types": "pydantic",
                 "starlette": "fastapi", "pydantic_core": "pydantic"}


def _imports(package: str) -> dict[str, set[str]]:
    out: dict[str, set[str]] = {}
    for path in (REPO_ROOT / package).rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                names = [node.module]
            else:
                continue
            for name in names:
                out.setdefault(name.split(".")[0], set()).add(str(path.relative_to(REPO_ROOT)))
    return out


def test_service_does_no_array_maths():
    imports = _imports("service")
    assert "numpy" not in imports, imports.get("numpy")


def test_inference_never_imports_torch_or_training():
    imports = _imports("inference")
    for banned in ("torch", "training", "service", "anny", "newton", "warp"):
        assert banned not in imports, (banned, imports.get(banned))


def test_runtime_imports_are_runtime_dependencies():
    spec = tomllib.loads((REPO_ROOT / "pyproject.toml").read_text())
    # runtime: the dependencies, and the optional runtime extra 'compress' (meshopt glb compression,
    # imported only when a request asks for it: inference.export.meshopt.available)
    runtime = spec["project"]["dependencies"] + spec["project"]["optional-dependencies"]["compress"]
    deps = {d.split(">")[0].split("=")[0].split("<")[0].strip().lower() for d in runtime}
    local = {"inference", "service", "training", "tests"}
    for package in ("inference", "service"):
        for name, files in _imports(package).items():
            if name in sys.stdlib_module_names or name in local or name == "__future__":
                continue
            assert DISTRIBUTIONS.get(name, name).lower() in deps, (name, sorted(files))
