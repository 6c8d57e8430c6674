"""GPU diagnosis: Warp render and gradients on a real scene against the float64 torch reference."""
import sys

import torch

from tlvg_warp import load_dataset, render
from tlvg_warp.reference import render_reference
from tlvg_warp.train.init import initialize

data = sys.argv[1]
ds = load_dataset(data, images="images_4")
g = initialize(ds, max_sh_degree=1, device="cuda")
g = g[0] if isinstance(g, tuple) else g
torch.manual_seed(0)
g.sh.data[:, 1:] = torch.randn_like(g.sh[:, 1:]) * 0.1
g.opacity_logits.data += torch.randn_like(g.opacity_logits) * 2  # a spread of opacities, high ones included
g.log_scales.data += 0.5
cam = ds.cameras[3].scaled(4.0)
gt = torch.nn.functional.interpolate(ds.image(3).permute(2, 0, 1)[None], size=(cam.height, cam.width),
                                     mode="area")[0].permute(1, 2, 0).cuda()
print("N", g.num, "camera", cam.width, cam.height)
res = {}
for name, dt, fn in (("warp32", torch.float32, render), ("warp64", torch.float64, render),
                     ("ref64", torch.float64, render_reference)):
    gl = g.to(dtype=dt).map(lambda t: t.detach().clone().requires_grad_(True))
    out = fn(gl, cam, return_weights=True)
    loss = (out.color - gt.to(dt)).abs().mean() + 0.1 * out.depth.mean()
    grads = torch.autograd.grad(loss, [gl.means, gl.quats, gl.log_scales, gl.opacity_logits, gl.sh, out.means2d])
    res[name] = (out, grads)
    print(name, "loss", loss.item(), "visible", (out.radii > 0).sum().item())
ref_out, ref_g = res["ref64"]
for name in ("warp64", "warp32"):
    out, gr = res[name]
    print(name, "color maxerr", (out.color.double() - ref_out.color).abs().max().item(),
          "weights rel", ((out.weights.double() - ref_out.weights).abs().max() / ref_out.weights.abs().max()).item())
    for f, a, b in zip(["means", "quats", "log_scales", "opac", "sh", "means2d"], gr, ref_g):
        err = (a.double() - b).abs().max().item()
        print(f"   d/d{f}: max err {err:.3g} (ref max {b.abs().max().item():.3g}), cos {torch.nn.functional.cosine_similarity(a.double().flatten(), b.flatten(), 0).item():.6f}")
