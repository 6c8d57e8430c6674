"""tlvg_warp.launch is the one module that uses Warp's private API (and torch's): each use is checked here against
the installed versions, so a Warp upgrade that moves or changes one fails here, by name, before any kernel runs."""
import ast
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]


def test_private_api_is_what_launch_expects():
    """Each entry of launch.PRIVATE_API: the names exist, native functions take the argument counts launch.py
    passes, a recorded wp.Launch has the slots and attributes fast_launch refills, a struct argument is its ctypes
    bytes."""
    import warp as wp

    from tlvg_warp.launch import PRIVATE_API, private_api_problems

    problems = private_api_problems()
    assert not problems, (f"Warp {wp.config.version} / torch {torch.__version__} changed private API that "
                          f"tlvg_warp/launch.py uses; update it there:\n  " + "\n  ".join(problems)
                          + "\nWhat it relies on:\n  " + "\n  ".join(f"{w} ({u})" for w, u in PRIVATE_API))


def test_private_api_problems_names_a_missing_function(monkeypatch):
    """The check reports, by name, a native function that lost an argument (simulated on Warp's ctypes entry,
    restored after the test) and a Launch attribute that went away."""
    import warp as wp

    from tlvg_warp.launch import _runtime, init_warp, private_api_problems

    init_warp()
    fn = _runtime().core.wp_array_scan_int_host
    monkeypatch.setattr(fn, "argtypes", list(fn.argtypes)[:-1])
    monkeypatch.delattr(wp.Launch, "set_dim")
    problems = private_api_problems()
    assert len(problems) == 2, problems
    assert "wp_array_scan_int_host" in problems[0] and "inclusive_scan_at" in problems[0]
    assert "takes 6 arguments, 7 expected" in problems[0]
    assert "wp.Launch" in problems[1] and "fast_launch" in problems[1] and "set_dim" in problems[1]


def test_private_warp_array_descriptor_is_still_what_from_torch_builds():
    """launch.ct builds Warp's private array_t itself (speed): its descriptors equal from_torch's."""
    import warp as wp

    from tlvg_warp.launch import ct, warp_array_ctype

    base = torch.arange(48, dtype=torch.float32)
    # ct caches one template per layout: the same layouts come twice over other storage, and must still carry each
    # tensor's own data pointer; a strided view and int32 / float64 tensors check the strides and element sizes
    cases = [(base[:12].reshape(4, 3), wp.vec3), (base[12:24].reshape(4, 3), wp.vec3), (base[:12], None),
             (base[24:36], None), (base.reshape(6, 8)[:, ::2], None), (base.reshape(8, 6).T, None),
             (torch.arange(10, dtype=torch.int32), None), (torch.zeros(5, 2, dtype=torch.float64), wp.vec2d)]
    for t, dtype in cases:
        ref = wp.from_torch(t, dtype=dtype, return_ctype=True)
        assert type(ref) is warp_array_ctype()
        ours = ct(t, dtype)
        for f in ("data", "grad", "ndim"):
            assert getattr(ours, f) == getattr(ref, f), (f, t.shape, t.stride())
        assert tuple(ours.shape)[:ours.ndim] == tuple(ref.shape)[:ref.ndim]
        assert tuple(ours.strides)[:ours.ndim] == tuple(ref.strides)[:ref.ndim]


def _private_uses(path: Path) -> list[str]:
    """``warp._src`` / ``warp.context`` imports and ``torch._C`` attribute reads in one source file."""
    found = []
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and node.module and (
                node.module.startswith(("warp._src", "warp.context", "warp.types")) or node.module == "warp"
                and any(a.name.startswith("_") for a in node.names)):
            found.append(f"from {node.module} import ...")
        elif isinstance(node, ast.Attribute) and isinstance(node.value, ast.Attribute) and \
                isinstance(node.value.value, ast.Name) and (node.value.value.id, node.value.attr) in (
                    ("torch", "_C"), ("wp", "_src"), ("warp", "_src")):
            found.append(f"{node.value.value.id}.{node.value.attr}.{node.attr}")
    return found


def test_only_launch_touches_private_api():
    """No other module of the package imports from warp._src (or Warp's pre-1.10 private modules) or reads
    torch._C: the checks above cover every use the package makes."""
    sources = sorted(p for f in (ROOT / "tlvg_warp", ROOT / "kernels") for p in f.rglob("*.py")
                     if "__pycache__" not in p.parts)
    outside = {str(p.relative_to(ROOT)): uses for p in sources if p.name != "launch.py" or p.parent.name != "tlvg_warp"
               if (uses := _private_uses(p))}
    assert outside == {}
    assert _private_uses(ROOT / "tlvg_warp" / "launch.py")  # the rule sees launch.py's own uses
