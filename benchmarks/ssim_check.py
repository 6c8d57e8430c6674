"""The fused Warp SSIM / fit loss on CUDA against its torch twin (development aid, run on a GPU).

python3 benchmarks/ssim_check.py  -> value and gradient differences (float32 and float64) and the forward+backward
time of both at the fit's 1008x756 and the stylize pre/post 504x378 (CUDA events, median of 50 after warm-up)."""
import torch

from tlvg_warp.losses.ssim import fit_loss, fit_loss_torch


def run(fn, img, ref):
    x = img.clone().requires_grad_(True)
    v = fn(x, ref, 0.2)
    v.backward()
    return v.detach(), x.grad


def timed(fn, img, ref, reps=50):
    x = img.clone().requires_grad_(True)
    for _ in range(5):
        fn(x, ref, 0.2).backward()
    ts = []
    for _ in range(reps):
        a, b = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
        a.record()
        fn(x, ref, 0.2).backward()
        b.record()
        torch.cuda.synchronize()
        ts.append(a.elapsed_time(b))
    return sorted(ts)[len(ts) // 2]


torch.manual_seed(0)
for dt in (torch.float64, torch.float32):
    ref = torch.rand(189, 252, 3, device="cuda", dtype=dt)
    img = (ref + 0.1 * torch.randn_like(ref)).clamp(0, 1)
    (va, ga), (vb, gb) = run(fit_loss, img, ref), run(fit_loss_torch, img, ref)
    print(f"{dt}: |value diff| {abs(va - vb).item():.3e}, max |grad diff| {(ga - gb).abs().max().item():.3e}, "
          f"max |grad| {gb.abs().max().item():.3e}")
for h, w in ((756, 1008), (378, 504)):
    ref = torch.rand(h, w, 3, device="cuda")
    img = (ref + 0.1 * torch.randn_like(ref)).clamp(0, 1)
    tf, tt = timed(fit_loss, img, ref), timed(fit_loss_torch, img, ref)
    print(f"fit loss fwd+bwd {w}x{h}: fused {tf:.3f} ms, torch {tt:.3f} ms ({tt / tf:.1f}x)")
