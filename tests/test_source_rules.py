"""Rules about the package's source, checked by reading it (nothing is imported or built here)."""
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
