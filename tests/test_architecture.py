"""The layers of estcal run one way (docs/architecture.md).

The import graph is built from the code itself: every ``import`` and ``from … import`` of
every module, at module level and inside functions, absolute and relative (and
``importlib.import_module("estcal.…")`` with a literal name). The tests fail on

(a) an import from a lower layer to a higher one,
(b) an import cycle between modules,
(c) a cycle between folders of the same layer,
(d) a function longer than :data:`MAX_FUNCTION_LINES` lines (``def`` line to last line).

Run ``python tests/test_architecture.py`` to print the findings and the folder graph, and
``python tests/test_architecture.py --write-docs`` to redraw the graph in docs/architecture.md
(``test_docs_graph_is_current`` fails when the page and the code disagree).
"""
from __future__ import annotations

import ast
import sys
from collections import defaultdict
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
DOC = REPO / "docs" / "architecture.md"
MAX_FUNCTION_LINES = 120

# The layer of each folder of estcal/ (docs/architecture.md). A folder may import its own layer
# and the layers below, never above. A new folder gets a row here before it gets code.
#
#   layer | folders
#   ------+------------------------------------------------------------------------
LAYERS = {
    "base": 0,                                                                    # errors, units, files
    "kinematics": 1, "robots": 1, "plots": 1, "scale": 1,                         # models, figures, runner
    "effects": 2, "parallel": 2,                                                  # effects, Gough–Stewart
    "io": 3,                                                                      # files users write
    "methods": 4, "validation": 4,                                                # measurement models
    "identify": 5,                                                                # identifiable parameters
    "estimate": 6,                                                                # estimators
    "simulate": 7, "sessions": 7, "compensation": 7, "design": 7,                 # the analyses
    "discrepancy": 7, "intake": 7,
    "report": 8,                                                                  # --report DIR
    "workflows": 9,                                                               # one module per job
    "cli": 10, "api": 10,                                                         # the two faces
    "__init__": 11,                                                               # lazy public names
}

# Imports forbidden although the layers would allow them: (importer prefix, imported prefix).
FORBIDDEN = [("estcal.api", "estcal.cli"), ("estcal.workflows", "estcal.cli")]

# Work in progress, each entry with who removes it. An entry that no longer occurs fails the test
# too (delete it here): the lists only shrink.
KNOWN_UPWARD: dict[tuple[str, str], str] = {}
KNOWN_FORBIDDEN: dict[tuple[str, str], str] = {}
KNOWN_CYCLES: dict[frozenset, str] = {}
# folders the function-length rule skips (emptied once the command modules were split into workflows)
SKIP_FUNCTION_LENGTH: list[str] = []
KNOWN_LONG: dict[str, str] = {}


# ---------------------------------------------------------------------------------------------
# the checker (also used on a fake package by the tests at the end)

def module_files(root: Path, package: str) -> dict[str, Path]:
    """``{module name: file}`` of every module of ``root/package``."""
    out = {}
    for p in sorted((root / package).rglob("*.py")):
        parts = p.relative_to(root).with_suffix("").parts
        if parts[-1] == "__init__":
            parts = parts[:-1]
        out[".".join(parts)] = p
    return out


def _base_of(module: str, path: Path, node: ast.ImportFrom) -> str:
    if not node.level:
        return node.module or ""
    pkg = module.split(".") if path.name == "__init__.py" else module.split(".")[:-1]
    pkg = pkg[: len(pkg) - (node.level - 1)]
    return ".".join(pkg + ([node.module] if node.module else []))


def _known(name: str, modules) -> str | None:
    while name and name not in modules:
        name = name.rpartition(".")[0]
    return name or None


def imports_of(module: str, path: Path, modules, package: str):
    """``[(target module, line)]`` of every import in ``path`` that names a module of the package."""
    out = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        names = []
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = _base_of(module, path, node)
            names = [f"{base}.{a.name}" if f"{base}.{a.name}" in modules else base for a in node.names]
        elif (isinstance(node, ast.Call) and getattr(node.func, "attr", getattr(node.func, "id", None)) == "import_module"
              and node.args and isinstance(node.args[0], ast.Constant) and isinstance(node.args[0].value, str)):
            names = [node.args[0].value]
        for n in names:
            if n == package or n.startswith(package + "."):
                target = _known(n, modules)
                if target and target != module:
                    out.append((target, node.lineno))
    return out


