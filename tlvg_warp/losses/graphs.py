"""Differentiable torch calls replayed as CUDA graphs: the stylize step is host-bound (hundreds of small kernels a
step), so a loss made of many small torch ops costs more host time launching them than GPU time running them.

``GraphedCall`` captures ``fn(x, *aux)`` for one set of input shapes as two graphs, forward and backward (the
gradient with respect to ``x`` only; ``aux`` are constants such as a target field, copied in on each call).
``GraphedFn`` keeps one ``GraphedCall`` per input shape (at most ``MAX_GRAPHS``, eager beyond) and runs eagerly
where graphs do not apply (CPU tensors, no gradient wanted).

What ``torch.cuda.make_graphed_callables`` builds, captured by hand so that the backward is seeded by a scalar,
``(out * grad_out).sum()``: autograd given a tensor seed imports torch.fx's symbolic shapes, and with them sympy,
2.2 s of a stylize run's start on a GPU host. The graphs' buffers are static: the output is overwritten by the
next replay, and a call's backward must run before the next call of the same shape (the training loop runs each
view's backward before it renders the next). ``fn`` must not copy from the host while it runs (build its
constants once, outside the call).
"""
from __future__ import annotations

from typing import Callable

import torch

MAX_GRAPHS = 4  # input shapes with a captured graph per GraphedFn (each keeps its activations' memory)


class GraphedCall:
    """``fn(x, *aux)`` for the shapes of the samples given, as a forward and a backward CUDA graph."""

    WARMUP = 3  # eager passes on a side stream before capture (cuDNN picks its algorithms, the allocator warms)

    def __init__(self, fn: Callable[..., torch.Tensor], x: torch.Tensor, *aux: torch.Tensor):
        self.x = x.detach().clone().requires_grad_(True)  # static input
        self.aux = [a.detach().clone() for a in aux]  # static constants
        dev = self.x.device
        side = torch.cuda.Stream(dev)
        side.wait_stream(torch.cuda.current_stream(dev))
        with torch.cuda.stream(side):
            for _ in range(self.WARMUP):
                out = fn(self.x, *self.aux)
                torch.autograd.grad(out.sum(), self.x)
            del out
        torch.cuda.current_stream(dev).wait_stream(side)
        pool = torch.cuda.graph_pool_handle()
        self.forward_graph, self.backward_graph = torch.cuda.CUDAGraph(), torch.cuda.CUDAGraph()
        with torch.cuda.graph(self.forward_graph, pool=pool):
            self.out = fn(self.x, *self.aux)  # static
        self.grad_out = torch.zeros_like(self.out)  # static seed, written before each backward replay
        with torch.cuda.graph(self.backward_graph, pool=pool):
            (self.grad_x,) = torch.autograd.grad((self.out * self.grad_out).sum(), self.x)  # static

    def __call__(self, x: torch.Tensor, *aux: torch.Tensor) -> torch.Tensor:
        for static, a in zip(self.aux, aux):
            static.copy_(a)
        return _GraphReplayFn.apply(self, x)


class _GraphReplayFn(torch.autograd.Function):
    @staticmethod
    def forward(ctx, graphed: GraphedCall, x):
        graphed.x.detach().copy_(x)
        graphed.forward_graph.replay()
        ctx.graphed = graphed
        return graphed.out.detach()

    @staticmethod
    def backward(ctx, grad_out):
        graphed = ctx.graphed
        graphed.grad_out.copy_(grad_out)
        graphed.backward_graph.replay()
        return None, graphed.grad_x.detach()


class GraphedFn:
    """``fn(x, *aux)`` replayed from a ``GraphedCall`` per input shape where graphs apply, else called eagerly."""

    def __init__(self, fn: Callable[..., torch.Tensor], max_graphs: int = MAX_GRAPHS):
        self.fn, self.max_graphs = fn, max_graphs
        self.graphs: dict = {}

    def __call__(self, x: torch.Tensor, *aux: torch.Tensor) -> torch.Tensor:
        if not (x.is_cuda and x.requires_grad and torch.is_grad_enabled()):
            return self.fn(x, *aux)
        key = tuple((tuple(t.shape), t.dtype, t.device) for t in (x, *aux))
        call = self.graphs.get(key)
        if call is None:
            if len(self.graphs) >= self.max_graphs:
                return self.fn(x, *aux)
            call = self.graphs[key] = GraphedCall(self.fn, x, *aux)
        return call(x, *aux)
