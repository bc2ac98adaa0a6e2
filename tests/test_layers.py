"""The import graph of dpcn_med: every import, at module level or inside a function, points down the layers of
STYLE.md (cli/slicer -> registration/train/benchmark -> models/synth/refine -> solver -> geometry/io), never up."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "dpcn_med"

LAYERS: dict[str, int] = {
    # 6: the entrances. The package itself re-exports the public API (dpcn_med.register).
    "dpcn_med": 6,
    "dpcn_med.__main__": 6,
    "dpcn_med.cli": 6,
    "dpcn_med.demo": 6,
    # 5: what a user asks for: a registration, a training run, a benchmark, and a registration's report.
    "dpcn_med.registration": 5,
    "dpcn_med.train": 5,
    "dpcn_med.benchmark": 5,
    "dpcn_med.report": 5,
    # and a registration's files, a cohort of them, and a cohort on Dask.
    "dpcn_med.outputs": 5,
    "dpcn_med.batch": 5,
    "dpcn_med.cluster": 5,
    # 4: the pieces they are built of.
    "dpcn_med.models": 4,
    "dpcn_med.synth": 4,
    "dpcn_med.refine": 4,
    "dpcn_med.local_search": 4,
    "dpcn_med.options": 4,
    "dpcn_med.result": 4,
    "dpcn_med.quality": 4,
    "dpcn_med.samples": 4,
    "dpcn_med.render": 4,
    # 3: from an image to a solver grid, and the measures of a pose.
    "dpcn_med.preprocess": 3,
    "dpcn_med.evaluation": 3,
    "dpcn_med.mutual_information": 3,
    "dpcn_med.lc2": 3,
    # 2: the solver, torch only.
    "dpcn_med.solver": 2,
    # 1: the conventions and the files.
    "dpcn_med.geometry": 1,
    "dpcn_med.io": 1,
    # 0: what everything may use: errors, argument checks, devices, two threads at once, and the version (set in dpcn_med/__init__.py
    # before it imports anything).
    "dpcn_med.errors": 0,
    "dpcn_med.arguments": 0,
    "dpcn_med.devices": 0,
    "dpcn_med.modalities": 0,
    "dpcn_med.threads": 0,
    "dpcn_med.__version__": 0,
}
"""Layer of each module (a package's entry covers its submodules: ``dpcn_med.io`` and ``dpcn_med.io.*`` alike). A
module may import from its own layer and the ones below."""


def module_name(path: Path) -> str:
    parts = list(path.relative_to(PACKAGE.parent).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


MODULES = {module_name(path): path for path in sorted(PACKAGE.rglob("*.py"))}


def layer(name: str) -> int:
    """The layer of module ``name``: the entry of the longest prefix of its dotted name in :data:`LAYERS`."""
    parts = name.split(".")
    for end in range(len(parts), 0, -1):
        if ".".join(parts[:end]) in LAYERS:
            return LAYERS[".".join(parts[:end])]
    raise KeyError(f"{name} has no layer in tests/test_layers.py's LAYERS; add it there")


def imported(tree: ast.AST, modules: set[str]) -> list[tuple[int, str]]:
    """``(line, module)`` for every import of dpcn_med in ``tree``, wherever it stands; ``from dpcn_med.x import y``
    counts as an import of ``dpcn_med.x.y`` when that is a module, of ``dpcn_med.x`` otherwise."""
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found += [(node.lineno, alias.name) for alias in node.names]
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            for alias in node.names:
                name = f"{node.module}.{alias.name}"
                found.append((node.lineno, name if name in modules or name == "dpcn_med.__version__"
                              else node.module))
    return [(line, name) for line, name in found if name == "dpcn_med" or name.startswith("dpcn_med.")]


def upward_imports(modules: dict[str, str]) -> list[str]:
    """Every import of a module from a layer above its own, as ``"importer:line imports module (layer a -> b)"``,
    for ``modules`` (name -> source)."""
    upward = []
    for name, source in modules.items():
        for line, target in imported(ast.parse(source), set(modules)):
            if layer(target) > layer(name):
                upward.append(f"{name}:{line} imports {target} (layer {layer(name)} -> {layer(target)})")
    return upward


def sources() -> dict[str, str]:
    return {name: path.read_text(encoding="utf-8") for name, path in MODULES.items()}


class TestLayers:
    def test_every_module_has_a_layer(self):
        for name in MODULES:
            layer(name)

    def test_no_import_runs_up_the_layers(self):
        assert upward_imports(sources()) == []

    @pytest.mark.parametrize(("module", "statement"), [
        ("dpcn_med.models.weights", "from dpcn_med.registration import resolve_device"),
        ("dpcn_med.solver.config", "import dpcn_med.refine"),
        ("dpcn_med.geometry", "from dpcn_med import preprocess"),
        ("dpcn_med.devices", "from dpcn_med import register"),
    ])
    def test_an_upward_import_is_found(self, module, statement):
        """At module level or inside a function alike."""
        tree = sources()
        for placed in (statement, f"def late():\n    {statement}\n"):
            upward = upward_imports({**tree, module: f"{tree[module]}\n{placed}\n"})
            assert len(upward) == 1 and upward[0].startswith(f"{module}:")

    def test_a_package_s_submodules_share_its_layer(self):
        assert layer("dpcn_med.io") == layer("dpcn_med.io.images") == 1
        assert layer("dpcn_med.benchmark.runner") == 5