def build_graph(root: Path = REPO, package: str = "estcal"):
    """``(modules, edges)``: ``edges[a][b]`` = the first line of ``a`` that imports ``b``."""
    modules = module_files(root, package)
    edges: dict[str, dict[str, int]] = defaultdict(dict)
    for m, p in modules.items():
        for target, line in imports_of(m, p, modules, package):
            edges[m].setdefault(target, line)
    return modules, edges


def folder_of(module: str) -> str:
    """``estcal.io.dataset`` → ``io``; ``estcal.api`` → ``api``; ``estcal`` → ``__init__`` (the face)."""
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else "__init__"


def layer_of(module: str, layers=LAYERS) -> int:
    folder = folder_of(module)
    if folder not in layers:
        raise KeyError(f"{module}: the folder {folder!r} has no layer — add it to LAYERS in {Path(__file__).name} "
                       f"and to docs/architecture.md")
    return layers[folder]


def upward_imports(edges, layers=LAYERS):
    """``{(a, b): line}`` for each import of ``b`` by ``a`` whose layer is below ``b``'s."""
    return {(a, b): line for a, bs in edges.items() for b, line in bs.items()
            if layer_of(a, layers) < layer_of(b, layers)}


def forbidden_imports(edges, rules=FORBIDDEN):
    """``{(a, b): line}`` for each import that a rule of ``rules`` forbids."""
    return {(a, b): line for a, bs in edges.items() for b, line in bs.items()
            for src, dst in rules if _under(a, src) and _under(b, dst)}


def _under(module: str, prefix: str) -> bool:
    return module == prefix or module.startswith(prefix + ".")


def strongly_connected(nodes, succ):
    """The strongly connected components of more than one node (Tarjan, iterative)."""
    index, low, on, stack, out, counter = {}, {}, set(), [], [], [0]
    for root in nodes:
        if root in index:
            continue
        work = [(root, iter(succ.get(root, ())))]
        index[root] = low[root] = counter[0]
        counter[0] += 1
        stack.append(root)
        on.add(root)
        while work:
            v, it = work[-1]
            for w in it:
                if w not in index:
                    index[w] = low[w] = counter[0]
                    counter[0] += 1
                    stack.append(w)
                    on.add(w)
                    work.append((w, iter(succ.get(w, ()))))
                    break
                if w in on:
                    low[v] = min(low[v], index[w])
            else:
                work.pop()
                if work:
                    low[work[-1][0]] = min(low[work[-1][0]], low[v])
                if low[v] == index[v]:
                    comp = set()
                    while True:
                        w = stack.pop()
                        on.discard(w)
                        comp.add(w)
                        if w == v:
                            break
                    if len(comp) > 1:
                        out.append(frozenset(comp))
    return out


def module_cycles(modules, edges):
    return strongly_connected(sorted(modules), {a: sorted(bs) for a, bs in edges.items()})


def folder_edges(edges):
    """``{(folder a, folder b): [module arrows]}`` between different folders."""
    out = defaultdict(list)
    for a, bs in edges.items():
        for b in bs:
            fa, fb = folder_of(a), folder_of(b)
            if fa != fb:
                out[(fa, fb)].append(f"{a} -> {b}")
    return out


def same_layer_folder_cycles(edges, layers=LAYERS):
    succ = defaultdict(set)
    for fa, fb in folder_edges(edges):
        if layers.get(fa) == layers.get(fb):
            succ[fa].add(fb)
    return strongly_connected(sorted(succ), {k: sorted(v) for k, v in succ.items()})


def long_functions(root: Path = REPO, package: str = "estcal", limit: int = MAX_FUNCTION_LINES, skip=()):
    """``{"path:qualified.name": lines}`` of each function longer than ``limit`` lines
    (from its ``def`` line to its last line; nested functions count in their parent too)."""
    out = {}
    for p in sorted((root / package).rglob("*.py")):
        rel = p.relative_to(root).as_posix()
        if any(rel.startswith(s) for s in skip):
            continue

        def visit(node, prefix):
            for child in ast.iter_child_nodes(node):
                if isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
                    name = f"{prefix}{child.name}"
                    if not isinstance(child, ast.ClassDef):
                        n = child.end_lineno - child.lineno + 1
                        if n > limit:
                            out[f"{rel}:{name}"] = n
                    visit(child, name + ".")
                else:
                    visit(child, prefix)

        visit(ast.parse(p.read_text(), str(p)), "")
    return out


