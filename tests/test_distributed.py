"""tlvg_warp.distributed.Dist: the collectives of two gloo processes (a real `torchrun --standalone
--nproc-per-node 2` launch, so the environment is torchrun's) against closed forms computed here, in the
parent, from the inputs each rank derives from its rank; and the single-process handle's no-ops."""
import json
import os
import subprocess
import sys
from pathlib import Path

import torch

from tlvg_warp.distributed import Dist, local_only

REPO = Path(__file__).resolve().parents[1]

WORKER = r'''
import json, os, sys, time
from pathlib import Path
import torch
import torch.distributed as tdist
from tlvg_warp.distributed import Dist, local_only

out = Path(sys.argv[1])
d = Dist.from_env("cpu")
r = d.rank


def inputs(rank):
    g = torch.Generator().manual_seed(100 + rank)
    a = torch.randn(4, 3, generator=g).t()                          # non-contiguous float32
    b = torch.randn(5, generator=g, dtype=torch.float64)
    c = torch.randint(-50, 50, (2, 2), generator=g)                 # int64
    p = torch.nn.Parameter(torch.zeros(6))
    p.grad = torch.randn(6, generator=g)                            # a parameter's gradient
    return a, b, c, p


calls = []
real_all_reduce = tdist.all_reduce
def counting(t, *args, **kw):
    calls.append(t.dtype)
    return real_all_reduce(t, *args, **kw)
tdist.all_reduce = counting

res = {"rank": r, "world": d.world, "local_rank": d.local_rank, "backend": d.backend, "is_main": d.is_main}
a, b, c, p = inputs(r)
d.all_reduce_mean_([a, None, p.grad, b])
res["mean_calls"] = [str(x) for x in calls]
res["mean"] = [a.tolist(), p.grad.tolist(), b.tolist()]
res["mean_a_strides"] = list(a.stride())
calls.clear()
a, b, c, p = inputs(r)
d.all_reduce_sum_([c, a, p.grad])
res["sum_calls"] = len(calls)
res["sum"] = [c.tolist(), a.tolist(), p.grad.tolist()]
a, b, c, p = inputs(r)
d.all_reduce_max_([a, b])
res["max"] = [a.tolist(), b.tolist()]
a, b, c, p = inputs(r)
d.broadcast_tensors_([a, c], src=1)
res["bcast"] = [a.tolist(), c.tolist()]
res["bobj"] = d.broadcast_object({"from": r, "list": [r] * 3}, src=1)
res["gather"] = d.gather_objects(("rank", r))
res["allgather"] = d.all_gather_objects(r * 10)
res["slice"] = d.rank_slice(list("abcdefg"))
# barrier: rank 1 writes a file late; rank 0 must see it once past the barrier
flag = out / "late.flag"
if r == 1:
    time.sleep(0.5)
    flag.write_text("x")
d.barrier()
res["flag_after_barrier"] = flag.exists()
with local_only():
    inner = Dist.from_env("cpu")
    res["local_only"] = [inner.world, inner.rank]
(out / f"rank{r}.json").write_text(json.dumps(res))
d.shutdown()
'''


def _inputs(rank):
    g = torch.Generator().manual_seed(100 + rank)
    a = torch.randn(4, 3, generator=g).t()
    b = torch.randn(5, generator=g, dtype=torch.float64)
    c = torch.randint(-50, 50, (2, 2), generator=g)
    grad = torch.randn(6, generator=g)
    return a, b, c, grad


