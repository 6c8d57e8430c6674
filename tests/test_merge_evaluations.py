"""benchmarks/merge_evaluations.py's ruler check: two evaluations of the same fits are one ruler when their anchors
agree on every view to 1e-9 (another thread count sums in another order), not when a view differs more, a metric is
missing or a view is unscored on one side. Loaded by path."""
import copy

import pytest
from _bench_helpers import load_benchmark


@pytest.fixture(scope="module")
def merge():
    return load_benchmark("merge_evaluations.py")


def _evaluation():
    per = {"flow_alignment": [0.81, 0.79, 0.8], "consistency_k1": [0.0399755352403662, 0.0361825233517265, None]}
    return {"references": "key", "views": [0, 1, 2], "anchors": [{"name": "no stylization", "per_view": per},
                                                                  {"name": "sticker", "per_view": copy.deepcopy(per)}]}


def test_anchors_alike_to_the_last_digits_are_one_ruler(merge):
    a, b = _evaluation(), _evaluation()
    assert merge.same_ruler(a, b)
    b["anchors"][0]["per_view"]["consistency_k1"][0] = 0.03997553524036623  # the last digit, as seen in a study
    assert merge.same_ruler(a, b)


@pytest.mark.parametrize("change", ["value", "missing metric", "unscored view", "views"])
def test_anchors_that_differ_are_refused(merge, change):
    a, b = _evaluation(), _evaluation()
    per = b["anchors"][1]["per_view"]
    if change == "value":
        per["flow_alignment"][1] *= 1 + 1e-6
    elif change == "missing metric":
        del per["consistency_k1"]
    elif change == "unscored view":
        per["flow_alignment"][2] = None
    else:
        b["views"] = [0, 1, 3]
    assert not merge.same_ruler(a, b)