def _is_command_decorator(d) -> bool:
    """``@command(...)``, ``@app.command(...)``, ``@x.command`` …: a decorator that registers a CLI command."""
    f = d.func if isinstance(d, ast.Call) else d
    return (isinstance(f, ast.Name) and f.id == "command") or (isinstance(f, ast.Attribute) and f.attr == "command")


def closure_commands(root: Path = REPO, package: str = "estcal", folder: str = "cli", decorator: str = "app.py"):
    """CLI commands not defined at module level: ``{"path:name": why}`` for every function named
    ``register`` (the old route: commands defined inside ``register(app)``), every command decorator on
    a function nested in another, and every ``app.command(...)(f)`` call inside a function; and every
    module of ``cli/commands`` that defines no module-level command. ``decorator``: the module whose
    ``command`` decorator itself registers the function (the one place an ``app.command`` call belongs)."""
    out = {}
    for p in sorted((root / package / folder).rglob("*.py")):
        rel = p.relative_to(root).as_posix()
        tree = ast.parse(p.read_text(), str(p))
        top = 0

        def visit(node, depth):
            nonlocal top
            for child in ast.iter_child_nodes(node):
                if isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef)):
                    if child.name == "register":
                        out[f"{rel}:{child.name}"] = f"line {child.lineno}: a register() route"
                    if any(_is_command_decorator(d) for d in child.decorator_list):
                        if depth:
                            out[f"{rel}:{child.name}"] = f"line {child.lineno}: a command defined inside a function"
                        else:
                            top += 1
                    visit(child, depth + 1)
                elif (depth and p.name != decorator and isinstance(child, ast.Call)
                      and isinstance(child.func, ast.Call) and _is_command_decorator(child.func)):
                    out[f"{rel}:line {child.lineno}"] = "a command registered inside a function"
                    visit(child, depth)
                else:
                    visit(child, depth)

        visit(tree, 0)
        if p.parent.name == "commands" and p.name != "__init__.py" and not top:
            out[f"{rel}"] = "defines no module-level command"
    return out


# ---------------------------------------------------------------------------------------------
# the rules on estcal

@pytest.fixture(scope="module")
def graph():
    return build_graph()


def _ratchet(found: dict, known: dict, what: str):
    new = sorted(k for k in found if k not in known)
    gone = sorted(k for k in known if k not in found)
    msg = []
    if new:
        msg.append(f"{what}:\n  " + "\n  ".join(f"{k}: {found[k]}" for k in new))
    if gone:
        msg.append(f"no longer found — remove from the known list of {Path(__file__).name}:\n  "
                   + "\n  ".join(str(k) for k in gone))
    assert not msg, "\n".join(msg)


def test_every_folder_has_a_layer(graph):
    modules, _ = graph
    missing = sorted({folder_of(m) for m in modules} - set(LAYERS))
    assert not missing, f"folders without a layer in LAYERS: {missing}"


def test_no_upward_import(graph):
    _, edges = graph
    found = {k: f"line {line} (layer {layer_of(k[0])} imports layer {layer_of(k[1])})"
             for k, line in upward_imports(edges).items()}
    _ratchet(found, KNOWN_UPWARD, "imports from a lower layer to a higher one")


def test_no_forbidden_import(graph):
    _, edges = graph
    found = {k: f"line {line}" for k, line in forbidden_imports(edges).items()}
    _ratchet(found, KNOWN_FORBIDDEN, "forbidden imports (the Python API and the workflows never import the CLI)")


def test_no_module_cycle(graph):
    modules, edges = graph
    found = {c: " <-> ".join(sorted(c)) for c in module_cycles(modules, edges)}
    _ratchet(found, KNOWN_CYCLES, "import cycles between modules")


def test_no_folder_cycle_within_a_layer(graph):
    _, edges = graph
    cycles = same_layer_folder_cycles(edges)
    arrows = folder_edges(edges)
    assert not cycles, "folders of one layer importing each other:\n" + "\n".join(
        f"  {sorted(c)}: " + "; ".join(a for (fa, fb), v in arrows.items() if fa in c and fb in c for a in v)
        for c in cycles)