def test_two_gloo_ranks_collectives_match_closed_forms(tmp_path):
    script = tmp_path / "worker.py"
    script.write_text(WORKER)
    env = dict(os.environ, PYTHONPATH=str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""),
               OMP_NUM_THREADS="1")
    p = subprocess.run([sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc-per-node", "2",
                        str(script), str(tmp_path)], env=env, capture_output=True, text=True, timeout=180)
    assert p.returncode == 0, p.stdout[-3000:] + p.stderr[-3000:]
    res = [json.loads((tmp_path / f"rank{r}.json").read_text()) for r in (0, 1)]
    x = [_inputs(r) for r in (0, 1)]
    close = lambda got, want: torch.testing.assert_close(torch.tensor(got, dtype=want.dtype), want,  # noqa: E731
                                                          rtol=1e-6, atol=1e-6)
    for r, out in enumerate(res):
        assert (out["rank"], out["world"], out["local_rank"], out["backend"], out["is_main"]) == \
            (r, 2, r, "gloo", r == 0)
        # mean: (x0 + x1) / 2 of each tensor, None skipped; float32 and float64 in one collective each
        close(out["mean"][0], (x[0][0] + x[1][0]) / 2)
        close(out["mean"][1], (x[0][3] + x[1][3]) / 2)
        close(out["mean"][2], (x[0][1] + x[1][1]) / 2)
        assert sorted(out["mean_calls"]) == ["torch.float32", "torch.float64"]
        assert out["mean_a_strides"] == [1, 3]  # in place: the caller's (transposed) tensor, not a copy
        # sum: integers exactly; the int64 tensor and the two float32 ones: two collectives, not three
        assert out["sum"][0] == (x[0][2] + x[1][2]).tolist()
        close(out["sum"][1], x[0][0] + x[1][0])
        close(out["sum"][2], x[0][3] + x[1][3])
        assert out["sum_calls"] == 2
        close(out["max"][0], torch.maximum(x[0][0], x[1][0]))
        close(out["max"][1], torch.maximum(x[0][1], x[1][1]))
        close(out["bcast"][0], x[1][0])
        assert out["bcast"][1] == x[1][2].tolist()
        assert out["bobj"] == {"from": 1, "list": [1, 1, 1]}
        assert out["allgather"] == [0, 10]
        assert out["flag_after_barrier"] is True
        assert out["local_only"] == [1, 0]
    assert res[0]["gather"] == [["rank", 0], ["rank", 1]] and res[1]["gather"] is None
    assert res[0]["slice"] == list("aceg") and res[1]["slice"] == list("bdf")


def test_single_process_handle_is_a_no_op(monkeypatch):
    monkeypatch.delenv("WORLD_SIZE", raising=False)
    d = Dist.from_env("cpu")
    assert (d.rank, d.world, d.is_main, d.device) == (0, 1, True, "cpu")
    t = torch.arange(6.0)
    for f in (d.all_reduce_mean_, d.all_reduce_sum_, d.all_reduce_max_):
        f([t, None])
    assert t.tolist() == list(range(6))
    assert d.broadcast_object({"a": 1}) == {"a": 1} and d.gather_objects(3) == [3]
    assert d.rank_slice([1, 2, 3]) == [1, 2, 3]
    d.barrier()
    monkeypatch.setenv("WORLD_SIZE", "4")  # torchrun's environment, but inside local_only: one process
    with local_only():
        assert Dist.from_env("cuda").world == 1


ISOLATE = r'''
import os, sys
from tlvg_warp.distributed import isolate_local_gpu
assert "warp" not in sys.modules  # importing distributed does not import Warp
assert isolate_local_gpu() and os.environ["CUDA_VISIBLE_DEVICES"] == "1"
assert "warp" not in sys.modules  # nor does the check, Warp not loaded
import warp  # loaded, not initialized: still isolates
from tlvg_warp.launch import init_warp, warp_runtime_up
os.environ["CUDA_VISIBLE_DEVICES"] = "0,5"
assert not warp_runtime_up() and isolate_local_gpu() and os.environ["CUDA_VISIBLE_DEVICES"] == "5"
os.environ["CUDA_VISIBLE_DEVICES"] = "0,5"
init_warp()  # Warp's runtime up: too late, nothing changes
assert warp_runtime_up() and not isolate_local_gpu() and os.environ["CUDA_VISIBLE_DEVICES"] == "0,5"
print("ok")
'''


def test_isolate_local_gpu_before_and_after_warp_starts():
    """Under torchrun's environment (rank 1 of 2) a process sees its own GPU only, unless Warp's runtime is already
    up (read through launch.warp_runtime_up); the check imports Warp only where it is loaded already."""
    env = dict(os.environ, PYTHONPATH=str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""),
               WORLD_SIZE="2", LOCAL_RANK="1")
    env.pop("CUDA_VISIBLE_DEVICES", None)
    p = subprocess.run([sys.executable, "-c", ISOLATE], capture_output=True, text=True, env=env, timeout=300, cwd=REPO)
    assert p.returncode == 0 and p.stdout.split()[-1:] == ["ok"], p.stderr
