"""benchmarks/pool_seeds.py: a config's seeds pooled into one run of (seed, view) items, the anchors repeated once per
seed, so the paired comparison of the pooled runs is the mean difference over every item (checked against numpy on
the concatenated arrays), and a pair with a missing seed is refused. Loaded by path."""
import numpy as np
import pytest
from _bench_helpers import load_benchmark


@pytest.fixture(scope="module")
def pool_seeds():
    return load_benchmark("pool_seeds.py")


def _evaluation(rng, names, n_views=5):
    runs = [{"name": n, "run": n, "summary": {"gaussians": 10 + i}, "per_view": {
        "flow_alignment": rng.uniform(0.5, 0.9, n_views).tolist(), "chroma_noise": rng.uniform(0, 1, n_views).tolist()}}
        for i, n in enumerate(names)]
    anchors = [{"name": a, "summary": {}, "per_view": {"flow_alignment": rng.uniform(0.3, 0.8, n_views).tolist(),
                                                      "chroma_noise": rng.uniform(0, 1, n_views).tolist()}}
               for a in ("no stylization", "sticker")]
    return {"names": names, "runs": runs, "anchors": anchors, "views": list(range(n_views)), "comparisons": {}}


def test_pooled_items_and_paired_means(pool_seeds):
    rng = np.random.default_rng(3)
    ev = _evaluation(rng, ["a", "a1", "a2", "b", "b1", "b2"])
    out = pool_seeds.pool(ev, {"A": ["a", "a1", "a2"], "B": ["b", "b1", "b2"]})
    by = {r["name"]: r["per_view"]["flow_alignment"] for r in ev["runs"]}
    a = np.concatenate([by["a"], by["a1"], by["a2"]])
    b = np.concatenate([by["b"], by["b1"], by["b2"]])
    runs = {r["name"]: r for r in out["runs"]}
    assert out["names"] == ["A", "B"]
    np.testing.assert_allclose(runs["A"]["per_view"]["flow_alignment"], a)
    assert runs["A"]["summary"]["flow_alignment"]["mean"] == pytest.approx(a.mean())
    assert runs["A"]["summary"]["gaussians"] == 10  # the first seed's scalars
    # the paired difference of the pooled runs is the item-wise mean difference, in evaluate's "A vs B" = A - B
    assert out["comparisons"]["A vs B"]["flow_alignment"]["mean"] == pytest.approx((a - b).mean())
    # each anchor repeated once per seed keeps the run-vs-anchor comparison paired item by item
    un = np.asarray(ev["anchors"][0]["per_view"]["flow_alignment"])
    un3 = np.tile(un, 3)
    np.testing.assert_allclose(out["anchors"][0]["per_view"]["flow_alignment"], un3)
    assert out["comparisons"]["A vs no stylization"]["flow_alignment"]["mean"] == pytest.approx((a - un3).mean())
    # each seed's own mean is kept beside the pooled interval
    assert out["seed_spread"]["B"]["b1"]["flow_alignment"] == pytest.approx(np.mean(by["b1"]))


def test_missing_seed_refused(pool_seeds):
    ev = _evaluation(np.random.default_rng(4), ["a", "a1", "b", "b1"])
    assert pool_seeds.pool(ev, {"A": ["a", "a1", "a2"], "B": ["b", "b1"]}) is None


def test_intervals_draw_seeds_then_views(pool_seeds):
    """Seeds whose views sit at 0, 1 and 2 (within-seed spread 1e-3): the pooled interval spans the seeds (about
    [0, 2], the all-lowest and all-highest draws of three seeds), where a bootstrap over the 15 items as if
    independent would give about 1 ± 0.4."""
    rng = np.random.default_rng(5)
    ev = _evaluation(rng, ["a", "a1", "a2", "b", "b1", "b2"])
    for r, mu in zip(ev["runs"], (0.0, 1.0, 2.0, 0.0, 0.0, 0.0)):
        r["per_view"]["flow_alignment"] = (mu + rng.normal(0, 1e-3, 5)).tolist()
    out = pool_seeds.pool(ev, {"A": ["a", "a1", "a2"], "B": ["b", "b1", "b2"]})
    s = {r["name"]: r["summary"]["flow_alignment"] for r in out["runs"]}["A"]
    assert s["lo"] == pytest.approx(0.0, abs=0.01) and s["hi"] == pytest.approx(2.0, abs=0.01)
    # against B (every seed near 0) the paired interval carries the same spread down to about 0: one of A's seeds
    # is no better than B, so the comparison does not call it (items taken as independent would: A by about 1)
    c = out["comparisons"]["A vs B"]["flow_alignment"]
    assert c["lo"] == pytest.approx(0.0, abs=0.01) and c["better"] == "no difference"


def test_seeds_on_different_views_refused(pool_seeds):
    """A config whose seeds were scored on fewer views than the other's: the items would not pair, so no pooling."""
    ev = _evaluation(np.random.default_rng(6), ["a", "a1", "b", "b1"])
    ev["runs"][3]["per_view"]["flow_alignment"] = ev["runs"][3]["per_view"]["flow_alignment"][:4]
    assert pool_seeds.pool(ev, {"A": ["a", "a1"], "B": ["b", "b1"]}) is None
