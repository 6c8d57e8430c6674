"""Does the palette transfer move the stroke field? Per scene x painting, the field matched from each photo and from
its palette-recoloured version (the pre-process's target) are compared: coherence-weighted mean cos 2(θa−θb) of the
two doubled-angle fields (1 = the same field). On the CPU, from ../shared/data:

    python benchmarks/field_agreement.py
"""
import os
import sys
from pathlib import Path

import cv2
import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from tlvg_warp.losses.vgg import load_vgg  # noqa: E402
from tlvg_warp.losses import (  # noqa: E402
    color_transfer, field_at_cells, flatten_feats, luminance, map_field_matched, match_style_cells, resize_style,
    stroke_field)

torch.set_num_threads(2)
S = os.environ.get('SHARED', '../shared') + '/data/'
vgg = load_vgg("hed", device="cpu")


def rd(p, h):
    im = cv2.imread(p)[:, :, ::-1].astype(np.float32) / 255; s = h / im.shape[0]
    return np.ascontiguousarray(cv2.resize(im, (round(im.shape[1] * s), h), interpolation=cv2.INTER_AREA))


scenes = {'beer': [S + 'scenes/beer_colmap/images/%04d.jpg' % i for i in range(0, 60, 10)],
          'fern': [S + 'scenes/fern_llff/images_8/' + f for f in sorted(os.listdir(S + 'scenes/fern_llff/images_8'))[::4]]}
H = {'beer': 320, 'fern': 189}
for st in ['starry_night.jpg', 'shipwreck.jpg', 'starry_night_over_the_rhone.png', 'monet_san_giorgio.jpg']:
    for sc, files in scenes.items():
        photos = [torch.from_numpy(rd(f, H[sc] * 2)) for f in files]
        style = resize_style(rd(S + 'styles/' + st, 1024), 2 * 2 * H[sc])   # stroke_scale 2 x view height
        with torch.no_grad():
            sf = vgg(luminance(torch.from_numpy(style)), scale=1.0)
        _, _, sd = stroke_field(style)
        cells = torch.from_numpy(field_at_cells(sd, tuple(sf.shape[-2:])))
        sff = flatten_feats(sf)
        rec, _, _ = color_transfer(photos, torch.from_numpy(style))
        agg = []
        for p, r in zip(photos, rec):
            ds = []
            for img in (p, r):
                with torch.no_grad():
                    f = vgg(luminance(img), scale=0.5)
                idx, w = match_style_cells(flatten_feats(f), sff)
                _, c, d = map_field_matched(cells, idx, w, img.shape[0], img.shape[1], tuple(f.shape[-2:]))
                ds.append(d)
            a, b = ds
            num = (a * b).sum(-1).sum(); den = (a.norm(dim=-1) * b.norm(dim=-1)).sum()
            agg.append(float(num / den))
        print(f"{sc} x {st}: agreement original vs recoloured field {np.mean(agg):.3f} (views {len(agg)})", flush=True)
