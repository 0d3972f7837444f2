"""docs/equations.md names real code: every `module.attr` in its "implemented by" column resolves,
and every `tests/file.py::test` in its "tested by" column exists."""
from __future__ import annotations

import ast
import importlib
import re

import pytest

from tests.conftest import REPO_ROOT

TABLE = (REPO_ROOT / "docs" / "equations.md").read_text()
CODE = sorted(set(re.findall(r"`((?:inference|training)\.[\w.]+)`", TABLE)))
TESTS = sorted(set(re.findall(r"`(tests/\w+\.py)::(\w+)`", TABLE)))


def _resolve(dotted: str):
    parts = dotted.split(".")
    for cut in range(len(parts), 0, -1):
        try:
            obj = importlib.import_module(".".join(parts[:cut]))
        except ModuleNotFoundError:
            continue
        for name in parts[cut:]:
            obj = getattr(obj, name)
        return obj
    raise ModuleNotFoundError(dotted)


def test_the_table_names_code_and_tests():
    assert len(CODE) >= 20 and len(TESTS) >= 20


@pytest.mark.parametrize("dotted", CODE)
def test_named_code_exists(dotted):
    assert callable(_resolve(dotted)), dotted


@pytest.mark.parametrize("path, name", TESTS)
def test_named_tests_exist(path, name):
    tree = ast.parse((REPO_ROOT / path).read_text())
    assert name in {n.name for n in ast.walk(tree) if isinstance(n, ast.FunctionDef)}, f"{path}::{name}"
