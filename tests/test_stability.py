"""The stability suite's fast subset: every scenario on a tiny demo (3 views 24x18, ~1.2k Gaussians, 3
iterations, random VGG) finishes with no NaN in any output; hole fraction and failure recording checked."""
import math

import pytest
import torch

from tlvg_warp.eval import stability as S


@pytest.fixture(scope="module")
def suite():
    base = S.demo_base(True, "cpu", n_views=3, size=(24, 18), stride=16, iterations=3)
    base.overrides["vgg_weights"] = "random"

    def boom(b):
        raise RuntimeError("injected failure")
    extra = [S.Scenario("injected_failure", "a scenario that raises", boom)]
    res = S.run_suite(True, "cpu", vgg_weights="random", log=None, base=base, extra=extra,
                      vgg_metrics=False)  # VGG distances are tested in test_eval_metrics; here they cost ~1 s each
    return {r["scenario"]: r for r in res["rows"]}


QUICK = [s.name for s in S.scenarios(6) if s.quick]
# Pipeline bugs this suite has found and that are not fixed yet (strict: a mark must go once fixed).
# Fixed so far: NaN Gaussians in the input (now dropped with a warning), 8x6 images (VGG upsamples tiny input).
KNOWN: dict = {}


@pytest.mark.parametrize("name", [pytest.param(n, marks=pytest.mark.xfail(reason=KNOWN[n], strict=True))
                                  if n in KNOWN else n for n in QUICK])
def test_scenario_finishes_without_nan(suite, name):
    r = suite[name]
    assert r["finished"], r.get("error")
    assert r["nan"] == 0
    assert 0.0 <= r["hole_fraction"] <= 1.0
    assert r["gaussians_out"] >= 1
    for k in ("flow_alignment", "consistency_k1"):  # measured on every finished scenario, and finite
        assert isinstance(r[k], float) and math.isfinite(r[k]), (k, r[k])
    assert -1.0 < r["flow_alignment"] < 1.0 and r["consistency_k1"] < 1.0  # renders in [0,1]: RMSE < 1
    assert r["style_gram"] is None and r["style_fast"] is None  # the suite runs without VGG metrics: not measured


def test_failures_are_recorded_not_raised(suite):
    r = suite["injected_failure"]
    assert r["finished"] is False and r["error"] == "RuntimeError: injected failure" and r["nan"] is None


def test_scenarios_build_what_they_say(suite):
    base = S.demo_base(True, "cpu", n_views=2, size=(24, 18), stride=16, iterations=3)
    n = base.gaussians.num
    sc = {s.name: s for s in S.scenarios(6)}
    g = sc["gauss_nan"].apply(base).gaussians
    bad = ~torch.isfinite(torch.cat([g.means, g.sh.reshape(n, -1)], 1)).all(1)
    assert int(bad.sum()) == 8
    st = sc["gauss_stacked"].apply(base)
    from tlvg_warp import render
    cam = base.cameras[0]
    extra = st.gaussians.subset(slice(n, None))
    assert extra.num == 2000 and torch.unique(extra.means, dim=0).shape[0] == 1
    p = extra.means[0].double() @ cam.R.T + cam.t  # projects onto the center pixel
    uv = torch.stack([cam.fx * p[0] / p[2] + cam.cx, cam.fy * p[1] / p[2] + cam.cy])
    assert torch.allclose(uv, torch.tensor([cam.width / 2 + 0.5, cam.height / 2 + 0.5], dtype=uv.dtype), atol=1e-4)
    near = sc["gauss_near_plane"].apply(base).gaussians.subset(slice(n, None))
    z = near.means.double() @ cam.R[2] + cam.t[2]
    assert torch.allclose(z, torch.full_like(z, 0.02), atol=1e-6)
    tiny = sc["image_tiny"].apply(base)
    assert all((c.width, c.height) == (8, 6) and p.shape == (6, 8, 3) for c, p in zip(tiny.cameras, tiny.photos))
    assert render(st.gaussians, cam).color.isfinite().all()


def test_hole_fraction_counts_only_newly_uncovered_pixels():
    before = [torch.tensor([[True, True], [False, True]])]
    after = [torch.tensor([[0.9, 0.2], [0.1, 0.49]])]
    # covered before: 3; of those, alpha fell under 0.5 at (0,1) and (1,1); (1,0) was never covered
    assert S.hole_fraction(before, after) == pytest.approx(2 / 3)
    assert S.hole_fraction([torch.zeros(2, 2, dtype=torch.bool)], after) == 0.0
