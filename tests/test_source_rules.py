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
