"""The layer rule of docs/architecture.md, checked on the source: a package of ``infinirl`` imports
only from its own row of layers or the rows below it, with the few known exceptions listed here
(each with its reason, as the architecture page gives it). Every import counts, the ones inside
functions too: a lazy import is still a dependency. A new upward import fails here; it belongs in
a lower layer, or, if it cannot be moved, in ALLOWED with its reason and on the architecture page."""

from __future__ import annotations

import ast
from collections import defaultdict
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[2] / "infinirl"

#: Bottom to top. Within a row imports may go either way; between rows only downwards.
ROWS: tuple[tuple[str, ...], ...] = (
    ("utils",),
    ("registry", "config", "results"),
    ("runtime",),
    ("data", "algorithms"),
    ("engines", "models"),
    ("envs", "tasks", "agents"),
    ("components", "realworld", "edge"),
    ("evaluation", "runners"),
    ("scheduler",),
    ("cli",),
)

#: Narrower rules than the rows: these layers import only the listed ones (besides themselves).
ONLY: dict[str, set[str]] = {
    "utils": set(),
    "runtime": {"utils"},
    "algorithms": {"registry"},
}

#: (importing file, imported layer): why the upward import stays.
ALLOWED: dict[tuple[str, str], str] = {
    ("data/demos.py", "envs"): "the demonstration recorder (`infinirl demos`) runs the simulators and their "
                               "scripted experts; lazy, so the dataset reader and writer load without them",
    ("data/demos.py", "models"): "the recorder prepares observations as the policies read them; lazy",
    ("edge/__main__.py", "runners"): "the edge command line builds the robot loop from a run's config through "
                                     "the runner's helpers: it sits at the top, like cli.py",
    ("edge/__main__.py", "cli"): "the edge command line reuses the training command's config loading",
    ("runners/run_support.py", "scheduler"): "`placement=auto` is resolved by the scheduler, which runs the "
                                             "runners to profile them; lazy",
}

_ROW_OF = {layer: row for row, layers in enumerate(ROWS) for layer in layers}


def _layer(module: str) -> str | None:
    parts = module.split(".")
    return parts[1] if parts[0] == "infinirl" and len(parts) > 1 else None


def imported_layers(package: Path = PACKAGE) -> dict[tuple[str, str], list[str]]:
    """(file relative to the package, imported layer) -> the lines of those imports, for every
    import of another ``infinirl`` layer anywhere in a file (module level or inside functions)."""
    found: dict[tuple[str, str], list[str]] = defaultdict(list)
    for path in sorted(package.rglob("*.py")):
        relative = path.relative_to(package)
        source_layer = relative.with_suffix("").parts[0]
        if source_layer == "__init__":
            continue  # the package's own __init__ imports nothing but its version
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"), str(path))):
            if isinstance(node, ast.Import):
                modules = [alias.name for alias in node.names]
            elif isinstance(node, ast.ImportFrom):
                assert node.level == 0, f"{relative}:{node.lineno}: relative import; the code base imports absolutely"
                modules = [node.module or ""]
            else:
                continue
            for module in modules:
                layer = _layer(module)
                if layer is not None and layer != source_layer:
                    found[(relative.as_posix(), layer)].append(f"{relative}:{node.lineno}")
    return found


def violations(found: dict[tuple[str, str], list[str]]) -> list[str]:
    bad = []
    for (file, layer), where in sorted(found.items()):
        source = file.split("/")[0].removesuffix(".py")
        if source not in _ROW_OF or layer not in _ROW_OF:
            bad.append(f"{where[0]}: layer {source if source not in _ROW_OF else layer!r} is in no row of ROWS")
        elif source in ONLY and layer not in ONLY[source]:
            allowed = ", ".join(sorted(ONLY[source])) or "nothing else of infinirl"
            bad.append(f"{where[0]}: {source} may import {allowed}, not {layer}")
        elif _ROW_OF[layer] > _ROW_OF[source] and (file, layer) not in ALLOWED:
            bad.append(f"{', '.join(where)}: {source} imports {layer}, a layer above it")
    return bad


@pytest.fixture(scope="module")
def found():
    return imported_layers()  # parsing every file once is most of this module's time


def test_imports_point_downwards_except_the_listed_ones(found):
    assert violations(found) == []


def test_every_allowed_exception_still_exists(found):
    """An exception that is gone (the import moved down) leaves the list, and the architecture page."""
    assert [pair for pair in ALLOWED if pair not in found] == []


def test_an_upward_import_inside_a_function_is_found(tmp_path):
    package = tmp_path / "infinirl"
    (package / "models").mkdir(parents=True)
    (package / "components").mkdir()
    (package / "models" / "stats.py").write_text(
        "import torch\n\ndef f():\n    from infinirl.components.policy import RunningMeanStd\n")
    (package / "components" / "policy.py").write_text("from infinirl.models.stats import f\n")
    (package / "utils.py").write_text("import infinirl.runtime.worker\n")
    assert violations(imported_layers(package)) == [
        "models/stats.py:4: models imports components, a layer above it",
        "utils.py:1: utils may import nothing else of infinirl, not runtime",
    ]
