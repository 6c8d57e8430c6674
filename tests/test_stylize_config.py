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


# what each ablation changes: one component of the method each (paper §4.4, SPEC §3 "Configs")
ABLATIONS = {
    "ablation_no_advection": {"lock_xyz", "w_align", "w_aniso"},  # the advection branch: flow gradients + moving μ
    "ablation_rgb_loss": {"luminance_only"},  # the style term's input
    "ablation_no_density": {"density_in_stylize"},
    "ablation_canvas_field": {"field_mapping"},
}


def test_every_shipped_config_loads_and_ablations_change_one_thing():
    tlvg = load_config(CONFIGS / "tlvg.yaml")
    assert {p.stem for p in CONFIGS.glob("ablation_*.yaml")} == set(ABLATIONS)
    for name, keys in ABLATIONS.items():
        raw = yaml.safe_load((CONFIGS / f"{name}.yaml").read_text())
        assert raw.pop("base") == "tlvg.yaml"
        assert set(raw) == keys, name
        cfg = load_config(CONFIGS / f"{name}.yaml")
        changed = {k for k, v in vars(cfg).items() if v != getattr(tlvg, k)}
        assert changed == keys, (name, changed)


# ABC-GS as released (vpx-ecnu/ABC-GS): configs/llff_single.yaml, abcgs/configs/__init__.py, abcgs/phases/*.py,
# gs/scene/gaussian_model.py. Our key -> its value (translated to our units where the comment says so).
ABCGS = {
    "iterations": 1400, "phases": [400, 600, 400],  # iterations_pre_process / _stylize / _post_process (LLFF)
    "style_loss": "fast", "luminance_only": False,
    "w_style": 2.0, "w_content": 0.005, "w_depth": 0.01, "w_tv": 0.01,  # lambda_img_tv 0.02 on a mean of two
    "w_opacity_reg": 1.0, "w_scale_reg": 1.0, "w_lab_start": 0.0, "w_lab_end": 0.0,
    "w_align": 0.0, "w_aniso": 0.0, "tangential_lambda": 0.0,
    "lr_means": 0.0, "lr_means_final": 0.0, "lock_xyz": True,  # spatial_lr_scale stays 0 for a loaded PLY
    "lr_sh_dc": 0.0025, "lr_sh_rest": 0.000125, "lr_opacity": 0.05, "lr_scales": 0.005, "lr_quats": 0.001,
    "density_in_pre": True, "density_in_stylize": False, "densify_interval": 50, "densify_grad_threshold": 2e-4,
    "percent_dense": 0.01, "split_mode": "3dgs", "min_opacity": 0.005, "max_screen_size": 20.0, "max_world_size": 0.1,
    "use_budget": False, "prune_unseen": False, "palette_init": False, "keep_sh": True,
    "vgg_scale": 0.5, "style_height": 256,
}


def test_abcgs_is_the_released_code():
    raw = yaml.safe_load((CONFIGS / "abcgs.yaml").read_text())
    assert "base" not in raw  # not TLVG with parts switched off
    b = load_config(CONFIGS / "abcgs.yaml")
    for k, v in ABCGS.items():
        assert getattr(b, k) == v, k
    assert b.phase_steps() == (400, 600, 400)
    # every value in the file carries a comment naming where it comes from (or is a continuation of one)
    for line in (CONFIGS / "abcgs.yaml").read_text().splitlines():
        if line and not line.startswith("#") and ":" in line.split("#")[0] and not line.startswith(" "):
            assert "#" in line, line


def test_tlvg_is_what_spec_says():
    t = load_config(CONFIGS / "tlvg.yaml")
    assert not t.lock_xyz and t.luminance_only and t.w_align > 0 and t.density_in_stylize
    assert t.tangential_lambda == 1.0 and t.use_budget and t.palette_init
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
