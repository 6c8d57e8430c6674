"""StylizeConfig: YAML `base:` inheritance, key=value overrides, bad keys/values, the Lab chroma schedule and
the phase split. Oracles: the YAML files as written (read with plain yaml), hand-computed schedule values."""
from pathlib import Path

import pytest
import yaml

from tlvg_warp.errors import InputError
from tlvg_warp.stylize import StylizeConfig, config_yaml, load_config
from tlvg_warp.stylize.config import config_from_dict

CONFIGS = Path(__file__).resolve().parents[1] / "configs"
SCHEDULE_TOL = 1e-12  # the schedule is one affine expression in float64


def test_every_shipped_config_loads_and_ablations_state_only_differences():
    tlvg = load_config(CONFIGS / "tlvg.yaml")
    for name in ("abcgs", "ablation_no_advection", "ablation_rgb_loss", "ablation_no_density",
                 "ablation_canvas_field"):
        raw = yaml.safe_load((CONFIGS / f"{name}.yaml").read_text())
        assert raw.pop("base") == "tlvg.yaml"
        cfg = load_config(CONFIGS / f"{name}.yaml")
        for k, v in vars(cfg).items():  # every key not in the file is inherited from tlvg.yaml
            assert v == (raw[k] if k in raw else getattr(tlvg, k)), (name, k)
        assert raw and all(getattr(tlvg, k) != v for k, v in raw.items()), f"{name} restates an inherited value"


def test_baseline_is_what_spec_says():
    b = load_config(CONFIGS / "abcgs.yaml")
    assert b.lock_xyz and not b.luminance_only and b.w_align == 0 and b.w_aniso == 0 and not b.density_in_stylize
    t = load_config(CONFIGS / "tlvg.yaml")
    assert not t.lock_xyz and t.luminance_only and t.w_align > 0 and t.density_in_stylize
    assert (t.iterations, t.phase_steps()) == (3000, (500, 2000, 500))


def test_base_chain_and_overrides(tmp_path):
    (tmp_path / "a.yaml").write_text("w_style: 3.0\nw_tv: 0.5\n")
    (tmp_path / "b.yaml").write_text("base: a.yaml\nw_tv: 0.25\n")
    cfg = load_config(tmp_path / "b.yaml", ["w_style=4", "field_mapping=canvas", "lock_xyz=true"])
    assert (cfg.w_style, cfg.w_tv, cfg.field_mapping, cfg.lock_xyz) == (4.0, 0.25, "canvas", True)
    assert cfg.w_content == StylizeConfig().w_content


def test_base_loop_is_an_error(tmp_path):
    (tmp_path / "a.yaml").write_text("base: b.yaml\n")
    (tmp_path / "b.yaml").write_text("base: a.yaml\n")
    with pytest.raises(InputError, match="loops"):
        load_config(tmp_path / "a.yaml")


@pytest.mark.parametrize("over, msg", [
    (["w_algn=0.1"], "w_align"),  # unknown key: named, with the close match
    (["no_such_thing=1"], "no_such_thing"),
    (["tangential_lambda=1.5"], r"\[0, 1\]"),
    (["w_style=-1"], ">= 0"),
    (["style_loss=l2"], "fast, nnfm, gram"),
    (["iterations=abc"], "cannot use"),
    (["iterations"], "key=value"),
])
def test_bad_overrides_are_input_errors(over, msg):
    with pytest.raises(InputError, match=msg):
        load_config(None, over)


def test_unknown_key_in_file(tmp_path):
    (tmp_path / "c.yaml").write_text("base: " + str(CONFIGS / "tlvg.yaml") + "\nlr_mean: 1\n")
    with pytest.raises(InputError, match="unknown config key 'lr_mean'.*lr_means"):
        load_config(tmp_path / "c.yaml")


def test_lab_schedule_values():
    c = StylizeConfig()
    n = 2000
    assert c.lab_weight(0, n) == pytest.approx(0.2, abs=SCHEDULE_TOL)
    assert c.lab_weight(n - 1, n) == pytest.approx(0.05, abs=SCHEDULE_TOL)
    assert c.lab_weight((n - 1) / 2, n) == pytest.approx(0.125, abs=SCHEDULE_TOL)
    w = [c.lab_weight(k, n) for k in range(n)]
    assert all(a > b for a, b in zip(w, w[1:]))  # strictly decreasing, linear steps
    assert max(abs((a - b) - 0.15 / (n - 1)) for a, b in zip(w, w[1:])) < 1e-12


@pytest.mark.parametrize("total", [1, 7, 30, 120, 3000, 3001])
def test_phase_split_sums(total):
    c = StylizeConfig(iterations=total)
    pre, sty, post = c.phase_steps()
    assert pre + sty + post == total and min(pre, sty, post) >= 0
    assert abs(pre - total / 6) <= 0.5 and abs(post - total / 6) <= 0.5


def test_resolved_yaml_round_trips(tmp_path):
    c = load_config(CONFIGS / "abcgs.yaml", ["w_align=0.3", "background=[1, 1, 1]"])
    (tmp_path / "r.yaml").write_text(config_yaml(c))
    assert load_config(tmp_path / "r.yaml") == c
    assert config_from_dict(yaml.safe_load(config_yaml(c))) == c
