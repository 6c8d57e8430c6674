"""Rules about the package's source, checked by reading it (nothing is imported or built here)."""
import ast
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGE, KERNELS = ROOT / "tlvg_warp", ROOT / "kernels"  # kernels/ installs as tlvg_warp.kernels


def _sources(*folders: Path) -> list[Path]:
    return sorted(p for f in folders for p in f.rglob("*.py") if "__pycache__" not in p.parts)


def test_only_documented_environment_switches():
    """The product reads two TLVG_WARP_* variables (fast math off, Warp's banner on); kernel variants are not picked
    from the environment (the ones that lost their A/B were deleted, and the fused SSIM's torch twin is a flag)."""
    names = {m for p in _sources(PACKAGE, KERNELS) for m in re.findall(r"TLVG_WARP_[A-Z0-9_]+", p.read_text())}
    assert names <= {"TLVG_WARP_FAST_MATH", "TLVG_WARP_VERBOSE"}, names


def _warp_decorated(tree: ast.AST) -> list[str]:
    """Names of the functions decorated with wp.kernel / wp.func / wp.func_native (called or not)."""
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.FunctionDef):
            for d in node.decorator_list:
                d = d.func if isinstance(d, ast.Call) else d
                if isinstance(d, ast.Attribute) and d.attr in ("kernel", "func", "func_native", "func_grad",
                                                                "func_replay") \
                        and isinstance(d.value, ast.Name) and d.value.id in ("wp", "warp"):
                    found.append(node.name)
    return found


def test_every_warp_kernel_lives_under_kernels():
    """tlvg_warp/ holds the torch side only; Warp kernels and their functions are kernels/'s (the rule is checked to
    see kernels there)."""
    outside = {str(p.relative_to(ROOT)): names for p in _sources(PACKAGE)
               if (names := _warp_decorated(ast.parse(p.read_text())))}
    assert outside == {}
    inside = [n for p in _sources(KERNELS) for n in _warp_decorated(ast.parse(p.read_text()))]
    assert {"blend_forward_kernel", "targets_kernel", "lab_ab_forward", "srgb_linear", "lane_id"} <= set(inside)


def _module_of(path: Path) -> tuple[str, bool]:
    """(dotted name, is a package) of a source file; kernels/ is tlvg_warp.kernels."""
    if path.is_relative_to(KERNELS):
        parts = ("tlvg_warp", "kernels", *path.relative_to(KERNELS).with_suffix("").parts)
    else:
        parts = path.relative_to(ROOT).with_suffix("").parts
    is_pkg = parts[-1] == "__init__"
    return ".".join(parts[:-1] if is_pkg else parts), is_pkg


def import_graph() -> dict[str, set[str]]:
    """Module -> the package's modules it imports, from every import statement in it (at the top or inside a
    function: a lazy import is still a dependency). ``from .x import y`` counts as importing module x.y where that
    is a module, else x."""
    files = {_module_of(p): p for p in _sources(PACKAGE, KERNELS)}
    names = {name for name, _ in files}
    graph = {}
    for (name, is_pkg), path in files.items():
        here = name.split(".") if is_pkg else name.split(".")[:-1]  # the package a relative import starts from
        deps = set()
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Import):
                deps |= {a.name for a in node.names}
            elif isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:
                    base = ".".join(here[:len(here) - node.level + 1] + ([node.module] if node.module else []))
                deps |= {f"{base}.{a.name}" if f"{base}.{a.name}" in names else base for a in node.names}
        graph[name] = {d for d in deps if d in names and d != name}
    return graph


def find_cycle(graph: dict[str, set[str]]) -> list[str]:
    """One cycle of ``graph`` as [a, b, ..., a], or [] (a depth-first search)."""
    state, stack = {}, []  # state: 1 on the current path, 2 done

    def visit(v):
        state[v] = 1
        stack.append(v)
        for w in sorted(graph[v]):
            if state.get(w) == 1:
                return stack[stack.index(w):] + [w]
            if w not in state and (found := visit(w)):
                return found
        stack.pop()
        state[v] = 2
        return []

    for v in sorted(graph):
        if v not in state and (found := visit(v)):
            return found
    return []


def test_the_package_has_no_import_cycle():
    """The modules' imports form a layered graph: no module reaches itself through imports, lazy ones included."""
    graph = import_graph()
    assert len(graph) > 60 and "tlvg_warp.io.splat_formats" in graph["tlvg_warp.io.ply"]  # the walk sees imports
    assert "tlvg_warp.kernels.lab" in graph["tlvg_warp.losses.lab_warp"]  # (kernels/ is tlvg_warp.kernels)
    assert find_cycle(graph) == [], " -> ".join(find_cycle(graph))


def test_find_cycle_finds_one():
    assert find_cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == ["a", "b", "c", "a"]
    assert find_cycle({"a": {"b"}, "b": set(), "c": {"a", "b"}}) == []
