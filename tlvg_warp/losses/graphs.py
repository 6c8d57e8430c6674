"""Differentiable torch calls replayed as CUDA graphs: the stylize step is host-bound (hundreds of small kernels a
step), so a loss made of many small torch ops costs more host time launching them than GPU time running them.

``GraphedCall`` captures ``fn(x, *aux)`` for one set of input shapes as two graphs, forward and backward (the
gradient with respect to ``x``, or to the first ``n_grad`` inputs; the rest, ``aux``, are constants such as a target
field, copied in on each call). ``GraphedFn`` keeps one ``GraphedCall`` per input shape (at most ``MAX_GRAPHS``,
eager beyond) and runs eagerly where graphs do not apply (CPU tensors, no gradient wanted).

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

    def __init__(self, fn: Callable[..., torch.Tensor], *inputs: torch.Tensor, n_grad: int = 1):
        self.xs = [x.detach().clone().requires_grad_(True) for x in inputs[:n_grad]]  # static inputs
        self.aux = [a.detach().clone() for a in inputs[n_grad:]]  # static constants
        dev = self.xs[0].device
        side = torch.cuda.Stream(dev)
        side.wait_stream(torch.cuda.current_stream(dev))
        with torch.cuda.stream(side):
            for _ in range(self.WARMUP):
                out = fn(*self.xs, *self.aux)
                torch.autograd.grad(out.sum(), self.xs, allow_unused=True)
            del out
        torch.cuda.current_stream(dev).wait_stream(side)
        pool = torch.cuda.graph_pool_handle()
        self.forward_graph, self.backward_graph = torch.cuda.CUDAGraph(), torch.cuda.CUDAGraph()
        with torch.cuda.graph(self.forward_graph, pool=pool):
            self.out = fn(*self.xs, *self.aux)  # static
        self.grad_out = torch.zeros_like(self.out)  # static seed, written before each backward replay
        with torch.cuda.graph(self.backward_graph, pool=pool):
            # static; an input the call does not read (e.g. depth with its term off) gets zeros
            self.grads = torch.autograd.grad((self.out * self.grad_out).sum(), self.xs, allow_unused=True,
                                             materialize_grads=True)

    def __call__(self, *inputs: torch.Tensor) -> torch.Tensor:
        n = len(self.xs)
        for static, a in zip(self.aux, inputs[n:]):
            static.copy_(a)
        return _GraphReplayFn.apply(self, *inputs[:n])


class _GraphReplayFn(torch.autograd.Function):
    @staticmethod
    def forward(ctx, graphed: GraphedCall, *xs):
        for static, x in zip(graphed.xs, xs):
            static.detach().copy_(x)
        graphed.forward_graph.replay()
        ctx.graphed = graphed
        return graphed.out.detach()

    @staticmethod
    def backward(ctx, grad_out):
        graphed = ctx.graphed
        graphed.grad_out.copy_(grad_out)
        graphed.backward_graph.replay()
        return (None, *(g.detach() for g in graphed.grads))


class GraphedFn:
    """``fn(*inputs)`` replayed from a ``GraphedCall`` per input shape where graphs apply, else called eagerly; the
    gradient flows to the first ``n_grad`` inputs."""

    def __init__(self, fn: Callable[..., torch.Tensor], max_graphs: int = MAX_GRAPHS, n_grad: int = 1):
        self.fn, self.max_graphs, self.n_grad = fn, max_graphs, n_grad
        self.graphs: dict = {}

    def __call__(self, *inputs: torch.Tensor) -> torch.Tensor:
        xs = inputs[:self.n_grad]
        if not (xs[0].is_cuda and any(x.requires_grad for x in xs) and torch.is_grad_enabled()):
            return self.fn(*inputs)
        key = tuple((tuple(t.shape), t.dtype, t.device) for t in inputs)
        call = self.graphs.get(key)
        if call is None:
            if len(self.graphs) >= self.max_graphs:
                return self.fn(*inputs)
            call = self.graphs[key] = GraphedCall(self.fn, *inputs, n_grad=self.n_grad)
        return call(*inputs)
