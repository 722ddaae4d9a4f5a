"""The packages form layers: no import cycle between them, counting the imports made inside
functions (a lazy import may spare start-up time, but one that points back up is a hidden
cycle) and those made only for type checking."""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def _package(module: str) -> str | None:
    """The package a module belongs to: ``annotator.<name>`` (a top-level module counts as
    its own), ``viewer``; None outside the project."""
    parts = module.split(".")
    if parts[0] == "viewer":
        return "viewer"
    if parts[0] != "annotator" or len(parts) < 2:
        return None
    return f"annotator.{parts[1]}"


def _imports() -> dict[str, dict[str, str]]:
    """package -> {imported package: a module that imports it}."""
    edges: dict[str, dict[str, str]] = {}
    for folder in ("annotator", "viewer"):
        for path in sorted((ROOT / folder).rglob("*.py")):
            module = ".".join(path.relative_to(ROOT).with_suffix("").parts)
            source = _package(module.removesuffix(".__init__"))
            if source is None:  # annotator/__init__.py: the public API sits above everything
                continue
            for node in ast.walk(ast.parse(path.read_text())):
                if isinstance(node, ast.Import):
                    names = [a.name for a in node.names]
                elif isinstance(node, ast.ImportFrom) and node.module and not node.level:
                    names = [node.module]
                else:
                    continue
                for name in names:
                    target = _package(name)
                    if target is not None and target != source:
                        edges.setdefault(source, {}).setdefault(target, module)
    return edges


def _cycle(edges: dict[str, dict[str, str]]) -> list[str] | None:
    """One cycle of the graph, as the packages along it, or None."""
    state: dict[str, int] = {}  # 1: on the current path, 2: done
    path: list[str] = []

    def visit(node: str) -> list[str] | None:
        state[node] = 1
        path.append(node)
        for nxt in sorted(edges.get(node, {})):
            if state.get(nxt) == 1:
                return path[path.index(nxt) :] + [nxt]
            if nxt not in state:
                found = visit(nxt)
                if found:
                    return found
        path.pop()
        state[node] = 2
        return None

    for node in sorted(edges):
        if node not in state:
            found = visit(node)
            if found:
                return found
    return None


def test_no_import_cycle_between_packages() -> None:
    edges = _imports()
    cycle = _cycle(edges)
    if cycle:
        steps = [f"{a} -> {b} ({edges[a][b]})" for a, b in zip(cycle, cycle[1:])]
        raise AssertionError("import cycle: " + "; ".join(steps))


def test_the_checker_finds_a_cycle() -> None:
    edges = {"a": {"b": "a.x"}, "b": {"c": "b.y"}, "c": {"a": "c.z"}, "d": {"a": "d.w"}}
    assert _cycle(edges) == ["a", "b", "c", "a"]
    assert _cycle({"a": {"b": "a.x"}, "b": {}}) is None


def test_no_import_cycle_between_the_viewers_modules() -> None:
    """The viewer's modules form layers too: a page (session, editor) knows its server only
    as :class:`viewer.page.host.ReviewHost`, never by importing viewer.server.app."""
    edges: dict[str, dict[str, str]] = {}
    modules = {
        ".".join(p.relative_to(ROOT).with_suffix("").parts).removesuffix(".__init__"): p
        for p in sorted((ROOT / "viewer").rglob("*.py"))
    }
    for module, path in modules.items():
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and node.module and not node.level:
                names = [node.module] + [f"{node.module}.{a.name}" for a in node.names]
            elif isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            else:
                continue
            for name in names:
                if name in modules and name != module and not module.startswith(name + "."):
                    edges.setdefault(module, {}).setdefault(name, module)
    assert len(modules) > 20 and edges, "the viewer's modules were not found"
    cycle = _cycle(edges)
    assert cycle is None, "import cycle: " + " -> ".join(cycle or [])
    groups = {m: m.split(".")[1] for m in modules if m.count(".") == 2}
    order = {"drawing": 0, "page": 1, "server": 2}  # each group imports only those below it
    upward = [
        f"{a} -> {b}"
        for a, targets in edges.items()
        for b in targets
        if a in groups and b in groups and order[groups[b]] > order[groups[a]]
    ]
    assert not upward, "a group imports one above it: " + "; ".join(upward)


