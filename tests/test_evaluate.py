"""`python -m tlvg_warp evaluate` on hand-made run folders: outputs, the view-dependence oracle, bad input."""
import json
import re

import numpy as np
import pytest
import torch

from _eval_helpers import make_run
from tlvg_warp.cli import main
from tlvg_warp.commands import evaluate as E
from tlvg_warp.errors import InputError
from tlvg_warp.io.demo import orbit_cameras

# A view-independent (SH degree 0) scene rendered consistently: the error left is resampling of the demo's
# high-contrast checkers/stripes (aliased at 48x36) and expected depth blended across grazing discs and
# silhouettes. Measured: 0.054 on the original demo colors, 0.082 on the fixture's inverted ones (median
# pixel error 0.026); 0.12 leaves margin while a view-dependent scene (below) is ~0.15 and more.
CONSISTENT_RMSE = 0.12


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    a = make_run(tmp_path_factory.mktemp("run_a"))[0]
    b = make_run(tmp_path_factory.mktemp("run_b"), view_dependent=2.0)[0]
    return a, b


def test_cameras_json_round_trip(tmp_path):
    from _eval_helpers import cameras_json

    cams = orbit_cameras(5, 40, 30)
    (tmp_path / "cameras.json").write_text(json.dumps(cameras_json(cams)))
    names, back = E.cameras_from_json(tmp_path / "cameras.json")
    assert names == [c.name for c in cams]
    for c, d in zip(cams, back):
        assert torch.allclose(c.world_to_camera, d.world_to_camera, atol=1e-12)
        assert (c.fx, c.fy, c.cx, c.cy, c.width, c.height) == (d.fx, d.fy, d.cx, d.cy, d.width, d.height)


def test_evaluate_writes_json_and_self_contained_report(runs, tmp_path):
    a, b = runs
    out = tmp_path / "ev"
    assert main(["evaluate", str(a), "--against", str(b), "--vgg-weights", "random", "--out", str(out),
                 "--device", "cpu"]) == 0
    res = json.loads((out / "evaluation.json").read_text())
    s, so = res["summary"], res["against"]["summary"]
    assert res["vgg_random"] is True
    for k in ("flow_alignment", "consistency_k1", "consistency_k5", "style_fast", "style_gram", "content"):
        assert s[k] is not None and np.isfinite(s[k]), k
    assert s["nan"] == 0 and s["gaussians"] > 1000 and s["bytes"] > s["gaussians"] * 4
    assert s["wall_time_s"] == pytest.approx(3.5)  # the phases of the fixture's metrics.json
    assert -1 <= s["flow_alignment"] <= 1
    # 7 views: 6 short pairs, 2 long pairs
    assert res["consistency"]["k1"]["pairs"] == 6 and res["consistency"]["k5"]["pairs"] == 2
    assert s["consistency_k1"] < CONSISTENT_RMSE
    # oracle: run B adds strong view-dependent color (random degree-1 SH) to the same geometry, so its
    # reprojected colors disagree, more so at long range; everything else is equal
    assert so["consistency_k1"] > 1.5 * s["consistency_k1"]
    assert so["consistency_k5"] > so["consistency_k1"]
    assert res["comparison"]["consistency_k1"]["better"] == "run"
    assert res["comparison"]["gaussians"]["better"] == "tie"
    html = (out / "evaluation.html").read_text()
    assert "src='http" not in html and "<link" not in html  # nothing fetched from outside
    imgs = re.findall(r"src='data:image/png;base64,", html)
    # per view: photo, original, run, against (4 x 7) + painting + stroke field
    assert len(imgs) == 4 * 7 + 2
    assert "randomly initialized" in html


def test_evaluate_defaults_to_run_folder(runs):
    a, _ = runs
    assert main(["evaluate", str(a), "--vgg-weights", "random", "--max-views", "3", "--device", "cpu"]) == 0
    res = json.loads((a / "evaluation.json").read_text())
    assert len(res["per_view"]) == 3 and res["consistency"]["k5"]["rmse"] is None  # no pair 5 apart in 3
    assert (a / "evaluation.html").is_file()


def test_stored_target_fields_are_used(tmp_path):
    a = make_run(tmp_path / "r", n_views=2)[0]
    E_run = E.load_run(a)
    from tlvg_warp.losses.stroke_field import stroke_field

    (a / "fields").mkdir()
    for c, img in zip(E_run["cameras"], E_run["renders"]):  # the render's own field: score exactly 1
        np.save(a / "fields" / f"{c.name}.npy", stroke_field(img.numpy())[2])
    from tlvg_warp.losses.vgg import load_vgg

    res = E.evaluate_run(E.load_run(a), load_vgg("random"), torch.device("cpu"))
    assert res["flow_target"] == "stored"
    assert res["summary"]["flow_alignment"] == pytest.approx(1.0, abs=1e-5)


def test_bad_input(tmp_path, runs, capsys):
    assert main(["evaluate", str(tmp_path / "nope"), "--vgg-weights", "random"]) == 2
    assert "run folder not found" in capsys.readouterr().err
    a, _ = runs
    bad = tmp_path / "bad"
    bad.mkdir()
    (bad / "stylized.ply").write_bytes((a / "stylized.ply").read_bytes())
    with pytest.raises(InputError, match="cameras.json: missing file"):
        E.load_run(bad)
    (bad / "cameras.json").write_text("[{\"img_name\": \"x\"}]")
    with pytest.raises(InputError, match="camera 0 lacks"):
        E.load_run(bad)
    (bad / "cameras.json").write_text("{not json")
    with pytest.raises(InputError, match="unreadable JSON"):
        E.load_run(bad)
    (bad / "cameras.json").write_text((a / "cameras.json").read_text())
    with pytest.raises(InputError, match="no painting"):
        E.load_run(bad)
    (bad / "style.png").write_bytes(b"not a png")
    with pytest.raises(InputError, match="unreadable image"):
        E.load_run(bad)
    (bad / "style.png").write_bytes((a / "style.png").read_bytes())
    (bad / "renders").mkdir()
    (bad / "renders" / "view_000.png").write_bytes((a / "style.png").read_bytes())  # wrong size
    with pytest.raises(InputError, match="expected 48x36"):
        E.load_run(bad)
    with pytest.raises(InputError, match="stylized.ply"):
        E.load_run(a / "renders")
