"""Which part of a stylize run takes an object's detail: a few views of the run rendered at each stage (the palette's
recoloured photos, which the pre-process fits; the Gaussians the run starts from; the end of each phase), each scored
by `evaluate`'s detail inside (the luminance's residual of a blur over the eroded pixels the un-stylized scene
covers, against the painting's at the evaluation height; 1 = the painting's).

    python benchmarks/phase_detail.py OUT [--views 0,7,14] STYLIZE ARGS ...
    e.g. python benchmarks/phase_detail.py /tmp/pd --scene lego.spz --data lego_blender --style starry_night.jpg

Runs `stylize` with STYLIZE ARGS and `--out OUT/run`, prints one row per stage (detail inside per view and their
mean; the un-stylized scene's in the first row) and writes OUT/phase_detail.json and OUT/phase_detail.png (the
stages of each view side by side). The first row (the un-stylized scene) and the last (after the post-process)
are `evaluate`'s own per-view detail inside for those views and that run. docs/study.md quotes it.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import cv2
import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.append(str(ROOT))  # after an installed package or the GPU scripts' source view

from tlvg_warp import cli  # noqa: E402
from tlvg_warp.eval import metrics as M  # noqa: E402
from tlvg_warp.eval.engine import auto_eval_height  # noqa: E402
from tlvg_warp.renderer import render  # noqa: E402
from tlvg_warp.stylize import pipeline  # noqa: E402

STAGES: dict[str, list] = {}  # stage -> [H,W,3] float images of the chosen views
SIDE: dict = {}  # the un-stylized views' alpha and colour, the painting


def snap(name: str, imgs) -> None:
    STAGES[name] = [np.ascontiguousarray(i.detach().clamp(0, 1).cpu().numpy(), np.float32) for i in imgs]


def instrument(views: list[int]) -> None:
    """Wrap pipeline.build_run so that the run's views are kept at its start and after each phase."""
    build = pipeline.build_run

    def build_run(inp, cfg, tg, *a, **k):
        run = build(inp, cfg, tg, *a, **k)
        cams, bg = [inp.cameras[i] for i in views], tuple(float(v) for v in cfg.background)
        SIDE.update(alpha=[tg.coverage[i][..., 0].cpu().numpy() for i in views],
                    unstylized=[tg.originals[i].numpy() for i in views],
                    painting=inp.style.detach().cpu().numpy().astype(np.float32), cameras=list(inp.cameras))
        snap("palette (the pre-process's targets)", [tg.recolored[i] for i in views])

        def renders(r):
            with torch.no_grad():
                g = r.params.gaussians()
                return [render(g, c, bg).color for c in cams]
        snap("start (refined, palette in the colours)", renders(run))
        inner = run.on_phase_end

        def on_phase_end(r, phase):
            snap(f"after {phase.name}", renders(r))
            return inner(r, phase) if inner is not None else {}
        run.on_phase_end = on_phase_end
        return run
    pipeline.build_run = build_run


def detail_inside(img: np.ndarray, alpha: np.ndarray, painting_hf: float, eval_height: int) -> float:
    ev = M.resize_to_height(img, eval_height)
    return M.detail(ev, painting_hf, M.interior(alpha, ev.shape[:2]))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("out")
    ap.add_argument("--views", default="0,7,14", help="comma-separated view indices (of the run's views)")
    args, stylize_args = ap.parse_known_args()
    views = [int(v) for v in args.views.split(",")]
    out = Path(args.out)
    instrument(views)
    rc = cli.main(["stylize", *stylize_args, "--out", str(out / "run"), "--overwrite"])
    if rc != 0:
        return rc
    h = auto_eval_height(SIDE["cameras"])
    hf = M.hf_energy(M.luma(M.resize_to_height(SIDE["painting"], h)))
    rows = {"un-stylized": SIDE["unstylized"], **STAGES}
    table = {name: [detail_inside(img, a, hf, h) for img, a in zip(imgs, SIDE["alpha"])] for name, imgs in rows.items()}
    print(f"| stage | detail inside, views {args.views} | mean |\n| --- | --- | --- |")
    for name, vals in table.items():
        print(f"| {name} | {' / '.join(f'{v:.3f}' for v in vals)} | {np.mean(vals):.3f} |")
    (out / "phase_detail.json").write_text(json.dumps({"views": views, "eval_height": h, "detail_inside": table},
                                                       indent=1))
    grid = np.vstack([np.hstack([imgs[j] for imgs in rows.values()]) for j in range(len(views))])
    cv2.imwrite(str(out / "phase_detail.png"), cv2.cvtColor((grid * 255 + 0.5).astype(np.uint8), cv2.COLOR_RGB2BGR))
    print(f"columns of {out / 'phase_detail.png'}: {', '.join(rows)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
