"""The import rules of docs/ARCHITECTURE.md, checked on the source: each layer imports only the layers its rule
allows, the server's run-time path imports no torch, and no two modules import each other (directly or around a
circle), function-level imports included.

The import graph is built with `ast` from every module of `ofera` and `ofera_protocol` (an `import` inside
`if TYPE_CHECKING:` does not count: it never runs).
"""

from __future__ import annotations

import ast
import json
import subprocess
import sys
from functools import cache
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = {"ofera": ROOT / "server" / "ofera", "ofera_protocol": ROOT / "protocol" / "ofera_protocol"}
ARCHITECTURE = ROOT / "docs" / "ARCHITECTURE.md"

BASE = {"errors", "assets", "jit", "thread_choice", "thread_placement"}
"""`ofera.errors` (the root error), `ofera.assets` (shipped files and the cache folder), `ofera.jit` (the numba
options and intrinsics of the fast paths), `ofera.thread_choice` (when their kernels run on numba's threads) and
`ofera.thread_placement` (where those threads run): any layer of `ofera` may import them."""
ALLOWED: dict[str, set[str]] = {
    "protocol": set(),  # ofera_protocol: the wire contract, nothing of the server
    "errors": set(),
    "assets": set(),
    "jit": set(),
    "thread_choice": set(),
    "thread_placement": set(),  # (jit, from BASE)
    "head": set(),  # the head model: nothing of avatar, mapping, streaming or anything else
    "mapping": {"head", "protocol"},  # the run-time mapping: numpy + onnxruntime, no training
    "avatar": {"head", "protocol"},
    "sources": {"mapping", "protocol"},
    "web": {"mapping"},
    "training": {"head", "avatar", "mapping", "protocol"},  # offline: the server never imports it
    "streaming": {"ofera", "head", "avatar", "mapping", "protocol", "web"},
    "client": {"ofera", "protocol"},  # a client library: nothing of the server
    "replay": {"client", "sources", "mapping", "protocol"},
    "ingest": {"replay", "client", "sources", "mapping", "protocol"},
    "cli": {"ofera", "head", "avatar", "mapping", "sources", "web", "training", "streaming", "client", "replay",
            "ingest", "protocol"},
    "ofera": set(),  # ofera/__init__.py: the version
}
"""Layer (a package of `ofera`, or `protocol` for `ofera_protocol`) -> the layers it may import, besides BASE."""


def _modules() -> dict[str, tuple[Path, bool]]:
    mods = {}
    for top, root in PACKAGES.items():
        for path in root.rglob("*.py"):
            parts = [top, *path.relative_to(root).with_suffix("").parts]
            is_pkg = parts[-1] == "__init__"
            mods[".".join(parts[:-1] if is_pkg else parts)] = (path, is_pkg)
    return mods


def _targets(mod: str, is_pkg: bool, node: ast.Import | ast.ImportFrom, known: dict) -> list[str]:
    """The modules an import statement names (`from pkg import sub` names the submodule when there is one)."""
    if isinstance(node, ast.Import):
        return [a.name for a in node.names]
    if node.level:
        base = mod.split(".")[: len(mod.split(".")) - (0 if is_pkg else 1)]
        base = base[: len(base) - (node.level - 1)]
        src = ".".join(base + ([node.module] if node.module else []))
    else:
        src = node.module or ""
    return [f"{src}.{a.name}" if f"{src}.{a.name}" in known else src for a in node.names]


@cache
def import_graph() -> dict[str, frozenset[str]]:
    """Module -> the modules of ofera / ofera_protocol it imports (anywhere in the file, TYPE_CHECKING aside)."""
    mods = _modules()
    graph = {}
    for mod, (path, is_pkg) in mods.items():
        deps = set()
        stack = list(ast.parse(path.read_text(encoding="utf-8")).body)
        while stack:
            node = stack.pop()
            if isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test):
                stack.extend(node.orelse)
                continue
            if isinstance(node, ast.Import | ast.ImportFrom):
                for target in _targets(mod, is_pkg, node, mods):
                    while target and target not in mods:  # an attribute of a module: the module
                        target = target.rpartition(".")[0]
                    if target and target != mod:
                        deps.add(target)
            stack.extend(ast.iter_child_nodes(node))
        graph[mod] = frozenset(deps)
    return graph


def test_the_graph_sees_every_kind_of_import() -> None:
    g = import_graph()
    assert "ofera.streaming.pipeline" in g["ofera.streaming.registry"]  # from .pipeline import ...
    assert "ofera.avatar" in g["ofera.streaming.registry"]  # inside a function (AvatarRegistry._load)
    assert "ofera.training.paired.rig" in g["ofera.training.paired.benchmark"]  # absolute
    assert "ofera_protocol.layouts" in g["ofera.mapping.layouts"]  # the other package


def layer(mod: str) -> str:
    parts = mod.split(".")
    if parts[0] == "ofera_protocol":
        return "protocol"
    return parts[1] if len(parts) > 1 else "ofera"


