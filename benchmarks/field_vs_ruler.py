"""Is the stroke field the flow terms train toward the one the ruler scores against? Per scene x painting, on photos
in place of un-stylized renders: the training field (luminance features of the view at x0.5 matched top-k to the
painting at its working height, the view's height x vgg_scale x stroke_scale, field taken at that height), the same
with the painting's field taken at 256 rows, and `evaluate`'s common field (RGB features, nearest cell, the painting
at 256 rows). Prints the coherence-weighted agreement (mean cos 2Δθ, 1 = the same field). On the CPU:

    python benchmarks/field_vs_ruler.py starry_night.jpg shipwreck.jpg
"""
import os
import sys
from pathlib import Path

import cv2
import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from tlvg_warp.eval.refs import common_field  # noqa: E402
from tlvg_warp.losses import (  # noqa: E402
    field_at_cells, flatten_feats, luminance, map_field_matched, match_style_cells, resize_style, stroke_field)
from tlvg_warp.losses.vgg import load_vgg  # noqa: E402

torch.set_num_threads(2)
S = os.environ.get('SHARED', '../shared') + '/data/'
vgg = load_vgg("hed", device="cpu")


def rd(p, h):
    im = cv2.imread(p)[:, :, ::-1].astype(np.float32) / 255; s = h / im.shape[0]
    return np.ascontiguousarray(cv2.resize(im, (round(im.shape[1] * s), h), interpolation=cv2.INTER_AREA))


scenes = {'beer': ([S + 'scenes/beer_colmap/images/%04d.jpg' % i for i in range(0, 60, 12)], 640),
          'fern': ([S + 'scenes/fern_llff/images_4/' + f for f in sorted(os.listdir(S + 'scenes/fern_llff/images_4'))[::5]], 378)}


def agree(a, b):
    a = torch.as_tensor(a).double(); b = torch.as_tensor(b).double()
    return float((a * b).sum() / (a.norm(dim=-1) * b.norm(dim=-1)).sum())


for st in sys.argv[1:]:
    paint = rd(S + 'styles/' + st, 1024)
    w256 = resize_style(paint, 256)
    with torch.no_grad():
        sf256 = vgg(torch.from_numpy(w256))
    ruler_cells = field_at_cells(stroke_field(w256)[2], tuple(sf256.shape[-2:]))
    ruler_feats = torch.nn.functional.normalize(flatten_feats(sf256).double(), dim=0)
    for sc, (files, vh) in scenes.items():
        work = resize_style(paint, int(round(vh * 0.5 * 2)))
        with torch.no_grad():
            sfl = vgg(luminance(torch.from_numpy(work)), scale=1.0)
        cells_work = torch.from_numpy(field_at_cells(stroke_field(work)[2], tuple(sfl.shape[-2:])))
        cells_256 = torch.from_numpy(field_at_cells(stroke_field(w256)[2], tuple(sfl.shape[-2:])))
        res = {'work': [], 'f256': [], 'work_vs_f256': []}
        for f in files:
            ph = rd(f, vh)
            ref = common_field(vgg, ph, paint, ruler_cells, ruler_feats)
            with torch.no_grad():
                fe = vgg(luminance(torch.from_numpy(ph)), scale=0.5)
            idx, wt = match_style_cells(flatten_feats(fe), flatten_feats(sfl))
            dA = map_field_matched(cells_work, idx, wt, vh, ph.shape[1], tuple(fe.shape[-2:]))[2]
            dB = map_field_matched(cells_256, idx, wt, vh, ph.shape[1], tuple(fe.shape[-2:]))[2]
            res['work'].append(agree(dA, ref)); res['f256'].append(agree(dB, ref)); res['work_vs_f256'].append(agree(dA, dB))
        print(sc, st, 'work height', work.shape[0], {k: round(float(np.mean(v)), 3) for k, v in res.items()}, flush=True)
