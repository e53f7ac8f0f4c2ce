"""The package's house rules, checked on its source: the wings of torchfra/LAYERS.txt import only from
themselves and the wings below them, no module imports itself back through others (no circle), fem/
imports nothing outside itself, assimilation/ and runtime/ nothing else of torchfra, and no command,
script, study or example edits sys.path. Imports inside functions count like any other."""
import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "torchfra"


def _modules() -> dict[str, Path]:
    out = {}
    for p in PACKAGE.rglob("*.py"):
        name = ".".join(p.relative_to(ROOT).with_suffix("").parts)
        out[name.removesuffix(".__init__")] = p
    return out


def _imports(name: str, path: Path, known) -> set[str]:
    """The torchfra modules ``name`` imports (a name imported from a package counts as its module when
    it is one, else as the package)."""
    base = name if path.name == "__init__.py" else name.rsplit(".", 1)[0]
    found = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Import):
            found |= {a.name for a in node.names}
        elif isinstance(node, ast.ImportFrom):
            mod = node.module or ""
            if node.level:
                parts = base.split(".")
                mod = ".".join(parts[: len(parts) - node.level + 1] + ([node.module] if node.module else []))
            found |= {mod} | {f"{mod}.{a.name}" for a in node.names}
    out = set()
    for m in found:
        while m and m not in known:
            m = m.rpartition(".")[0]
        if m and m != name and m != "torchfra":
            out.add(m)
    return out


def _graph():
    mods = _modules()
    return {m: _imports(m, p, mods) for m, p in mods.items()}


def _layers() -> list[str]:
    return [line.strip() for line in (PACKAGE / "LAYERS.txt").read_text().splitlines()
            if line.strip() and not line.startswith("#")]


def _wing(module: str, layers: list[str]) -> int | None:
    return next((i for i, w in enumerate(layers) if module == w or module.startswith(w + ".")), None)


def test_every_module_lies_in_a_wing_and_imports_only_its_own_and_those_below():
    layers, graph = _layers(), _graph()
    outside = sorted(m for m in graph if _wing(m, layers) is None and m not in ("torchfra", "torchfra.__main__"))
    assert not outside, f"modules in no wing of LAYERS.txt: {outside}"
    against = sorted(f"{m} -> {w}" for m, ws in graph.items() for w in ws
                     if _wing(m, layers) is not None and _wing(w, layers) is not None and _wing(w, layers) < _wing(m, layers))
    assert not against, "imports against the layers:\n" + "\n".join(against)


def test_no_import_circle():
    graph = _graph()
    seen, on_path, circles = set(), [], []

    def visit(m):
        if m in on_path:
            circles.append(on_path[on_path.index(m):] + [m])
            return
        if m in seen:
            return
        seen.add(m)
        on_path.append(m)
        for w in sorted(graph.get(m, ())):
            visit(w)
        on_path.pop()

    for m in sorted(graph):
        visit(m)
    assert not circles, "import circles: " + "; ".join(" -> ".join(c) for c in circles)


def test_the_fem_library_and_the_standalone_wings_import_nothing_above_them():
    graph = _graph()
    for wing, allowed in (("torchfra.fem", ("torchfra.fem",)), ("torchfra.assimilation", ("torchfra.assimilation",)),
                          ("torchfra.runtime", ("torchfra.runtime",))):
        bad = sorted(f"{m} -> {w}" for m, ws in graph.items() if m == wing or m.startswith(wing + ".")
                     for w in ws if not any(w == a or w.startswith(a + ".") for a in allowed))
        assert not bad, f"{wing} imports outside itself: {bad}"


def test_no_command_script_study_or_example_edits_sys_path():
    places = [PACKAGE, ROOT / "scripts", ROOT / "studies", ROOT / "examples", ROOT / "benchmarks"]
    bad = [str(p.relative_to(ROOT)) for d in places if d.exists() for p in d.rglob("*.py")
           if "sys.path.insert" in p.read_text(encoding="utf-8") or "sys.path.append" in p.read_text(encoding="utf-8")]
    assert not bad, f"sys.path edited in {bad}: the package is installed (pip install -e .)"
