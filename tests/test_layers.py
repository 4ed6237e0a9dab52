"""The packages keep their layers (issue 42), read from the source's import statements (ast),
those inside functions included:

- the runtime modules of `mosaic` (every module of `mosaic/` itself but the two command lines,
  the edges that offer every command) import neither `mosaic.eval` nor `mosaic.synthetic`;
- at most two `mosaic` modules import `glampoints`: the detector adapter (`mosaic.features`)
  and the `glampoints` command line (`mosaic.glampoints_cli`);
- no `glampoints` module imports `mosaic`: the model package knows no videos;
- no module reads another's private names (`from m import _x`, `m._x`, `obj._x`).

Each check is a pure function of the sources and is shown to catch a fake import.
"""

from __future__ import annotations

import ast
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
MOSAIC = REPO / "mosaic"
# the edges that may import every layer: the command lines offer evaluate, bench and synth
EDGES = {"cli.py", "glampoints_cli.py"}
AROUND_RUNTIME = ("mosaic.eval", "mosaic.synthetic")
# the only mosaic modules that may import glampoints: the adapter, and the glampoints command line
GLAMPOINTS_DOORS = {"mosaic.features", "mosaic.glampoints_cli"}


def module_name(path: Path) -> str:
    """`mosaic/eval/video_eval.py` -> `mosaic.eval.video_eval` (a package's `__init__` its own)."""
    parts = path.relative_to(REPO).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def imported_modules(source: str, module: str) -> set[str]:
    """Every module a source imports, absolute (relative imports resolved against `module`,
    `from a import b` counted as both `a` and `a.b`, since b may be a module)."""
    names: set[str] = set()
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                package = module.split(".")[: len(module.split(".")) - node.level]
                base = ".".join([*package, base] if base else package)
            names.add(base)
            names.update(f"{base}.{alias.name}" for alias in node.names)
    return names


def _within(name: str, packages: tuple[str, ...]) -> bool:
    return any(name == p or name.startswith(p + ".") for p in packages)


def runtime_modules() -> list[Path]:
    """The modules of `mosaic/` itself (not its subpackages), the CLI left out."""
    return sorted(p for p in MOSAIC.glob("*.py") if p.name not in EDGES)


def package_sources(package: str) -> dict[str, str]:
    """module name -> source text of every module of `package` (subpackages included)."""
    return {
        module_name(p): p.read_text(encoding="utf-8")
        for p in sorted((REPO / package).rglob("*.py"))
    }


def layer_breaches(sources: dict[str, str], forbidden: tuple[str, ...]) -> list[str]:
    """`module -> imported` for each import of a `forbidden` package (or its modules) that one
    of `sources` (module name -> source text) makes (`from a import b` named once, as `a`
    when a is forbidden)."""
    breaches = []
    for module, source in sources.items():
        names = imported_modules(source, module)
        for name in names:
            if _within(name, forbidden) and name.rpartition(".")[0] not in names:
                breaches.append(f"{module} -> {name}")
    return sorted(breaches)


def test_imported_modules_resolves_every_form():
    source = (
        "import mosaic.eval.bench as b\n"
        "from mosaic import synthetic\n"
        "def f():\n    from .eval.video_eval import x\n"
    )
    names = imported_modules(source, "mosaic.quality")
    assert {"mosaic.eval.bench", "mosaic.synthetic", "mosaic.eval.video_eval"} <= names


def test_runtime_stages_import_neither_eval_nor_synthetic():
    sources = {module_name(p): p.read_text(encoding="utf-8") for p in runtime_modules()}
    assert {"mosaic.quality", "mosaic.pipeline", "mosaic.runner"} <= set(sources)
    assert layer_breaches(sources, AROUND_RUNTIME) == []
    # the check catches a stage that imports the synthetic data, even inside a function
    sources["mosaic.quality"] += "\ndef f():\n    from mosaic.synthetic.synth import x\n"
    assert layer_breaches(sources, AROUND_RUNTIME) == ["mosaic.quality -> mosaic.synthetic.synth"]


def importers_of(sources: dict[str, str], package: str) -> set[str]:
    """The modules of `sources` that import `package` (or one of its modules)."""
    return {
        module
        for module, source in sources.items()
        if any(_within(name, (package,)) for name in imported_modules(source, module))
    }


def test_at_most_two_mosaic_modules_import_glampoints():
    sources = package_sources("mosaic")
    assert {"mosaic.features", "mosaic.eval.pair_eval", "mosaic.synthetic.synth"} <= set(sources)
    assert len(GLAMPOINTS_DOORS) <= 2
    assert importers_of(sources, "glampoints") == GLAMPOINTS_DOORS
    # the check catches a module that imports glampoints to catch its error
    sources["mosaic.batch"] += "\ndef f():\n    from glampoints.detector import WeightsError\n"
    assert importers_of(sources, "glampoints") - GLAMPOINTS_DOORS == {"mosaic.batch"}


def test_no_glampoints_module_imports_mosaic():
    sources = package_sources("glampoints")
    assert {"glampoints.detector", "glampoints.training", "glampoints"} <= set(sources)
    assert importers_of(sources, "mosaic") == set()
    # the check catches a lazy import of the application's I/O
    sources["glampoints.training"] += "\ndef f():\n    from mosaic.io import same_file\n"
    assert importers_of(sources, "mosaic") == {"glampoints.training"}


# objects whose private attributes are their own class's: self and cls, and `other` in the
# methods that build a copy of their own class; torch's module tree and its fused kernels
OWN = {"self", "cls", "other", "super()"}
THIRD_PARTY = ("torch.", "module._modules", "mk.", "os._exit")


def private_reads(sources: dict[str, str]) -> list[str]:
    """`module: expression` for each private (single underscore) name a module reads from
    another module or object."""
    reads = []
    for module, source in sources.items():
        for node in ast.walk(ast.parse(source)):
            if isinstance(node, ast.ImportFrom):
                reads += [
                    f"{module}: from {node.module} import {alias.name}"
                    for alias in node.names
                    if alias.name.startswith("_") and not alias.name.startswith("__")
                ]
            elif isinstance(node, ast.Attribute) and node.attr.startswith("_"):
                owner = ast.unparse(node.value)
                text = f"{owner}.{node.attr}"
                if node.attr.startswith("__") or owner in OWN or text.startswith(THIRD_PARTY):
                    continue
                reads.append(f"{module}: {text}")
    return sorted(reads)


def test_no_module_reads_private_names_of_another():
    sources = {**package_sources("mosaic"), **package_sources("glampoints")}
    assert private_reads(sources) == []
    # the check catches a private import and a private attribute read
    sources["mosaic.batch"] += "\nfrom mosaic.pipeline import _x\ny = builder._records\n"
    assert private_reads(sources) == [
        "mosaic.batch: builder._records",
        "mosaic.batch: from mosaic.pipeline import _x",
    ]
