"""Layers point down: core at the bottom, the engine pure, workers below the routers, domain
services free of the workers. Checked on the import statements of every module in ``app/``."""

from __future__ import annotations

import ast
import re
import sys
from pathlib import Path

import pytest

APP = Path(__file__).resolve().parents[1] / "app"
ENGINE_THIRD_PARTY = {"numpy", "scipy", "numba"}
"""What the engine may import: numerics (numba compiles its hot loops), no web, no database."""
# the counting of occupancy and the placing of heatmap cells: numpy only, checked by hand
ANALYTICS_PURE = {"app.analytics.occupancy", "app.analytics.heatmap"}
ROUTER = re.compile(r"^app\.\w+\.router(\.|$)")
DOMAIN_SERVICE = re.compile(r"^app\.\w+\.service$")
REQUEST_LAYER = re.compile(r"^app\.(main|\w+\.router|\w+\.deps)$")
"""Modules that serve requests: the only ones that may reach for the app's state."""


def module_name(path: Path) -> str:
    """Return the dotted name of a module file under ``app/``."""
    parts = path.relative_to(APP.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def imported_names(source: str, module: str, *, is_package: bool = False) -> list[str]:
    """Return every module name ``source`` imports, relative imports resolved, including
    imports inside functions; ``from a import b`` yields both ``a`` and ``a.b``, since ``b``
    may be a module."""
    package = module.split(".") if is_package else module.split(".")[:-1]
    names: list[str] = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            names.extend(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = package[: len(package) - node.level + 1]
                base = ".".join([*anchor, base] if base else anchor)
            names.append(base)
            names.extend(f"{base}.{alias.name}" for alias in node.names)
    return names


def _inside(name: str, package: str) -> bool:
    return name == package or name.startswith(package + ".")


def violations(module: str, imports: list[str]) -> list[str]:
    """Return the layering rules that ``module`` importing ``imports`` breaks."""
    found = []
    for name in imports:
        if _inside(module, "app.core") and _inside(name, "app") and not _inside(name, "app.core"):
            found.append(f"{module} (core) imports {name}")
        if _inside(module, "app.engine") and not (
            _inside(name, "app.engine")
            or name.split(".")[0] in sys.stdlib_module_names
            or name.split(".")[0] in ENGINE_THIRD_PARTY
        ):
            found.append(f"{module} (engine) imports {name}")
        if module in ANALYTICS_PURE and not (
            name.split(".")[0] in sys.stdlib_module_names or name.split(".")[0] == "numpy"
        ):
            found.append(f"{module} (analytics arithmetic) imports {name}")
        if _inside(module, "app.workers") and ROUTER.match(name):
            found.append(f"{module} (workers) imports the router {name}")
        if DOMAIN_SERVICE.match(module) and _inside(name, "app.workers"):
            found.append(f"{module} (domain service) imports {name}")
        if ROUTER.match(name) and module != "app.main":
            found.append(f"{module} imports the router {name}; only app.main mounts routers")
        if _inside(name, "app.state") and not REQUEST_LAYER.match(module):
            found.append(f"{module} imports the app state {name}; only the request layer may")
    return found


def _imports_by_module() -> dict[str, list[str]]:
    return {
        module_name(p): imported_names(
            p.read_text(), module_name(p), is_package=p.name == "__init__.py"
        )
        for p in sorted(APP.rglob("*.py"))
    }


def test_every_module_imports_only_downwards() -> None:
    imports = _imports_by_module()
    assert len(imports) > 50, "the walk found too few modules to check"
    assert [v for module, names in imports.items() for v in violations(module, names)] == []


def test_relative_imports_are_resolved() -> None:
    assert "app.workers.convert" in imported_names("from ..workers import convert", "app.ingest.x")
    assert "app.engine.samples" in imported_names(
        "from .samples import Batch", "app.engine", is_package=True
    )


@pytest.mark.parametrize(
    ("module", "source"),
    [
        ("app.core.config", "from app.sites.models import Site"),
        ("app.core.db", "def f():\n    import app.workers.runtime"),
        ("app.engine.hmm", "import shapely"),
        ("app.engine.hmm", "from app.geometry.raster import floor_plan"),
        ("app.workers.shard", "from app.sites import router"),
        ("app.workers.shard", "from app.ingest.router import router"),
        ("app.radiomaps.service", "from app.workers.runtime import Runtime"),
        ("app.ingest.service", "from ..workers import convert"),
        ("app.state", "from app.tracks.router import router"),
        ("app.tracks.jobs", "from app.state import AppState"),
        ("app.analytics.occupancy", "from sqlalchemy import select"),
    ],
)
def test_the_checker_catches_a_violation(module: str, source: str) -> None:
    assert violations(module, imported_names(source, module))


@pytest.mark.parametrize(
    ("module", "source"),
    [
        ("app.core.errors", "from app.core.time import now_ms\nimport fastapi"),
        ("app.engine.hmm", "import numpy as np\nfrom scipy import sparse\nfrom . import samples"),
        ("app.workers.shard", "from app.sites.assembly import assemble_site"),
        ("app.ingest.flows", "from app.workers.runtime import Runtime"),
        ("app.main", "from app.sites.router import router"),
        ("app.keys.deps", "from app.state import app_state"),
    ],
)
def test_the_checker_allows_downward_imports(module: str, source: str) -> None:
    assert violations(module, imported_names(source, module)) == []