def _private_imports() -> list[str]:
    """Every ``from annotator.x import _name`` (or viewer's) in the project's modules."""
    found = []
    for folder in ("annotator", "viewer"):
        for path in sorted((ROOT / folder).rglob("*.py")):
            for node in ast.walk(ast.parse(path.read_text())):
                if not (isinstance(node, ast.ImportFrom) and node.module and not node.level):
                    continue
                if node.module.split(".")[0] not in ("annotator", "viewer"):
                    continue
                for a in node.names:
                    if a.name.startswith("_") and not a.name.startswith("__"):
                        rel = path.relative_to(ROOT)
                        found.append(f"{rel}:{node.lineno} {node.module}.{a.name}")
    return found


def test_no_private_name_is_imported_from_another_module() -> None:
    """A name with a leading underscore is its module's own: a module that needs it from
    another needs it made public (and documented) there."""
    found = _private_imports()
    assert not found, "private names imported across modules: " + "; ".join(found)


def test_commands_only_parse_and_print() -> None:
    """Every command module stays a thin layer over its library function: at most 200
    lines."""
    long = [
        f"{p.relative_to(ROOT)} ({n} lines)"
        for p in sorted((ROOT / "annotator" / "commands").glob("*.py"))
        if (n := len(p.read_text().splitlines())) > 200
    ]
    assert not long, "command modules over 200 lines: " + ", ".join(long)


#: The packages' layers, lowest first (README, Development): each imports only from layers
#: below its own. A new package takes the lowest layer above everything it imports.
LAYERS = [
    ["errors", "noise", "summary"],
    ["geometry", "values"],
    ["io", "pnp", "rendering", "symmetry"],
    ["markers"],
    ["dataset", "detection"],
    ["calibration", "formats", "parts", "refinement", "review", "runner"],
    ["ingest", "occlusion", "physics", "repair"],
    ["annotation", "evaluation", "export", "synthesis"],
    ["estimation", "sites", "twins", "viewer"],
    ["commands"],
    ["cli"],
    ["__main__"],
]


def _layer_of() -> dict[str, int]:
    return {
        ("viewer" if name == "viewer" else f"annotator.{name}"): k
        for k, names in enumerate(LAYERS)
        for name in names
    }


def test_every_import_points_down_the_layers() -> None:
    layer = _layer_of()
    edges = _imports()
    unplaced = sorted((set(edges) | {b for t in edges.values() for b in t}) - set(layer))
    assert not unplaced, "packages in no layer of LAYERS: " + ", ".join(unplaced)
    upward = [
        f"{a} -> {b} ({module})"
        for a, targets in edges.items()
        for b, module in targets.items()
        if layer[b] >= layer[a]
    ]
    assert not upward, "imports not pointing down the layers: " + "; ".join(upward)


#: A function longer than this needs a reason in its docstring ("Over 80 lines: ...").
MAX_FUNCTION_LINES = 80


def _long_functions() -> list[tuple[str, int, bool]]:
    """Every function of the project over MAX_FUNCTION_LINES (docstring included): where,
    its length, whether its docstring states why."""
    found = []
    for folder in ("annotator", "viewer"):
        for path in sorted((ROOT / folder).rglob("*.py")):
            for node in ast.walk(ast.parse(path.read_text())):
                if not isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                    continue
                assert node.end_lineno is not None
                n = node.end_lineno - node.lineno + 1
                if n > MAX_FUNCTION_LINES:
                    doc = ast.get_docstring(node) or ""
                    where = f"{path.relative_to(ROOT)}:{node.lineno} {node.name}"
                    found.append((where, n, "Over 80 lines: " in doc))
    return found