def test_cli_commands_are_defined_at_module_level():
    """docs/architecture.md, "cli": every command is a module-level function under ``@command``
    (readers and tools see it); the ``register(app)`` closures are gone for good."""
    found = closure_commands()
    assert not found, "CLI commands not at module level:\n" + "\n".join(f"  {k}: {v}" for k, v in found.items())


def test_no_long_function():
    found = {k: f"{n} lines" for k, n in long_functions(skip=SKIP_FUNCTION_LENGTH).items()}
    _ratchet(found, KNOWN_LONG, f"functions longer than {MAX_FUNCTION_LINES} lines (split them into named steps)")


# ---------------------------------------------------------------------------------------------
# the checker can fail: a fake package with one planted fault of each kind

FAKE_LAYERS = {"low": 0, "mid": 1, "high": 2, "__init__": 3}


def _fake_package(tmp_path, files: dict[str, str]) -> Path:
    for rel, text in {"pkg/__init__.py": "", "pkg/low/__init__.py": "", "pkg/mid/__init__.py": "",
                      "pkg/high/__init__.py": "", **files}.items():
        p = tmp_path / rel
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_text(text)
    return tmp_path


def test_checker_finds_an_upward_import_inside_a_function(tmp_path):
    root = _fake_package(tmp_path, {
        "pkg/low/a.py": "import os\n\ndef f():\n    from ..high.c import g\n    return g()\n",
        "pkg/mid/b.py": "from pkg.low.a import f\n",
        "pkg/high/c.py": "from pkg.mid import b\n\ndef g():\n    return 1\n"})
    _, edges = build_graph(root, "pkg")
    assert edges["pkg.mid.b"] == {"pkg.low.a": 1} and edges["pkg.high.c"] == {"pkg.mid.b": 1}
    assert upward_imports(edges, FAKE_LAYERS) == {("pkg.low.a", "pkg.high.c"): 4}


def test_checker_finds_cycles_of_modules_and_of_folders(tmp_path):
    root = _fake_package(tmp_path, {
        "pkg/low/a.py": "from . import b\n",
        "pkg/low/b.py": "import importlib\nx = importlib.import_module('pkg.low.a')\n",
        "pkg/mid/c.py": "import pkg.extra.d\n",
        "pkg/extra/__init__.py": "", "pkg/extra/d.py": "def f():\n    from pkg.mid import c\n"})
    modules, edges = build_graph(root, "pkg")
    assert module_cycles(modules, edges) == [frozenset({"pkg.low.a", "pkg.low.b"})] or \
        set(module_cycles(modules, edges)) == {frozenset({"pkg.low.a", "pkg.low.b"}),
                                               frozenset({"pkg.mid.c", "pkg.extra.d"})}
    assert same_layer_folder_cycles(edges, {**FAKE_LAYERS, "extra": 1}) == [frozenset({"mid", "extra"})]
    assert same_layer_folder_cycles(edges, {**FAKE_LAYERS, "extra": 0}) == []  # then it is an upward import
    assert upward_imports(edges, {**FAKE_LAYERS, "extra": 0}) == {("pkg.extra.d", "pkg.mid.c"): 2}


def test_checker_finds_a_long_function(tmp_path):
    body = "".join(f"    x{i} = {i}\n" for i in range(MAX_FUNCTION_LINES))
    root = _fake_package(tmp_path, {"pkg/mid/long.py": f"class A:\n    def ok(self):\n        pass\n\n"
                                                       f"    def long(self):\n    {body.replace(chr(10) + '    ', chr(10) + '        ')}"
                                                       f"\n\ndef short():\n{body[:40]}\n"})
    found = long_functions(root, "pkg")
    assert found == {"pkg/mid/long.py:A.long": MAX_FUNCTION_LINES + 1}
    assert long_functions(root, "pkg", skip=["pkg/mid/"]) == {}


