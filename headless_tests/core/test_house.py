"""The house rules that keep the package readable: the core never needs Blender, imports run one
way (no cycle anywhere in the package), and no core module outgrows a screenful of files (300 lines)."""

import ast
import pathlib
import subprocess
import sys

PACKAGE = pathlib.Path(__file__).resolve().parents[2] / "headadapt_addon"


def _modules(root=PACKAGE):
    """{dotted name: path} of every module of the package."""
    out = {}
    for path in sorted(root.rglob("*.py")):
        parts = list(path.relative_to(root.parent).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        out[".".join(parts)] = path
    return out


def _imports(name, path, known):
    """The package's modules that module `name` imports (at any depth of its code)."""
    package = name if path.name == "__init__.py" else name.rsplit(".", 1)[0]
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = ".".join(base[: len(base) - node.level + 1])
                mod = base + ("." + node.module if node.module else "")
            else:
                mod = node.module or ""
            for alias in node.names:          # `from . import x` depends on x, not on the package
                found.add(mod + "." + alias.name if mod + "." + alias.name in known else mod)
        elif isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
    return {m for m in found if m in known and m != name}


def test_no_import_cycle_in_the_package():
    known = _modules()
    graph = {name: _imports(name, path, known) for name, path in known.items()}
    state, cycles = {}, []

    def visit(node, trail):
        state[node] = "open"
        for nxt in sorted(graph[node]):
            if state.get(nxt) == "open":
                cycles.append(trail[trail.index(nxt):] + [nxt])
            elif nxt not in state:
                visit(nxt, trail + [nxt])
        state[node] = "done"

    for name in graph:
        if name not in state:
            visit(name, [name])
    assert not cycles, cycles


def test_the_core_imports_with_blender_blocked():
    """Every core module imports in a Python where bpy and mathutils cannot be imported."""
    names = sorted(n for n in _modules() if n.startswith("headadapt_addon.core"))
    code = ("import sys, importlib, importlib.abc\n"
            "class Block(importlib.abc.MetaPathFinder):\n"
            "    def find_spec(self, name, path=None, target=None):\n"
            "        if name.split('.')[0] in ('bpy', 'mathutils', 'bmesh'):\n"
            "            raise ImportError('blocked: ' + name)\n"
            "sys.meta_path.insert(0, Block())\n"
            f"for name in {names!r}:\n"
            "    importlib.import_module(name)\n"
            "assert not {'bpy', 'mathutils'} & set(sys.modules), sorted(sys.modules)\n"
            "print(len(sys.modules))\n")
    proc = subprocess.run([sys.executable, "-c", code], cwd=PACKAGE.parent, capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr[-2000:]


def test_no_core_module_is_over_300_lines():
    long = {str(p.relative_to(PACKAGE)): n for p in (PACKAGE / "core").rglob("*.py")
            if (n := len(p.read_text().splitlines())) > 300}
    assert not long, long


def test_every_relative_import_names_a_module_of_the_package():
    """Lazy imports inside functions too (a moved module breaks them only when they run)."""
    known = _modules()
    missing = []
    for name, path in known.items():
        package = name if path.name == "__init__.py" else name.rsplit(".", 1)[0]
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and node.level:
                base = package.split(".")
                target = ".".join(base[: len(base) - node.level + 1] + ([node.module] if node.module else []))
                if target not in known:
                    missing.append(f"{path.relative_to(PACKAGE.parent)}:{node.lineno} {target}")
    assert not missing, missing