def test_no_function_is_long_without_a_reason() -> None:
    found = _long_functions()
    unexplained = [f"{w} ({n} lines)" for w, n, why in found if not why]
    assert not unexplained, "functions over 80 lines with no reason: " + ", ".join(unexplained)
    assert len(found) <= 2, "more than two functions over 80 lines: " + ", ".join(
        w for w, _, _ in found
    )


#: Summaries that are not a stage's return value: the paper's AP over a set of scenes is one
#: score of :class:`annotator.evaluation.evaluate.EvaluationReport`, not what a stage did.
NOT_STAGES = {"annotator.evaluation.metrics.Summary"}


def _summary_classes() -> list[str]:
    """Every class named ``*Summary`` in annotator/, as ``module.Class``."""
    found = []
    for path in sorted((ROOT / "annotator").rglob("*.py")):
        module = ".".join(path.relative_to(ROOT).with_suffix("").parts).removesuffix(".__init__")
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ClassDef) and node.name.endswith("Summary"):
                found.append(f"{module}.{node.name}")
    return found


def test_every_stage_summary_satisfies_the_protocol() -> None:
    """What every stage returns answers :class:`annotator.summary.StageSummary` (counts,
    warnings, written paths, text, to_json, exit status), checked at run time."""
    import importlib

    from annotator.summary import StageSummary

    names = [n for n in _summary_classes() if n not in NOT_STAGES]
    assert len(names) >= 15, names
    missing = []
    for name in names:
        module, _, cls = name.rpartition(".")
        if not issubclass(getattr(importlib.import_module(module), cls), StageSummary):
            missing.append(name)
    assert not missing, "summaries not satisfying StageSummary: " + ", ".join(missing)


def test_commands_end_through_the_summary() -> None:
    """A command prints a stage's summary through :func:`annotator.commands.finish` (or
    :func:`~annotator.commands.show`): none calls ``to_json`` or ``json.dumps`` itself,
    except ``check`` (its report is a list of problems, not a stage's summary) and
    ``twin-report`` and ``evaluate`` (which write their JSON to a file)."""
    own_json = {"check.py", "twin_report.py", "evaluate.py"}
    found = []
    for path in sorted((ROOT / "annotator" / "commands").glob("*.py")):
        if path.name in own_json or path.name == "__init__.py":
            continue
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Attribute) and node.attr in ("to_json", "dumps", "line"):
                found.append(f"{path.relative_to(ROOT)}:{node.lineno} .{node.attr}")
    assert not found, "commands printing a summary themselves: " + "; ".join(found)


def test_evaluate_names_its_scores_only_in_the_registry() -> None:
    """A score of ``evaluate`` is registered once (:mod:`annotator.evaluation.scores`): the
    command's options and the rules of which needs what come from there, so neither the
    command nor the evaluation names a score's option."""
    options = ["--bop19", "--bop24", "--coco-results", "--physics"]
    for rel in ("annotator/commands/evaluate.py", "annotator/evaluation/dataset.py"):
        text = (ROOT / rel).read_text()
        named = [o for o in options if o in text]
        assert not named, f"{rel} names {named}: register them in evaluation/scores.py"


def test_one_noise_record_and_one_least_squares_loop() -> None:
    """The measurement noise is one record (:class:`annotator.noise.NoiseModel`) and every
    solver iterates with :func:`annotator.geometry.least_squares.levenberg_marquardt`: no
    other ``*Noise*`` class, and each solver module calls the one loop."""
    noise = []
    for path in sorted((ROOT / "annotator").rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ClassDef) and "Noise" in node.name:
                noise.append(f"{path.relative_to(ROOT)}:{node.lineno} {node.name}")
    assert len(noise) == 1 and noise[0].startswith("annotator/noise.py"), noise
    solvers = ["pnp/multiview.py", "pnp/bundle.py", "calibration/bundle.py", "refinement/depth.py"]
    for rel in solvers:
        assert "levenberg_marquardt(" in (ROOT / "annotator" / rel).read_text(), rel
