"""Sliced Wasserstein distances between a render and the painting: the whole distribution, not its nearest cells.

Why: nearest-neighbour matching (NNFM, FAST) is satisfied once every cell of a render finds *some* close cell of
the painting. A tinted photo does that: its fine texture finds the painting's fine dark-blue strokes, and nothing
asks for the yellow stars or the swirls' share of the view (on fern x The Starry Night NNFM ends at the distance
between the painting's two halves while the views still read as the photo). A sliced Wasserstein distance compares
the two sets as distributions (Heitz et al., "A Sliced Wasserstein Loss for Neural Texture Synthesis", CVPR 2021):
both are projected on random unit directions, each projection sorted, and the k-th smallest render value is pulled
to the painting's value at the same quantile. Every part of the painting's distribution then has to appear in the
view in its own proportion.

Two uses in the Stylize phase: on the style term's VGG features (the painting's texture as a whole) and on the
pixels' RGB colours (the painting's colour distribution: its yellow-against-blue, not only its mean tint).
"""
from __future__ import annotations

import torch


def random_directions(dim: int, count: int, seed: int, device) -> torch.Tensor:
    """``count`` unit directions in R^dim [dim, count], drawn on ``device`` from ``seed`` (no host sync)."""
    gen = torch.Generator(device=device)
    gen.manual_seed(int(seed))
    d = torch.randn(dim, count, generator=gen, device=device)  # [dim, count]
    return d / d.norm(dim=0, keepdim=True).clamp_min(1e-12)


def quantile_index(n: int, m: int, device) -> torch.Tensor:
    """For ``n`` sorted samples, the index into ``m`` sorted target samples at the same quantile (mid-ranks)."""
    return ((torch.arange(n, device=device, dtype=torch.float64) + 0.5) * (m / n)).long().clamp_(0, m - 1)  # [n]


def sliced_wasserstein(x: torch.Tensor, y: torch.Tensor, dirs: torch.Tensor) -> torch.Tensor:
    """Mean over directions and samples of (sorted x·d - y·d at the same quantile)^2.

    x: [N, D] the render's samples (differentiable); y: [M, D] the painting's (fixed); dirs: [D, P] unit columns.
    N and M may differ: x's k-th smallest projection meets y's at quantile (k + 1/2) / N."""
    px = torch.sort(x @ dirs.to(x.dtype), dim=0).values  # [N, P]
    with torch.no_grad():
        py = torch.sort(y.to(x.dtype) @ dirs.to(x.dtype), dim=0).values  # [M, P]
        py = py.index_select(0, quantile_index(x.shape[0], y.shape[0], x.device))  # [N, P]
    return ((px - py) ** 2).mean()


MAX_TARGET = 65536  # the painting's samples kept (a seeded random subset beyond): its quantiles move by sampling
# noise only, and sorting a painting's every pixel each step cost more than the rest of the step together


def subsample(y: torch.Tensor, limit: int, seed: int) -> torch.Tensor:
    """At most ``limit`` rows of ``y`` [M, D]: all of them, or a seeded random subset (the same for the same seed)."""
    if y.shape[0] <= limit:
        return y
    gen = torch.Generator().manual_seed(int(seed))
    return y.index_select(0, torch.randperm(y.shape[0], generator=gen)[:limit].to(y.device))


class SlicedWasserstein:
    """The painting's side of one sliced Wasserstein term: its samples [M, D], their spread (the loss is divided by
    it, so a weight means the same on features and colours) and the direction draws (``count`` new directions each
    call, from ``seed`` and the call number, so a resumed run draws what an uninterrupted one would)."""

    def __init__(self, target: torch.Tensor, count: int, seed: int = 0, max_target: int = MAX_TARGET):
        self.target = subsample(target.detach(), max_target, seed)  # [M, D]
        self.count, self.seed, self.calls = int(count), int(seed), 0
        spread = float(self.target.double().var(dim=0, unbiased=False).mean())  # one host read, at the run's start
        self.scale = 1.0 / max(spread, 1e-12)

    def __call__(self, x: torch.Tensor) -> torch.Tensor:
        """x: [N, D] the render's samples."""
        dirs = random_directions(self.target.shape[1], self.count, self.seed * 1_000_003 + self.calls, x.device)
        self.calls += 1
        return sliced_wasserstein(x, self.target, dirs) * self.scale