def test_checker_finds_a_command_inside_a_function(tmp_path):
    root = _fake_package(tmp_path, {
        "pkg/cli/__init__.py": "", "pkg/cli/commands/__init__.py": "",
        "pkg/cli/commands/good.py": "@command('good')\ndef good():\n    pass\n",
        "pkg/cli/commands/old.py": "def register(app):\n    @app.command('old')\n    def old():\n        pass\n",
        "pkg/cli/commands/call.py": "@command('x')\ndef x():\n    pass\n\ndef mount(app, f):\n    app.command('y')(f)\n"})
    found = closure_commands(root, "pkg")
    assert set(found) == {"pkg/cli/commands/old.py:register", "pkg/cli/commands/old.py:old",
                          "pkg/cli/commands/old.py", "pkg/cli/commands/call.py:line 6"}


def test_checker_counts_the_real_graph(graph):
    """A spot check of the builder on estcal: known arrows of each form are seen."""
    modules, edges = graph
    assert "estcal.base.errors" in modules
    assert "estcal.base.errors" in edges["estcal.io.columns"]           # absolute, module level
    assert "estcal.base.atomic" in edges["estcal.base.jsonio"]          # relative, module level
    assert not any(b.startswith("estcal.") for b in edges.get("estcal.base.errors", {}))


# ---------------------------------------------------------------------------------------------
# the graph of docs/architecture.md

BEGIN, END = "<!-- folder graph: begin (python tests/test_architecture.py --write-docs) -->", \
    "<!-- folder graph: end -->"


def folder_graph_markdown(edges) -> str:
    """The folders by layer and their import arrows, as a mermaid flowchart (top layer first)."""
    arrows = folder_edges(edges)
    by_layer = defaultdict(list)
    for f, n in LAYERS.items():
        by_layer[n].append(f)
    present = {folder_of(m) for m in build_graph()[0]}
    lines = ["```mermaid", "flowchart TB"]
    for n in sorted(by_layer, reverse=True):
        names = [f for f in by_layer[n] if f in present]
        if names:
            lines.append(f'  subgraph L{n}["layer {n}"]')
            lines += [f'    {_node(f)}["{_label(f)}"]' for f in names]
            lines.append("  end")
    for (fa, fb), v in sorted(arrows.items(), key=lambda kv: (-LAYERS[kv[0][0]], kv[0])):
        lines.append(f"  {_node(fa)} -->|{len(v)}| {_node(fb)}")
    lines.append("```")
    return "\n".join(lines)


def _node(folder):
    return "face" if folder == "__init__" else folder


def _label(folder):
    return {"__init__": "estcal/__init__.py", "api": "estcal/api.py"}.get(folder, f"{folder}/")


def _doc_block(edges) -> str:
    return f"{BEGIN}\n{folder_graph_markdown(edges)}\n{END}"


def test_docs_graph_is_current(graph):
    _, edges = graph
    text = DOC.read_text()
    assert BEGIN in text and END in text, f"{DOC}: the generated folder graph is missing"
    current = text[text.index(BEGIN): text.index(END) + len(END)]
    assert current == _doc_block(edges), \
        f"{DOC}: the folder graph differs from the code — run python tests/test_architecture.py --write-docs"


def _write_docs() -> None:
    _, edges = build_graph()
    text = DOC.read_text()
    head, tail = text.split(BEGIN)[0], text.split(END)[1]
    DOC.write_text(head + _doc_block(edges) + tail)
    print(f"wrote the folder graph into {DOC}")


def _print_findings() -> None:
    modules, edges = build_graph()
    up = upward_imports(edges)
    cycles = module_cycles(modules, edges)
    long = long_functions()
    print(f"{len(modules)} modules, {sum(len(v) for v in edges.values())} imports between them")
    print(f"upward imports: {len(up)}")
    for (a, b), line in sorted(up.items()):
        print(f"  {a}:{line} -> {b}  (layer {layer_of(a)} -> {layer_of(b)})")
    forb = forbidden_imports(edges)
    print(f"forbidden imports: {len(forb)}")
    for (a, b), line in sorted(forb.items()):
        print(f"  {a}:{line} -> {b}")
    print(f"module cycles: {len(cycles)}")
    for c in cycles:
        print("  " + " <-> ".join(sorted(c)))
    print(f"folder cycles within a layer: {same_layer_folder_cycles(edges)}")
    print(f"functions over {MAX_FUNCTION_LINES} lines: {len(long)}")
    for k, n in sorted(long.items(), key=lambda kv: -kv[1]):
        print(f"  {n:4d}  {k}")


if __name__ == "__main__":
    if "--write-docs" in sys.argv[1:]:
        _write_docs()
    else:
        _print_findings()
