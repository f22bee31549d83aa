"""The layers import downwards only: ``pipeline/`` never imports ``tuner`` (it knows nothing of Optuna), and the tuner's
library modules never import the command layer (``tuner/commands``, ``tuner/cli.py``; ``python -m tuner``'s
``__main__`` is its entry), so that a Python caller of
``tuner.compare`` gets no argparse code and a command can be rewritten without touching the library. Every import
statement is read from the source (those inside functions too), not only the module's top."""
from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def imported_modules(path: Path) -> list[tuple[int, str]]:
    """(line, module) of every import in ``path``: ``import a.b`` -> a.b; ``from a.b import c`` -> a.b and a.b.c
    (``from tuner import commands`` imports the package tuner.commands)."""
    out = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            out += [(node.lineno, a.name) for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            out.append((node.lineno, node.module))
            out += [(node.lineno, f"{node.module}.{a.name}") for a in node.names]
    return out


def offenders(files, banned: str) -> list[str]:
    return [f"{p}:{line} imports {mod}" for p in files for line, mod in imported_modules(p)
            if mod == banned or mod.startswith(banned + ".")]


def test_imported_modules_sees_imports_inside_functions(tmp_path):
    """The reader itself: the old tuner/compare.py imported the command layer inside a function."""
    p = tmp_path / "m.py"
    p.write_text("import os\n\ndef f():\n    from tuner.commands.viz import resolve_source\n    from tuner import commands\n")
    mods = [m for _, m in imported_modules(p)]
    assert "tuner.commands.viz" in mods and "tuner.commands" in mods and "os" in mods
    assert offenders([p], "tuner.commands") != []


def test_the_tuner_library_never_imports_the_command_layer():
    tuner = ROOT / "tuner"
    files = [p for p in sorted(tuner.rglob("*.py"))
             if (tuner / "commands") not in p.parents and p not in (tuner / "cli.py", tuner / "__main__.py")]
    assert len(files) > 20, files  # the library's modules were found
    assert offenders(files, "tuner.commands") == []
    assert offenders(files, "tuner.cli") == []


def test_pipeline_never_imports_the_tuner():
    files = sorted((ROOT / "pipeline").rglob("*.py"))
    assert len(files) > 20, files
    assert offenders(files, "tuner") == []
    assert offenders(files, "optuna") == []



def module_graph(root: Path = ROOT) -> dict[str, set[str]]:
    """{module: modules of pipeline/ and tuner/ it imports}, package ``__init__`` modules left out (they re-export
    their submodules by design, so a submodule importing its package's name is no cycle)."""
    mods = {".".join(p.relative_to(root).with_suffix("").parts): p
            for pkg in ("pipeline", "tuner") for p in (root / pkg).rglob("*.py") if p.name != "__init__.py"}

    def resolve(name: str) -> str | None:  # a.b.c -> the longest prefix that is a module of ours
        while name and name not in mods:
            name = name.rpartition(".")[0]
        return name or None
    return {m: {r for _, t in imported_modules(p) if (r := resolve(t)) and r != m} for m, p in mods.items()}


def import_cycle(graph: dict[str, set[str]]) -> list[str]:
    """One cycle of ``graph`` ([] if none), found by the standard library's topological sort."""
    import graphlib
    try:
        tuple(graphlib.TopologicalSorter(graph).static_order())
    except graphlib.CycleError as e:
        return list(e.args[1])
    return []


def test_no_import_cycles_between_modules():
    """Imports inside functions count: a lazy import that closes a cycle (tuner.freeze <-> tuner.study, once)
    still ties two modules together so that neither can be read or changed without the other."""
    graph = module_graph()
    assert len(graph) > 100 and "tuner.protocol" in graph["tuner.freeze"]  # the graph was built
    assert import_cycle(graph) == []


def test_the_cycle_check_sees_a_lazy_import_cycle(tmp_path):
    (tmp_path / "tuner").mkdir()
    (tmp_path / "pipeline").mkdir()
    (tmp_path / "tuner" / "a.py").write_text("from tuner.b import f\n")
    (tmp_path / "tuner" / "b.py").write_text("def f():\n    from tuner.a import g\n")
    assert sorted(set(import_cycle(module_graph(tmp_path)))) == ["tuner.a", "tuner.b"]