def test_every_layer_has_a_rule_and_a_line_in_the_architecture_page() -> None:
    layers = {layer(m) for m in import_graph()}
    assert layers == set(ALLOWED), f"give every package a rule here: {sorted(layers ^ set(ALLOWED))}"
    text = ARCHITECTURE.read_text(encoding="utf-8")
    for name in sorted(layers - {"ofera", "protocol"}):
        if (PACKAGES["ofera"] / name).is_dir():
            assert f"server/ofera/{name}/" in text, f"docs/ARCHITECTURE.md does not name server/ofera/{name}/"
        else:  # a module of the base (BASE): named in the layers' paragraph
            assert f"`ofera.{name}`" in text, f"docs/ARCHITECTURE.md does not name ofera.{name}"
    assert "protocol/ofera_protocol/" in text


@pytest.mark.parametrize("name", sorted(ALLOWED))
def test_layer_imports_only_what_its_rule_allows(name: str) -> None:
    allowed = ALLOWED[name] | (BASE if name != "protocol" else set()) | {name}  # the protocol: not even BASE
    bad = sorted(f"{m} -> {d}" for m, deps in import_graph().items() if layer(m) == name
                 for d in deps if layer(d) not in allowed)
    assert not bad, f"{name} may import only {sorted(allowed - {name})}:\n" + "\n".join(bad)


def test_no_import_cycles() -> None:
    graph = import_graph()
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    cycles: list[list[str]] = []

    def visit(v: str) -> None:  # Tarjan's strongly connected components
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph[v]):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                cycles.append(sorted(comp))

    sys.setrecursionlimit(max(sys.getrecursionlimit(), 10 * len(graph)))
    for v in sorted(graph):
        if v not in index:
            visit(v)
    detail = "\n".join(f"{c}: " + "; ".join(f"{m} -> {sorted(graph[m] & set(c))}" for m in c) for c in cycles)
    assert not cycles, f"modules that import each other (around a circle):\n{detail}"


RUNTIME = [
    "ofera.streaming", "ofera.streaming.app", "ofera.streaming.server", "ofera.streaming.session",
    "ofera.streaming.roles", "ofera.streaming.registry", "ofera.streaming.pipeline", "ofera.streaming.encode_fast",
    "ofera.avatar", "ofera.avatar.fast", "ofera.avatar.fast_vertex", "ofera.mapping.layouts", "ofera.mapping.bda",
    "ofera.mapping.runtime", "ofera.mapping.flame_values", "ofera.mapping.baselines", "ofera.mapping.provenance",
    "ofera.web", "ofera.client", "ofera.replay", "ofera.ingest", "ofera.sources", "ofera.cli.main",
]
"""What `ofera serve` (and the client, replay and ingest commands) import."""

_NO_TORCH = """
import importlib, json, sys

attempts = []

class BlockTorch:
    def find_spec(self, name, path=None, target=None):
        if name == "torch" or name.startswith("torch."):
            attempts.append(name)
            raise ImportError(f"{name} is blocked by tests/test_architecture.py")
        return None

sys.meta_path.insert(0, BlockTorch())
for mod in json.loads(sys.argv[1]):
    importlib.import_module(mod)
print(json.dumps({"attempts": attempts, "loaded": sorted(m for m in sys.modules if m.split(".")[0] == "torch")}))
"""


def test_the_servers_run_time_path_imports_no_torch() -> None:
    res = subprocess.run([sys.executable, "-c", _NO_TORCH, json.dumps(RUNTIME)], capture_output=True, text=True,
                         timeout=300, check=False, cwd=ROOT)
    assert res.returncode == 0, res.stdout + res.stderr
    out = json.loads(res.stdout.strip().splitlines()[-1])
    assert out == {"attempts": [], "loaded": []}, out


def test_the_packages_input_errors_have_one_root() -> None:
    """Every ValueError subclass of ofera is also an OferaError (ofera.errors), directly or through its parent."""
    classes: dict[str, list[str]] = {}
    for path, _ in _modules().values():
        if path.is_relative_to(PACKAGES["ofera"]):
            for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
                if isinstance(node, ast.ClassDef):
                    classes[node.name] = [ast.unparse(b).rpartition(".")[2] for b in node.bases]

    def rooted(name: str, seen: frozenset = frozenset()) -> bool:
        bases = classes.get(name, [])
        return "OferaError" in bases or any(rooted(b, seen | {name}) for b in bases if b not in seen)

    def value_error(name: str, seen: frozenset = frozenset()) -> bool:
        bases = classes.get(name, [])
        return "ValueError" in bases or any(value_error(b, seen | {name}) for b in bases if b not in seen)

    stray = sorted(n for n in classes if value_error(n) and not rooted(n))
    assert not stray, f"ValueError subclasses that are not OferaError: {stray}"
    assert {"HeadModelError", "AvatarError", "LayoutError", "BDAError", "MapperError", "EPMError"} <= {
        n for n in classes if rooted(n) and value_error(n)}
