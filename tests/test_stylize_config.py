"""StylizeConfig: YAML `base:` inheritance, key=value overrides (dotted keys; old flat names with a note), bad
keys/values naming their file, the Lab chroma schedule and the phase split. Oracles: the YAML files as written
(read with plain yaml), hand-computed schedule values."""
from pathlib import Path

import pytest
import yaml

from tlvg_warp.config_io import flatten
from tlvg_warp.errors import InputError
from tlvg_warp.stylize import StylizeConfig, config_yaml, load_config
from tlvg_warp.stylize.config import config_from_dict

CONFIGS = Path(__file__).resolve().parents[1] / "configs"
SCHEDULE_TOL = 1e-12  # the schedule is one affine expression in float64


# what each ablation changes: one component of the method each (paper §4.4, SPEC §3 "Configs")
ABLATIONS = {
    # the advection branch: flow gradients + moving μ
    "ablation_no_advection": {"geometry.lock_xyz", "loss.w_align", "loss.w_aniso"},
    "ablation_rgb_loss": {"loss.luminance_only"},  # the style term's input
    "ablation_no_density": {"density.phases"},  # [pre, stylize] -> [pre]
    "ablation_canvas_field": {"loss.field_mapping"},
}


def _dotted(d: dict, prefix="") -> dict:
    out = {}
    for k, v in d.items():
        out.update(_dotted(v, f"{prefix}{k}.") if isinstance(v, dict) else {prefix + k: v})
    return out


def test_every_shipped_config_loads_and_ablations_change_one_thing(capsys):
    tlvg = flatten(load_config(CONFIGS / "tlvg.yaml"))
    assert {p.stem for p in CONFIGS.glob("ablation_*.yaml")} == set(ABLATIONS)
    for name, keys in ABLATIONS.items():
        raw = yaml.safe_load((CONFIGS / f"{name}.yaml").read_text())
        assert raw.pop("base") == "tlvg.yaml"
        assert set(_dotted(raw)) == keys, name
        cfg = flatten(load_config(CONFIGS / f"{name}.yaml"))
        changed = {k for k, v in cfg.items() if v != tlvg[k]}
        assert changed == keys, (name, changed)
    from tlvg_warp.train.reconstruct import load_config as load_reconstruct

    for p in CONFIGS.glob("*.yaml"):  # the shipped files use the current names only (no deprecation note)
        if p.stem != "study_paper":
            (load_reconstruct if p.stem == "reconstruct" else load_config)(p)
    assert "note" not in capsys.readouterr().err


# ABC-GS as released (vpx-ecnu/ABC-GS): configs/llff_single.yaml, abcgs/configs/__init__.py, abcgs/phases/*.py,
# gs/scene/gaussian_model.py. Our key -> its value (translated to our units where the comment says so).
ABCGS = {
    "iterations": 1400, "phases": [400, 600, 400],  # iterations_pre_process / _stylize / _post_process (LLFF)
    "loss.style_loss": "fast", "loss.luminance_only": False,
    "loss.w_style": 2.0, "loss.w_content": 0.005, "loss.w_depth": 0.01,
    "loss.w_tv": 0.01,  # lambda_img_tv 0.02 on a mean of two
    "loss.w_opacity_reg": 1.0, "loss.w_scale_reg": 1.0, "loss.w_lab_start": 0.0, "loss.w_lab_end": 0.0,
    "loss.w_align": 0.0, "loss.w_aniso": 0.0, "geometry.tangential_lambda": 0.0,
    "lr.means": 0.0, "lr.means_final": 0.0, "geometry.lock_xyz": True,  # spatial_lr_scale stays 0 for a loaded PLY
    "lr.sh_dc": 0.0025, "lr.sh_rest": 0.000125, "lr.opacity": 0.05, "lr.scales": 0.005, "lr.quats": 0.001,
    "density.phases": ["pre"], "density.interval": 50, "density.grad_threshold": 2e-4,
    "density.percent_dense": 0.01, "density.split_mode": "3dgs", "density.min_opacity": 0.005,
    "density.max_screen_size": 20.0, "density.size_rules": "always", "density.max_world_size": 0.1,
    "density.opacity_reset_interval": 0, "density.use_budget": False, "density.prune_unseen": False,
    "palette_init": False, "keep_sh": True, "vgg_scale": 0.5, "style_height": 256,
}


def test_abcgs_is_the_released_code():
    raw = yaml.safe_load((CONFIGS / "abcgs.yaml").read_text())
    assert "base" not in raw  # not TLVG with parts switched off
    b = flatten(load_config(CONFIGS / "abcgs.yaml"))
    for k, v in ABCGS.items():
        assert b[k] == v, k
    assert load_config(CONFIGS / "abcgs.yaml").phase_steps() == (400, 600, 400)
    # every value in the file carries a comment naming where it comes from (or is a continuation of one);
    # section headers (a key with a nested mapping) carry none
    for line in (CONFIGS / "abcgs.yaml").read_text().splitlines():
        head = line.split("#")[0]
        if line.strip() and not line.lstrip().startswith("#") and ":" in head and head.split(":", 1)[1].strip():
            assert "#" in line, line


def test_tlvg_is_what_spec_says():
    t = load_config(CONFIGS / "tlvg.yaml")
    assert not t.geometry.lock_xyz and t.loss.luminance_only and t.loss.w_align > 0
    assert t.density.phases == ["pre", "stylize"]
    assert t.geometry.tangential_lambda == 1.0 and t.density.use_budget and t.palette_init
    assert (t.iterations, t.phase_steps()) == (3000, (500, 2000, 500))


def test_base_chain_and_overrides(tmp_path):
    (tmp_path / "a.yaml").write_text("loss:\n  w_style: 3.0\n  w_tv: 0.5\n")
    (tmp_path / "b.yaml").write_text("base: a.yaml\nloss: {w_tv: 0.25}\n")
    cfg = load_config(tmp_path / "b.yaml", ["loss.w_style=4", "loss.field_mapping=canvas", "geometry.lock_xyz=true"])
    assert (cfg.loss.w_style, cfg.loss.w_tv, cfg.loss.field_mapping, cfg.geometry.lock_xyz) == (4.0, 0.25, "canvas", True)
    assert cfg.loss.w_content == StylizeConfig().loss.w_content


def test_old_flat_names_still_load_with_one_note(tmp_path, capsys):
    (tmp_path / "old.yaml").write_text("w_style: 3.0\ndensify_interval: 7\ndensity_in_stylize: false\n")
    cfg = load_config(tmp_path / "old.yaml", ["w_align=0.5", "lr_means=0.001"])
    assert (cfg.loss.w_style, cfg.density.interval, cfg.density.phases) == (3.0, 7, ["pre"])
    assert (cfg.loss.w_align, cfg.lr.means) == (0.5, 0.001)
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "w_style -> loss.w_style" in err[0] and "lr_means -> lr.means" in err[0]
    # a config that fails says only why: no note line
    with pytest.raises(InputError, match="w_tv"):
        load_config(None, ["w_align=0.5", "w_tv=lots"])
    assert capsys.readouterr().err == ""


def test_base_loop_is_an_error(tmp_path):
    (tmp_path / "a.yaml").write_text("base: b.yaml\n")
    (tmp_path / "b.yaml").write_text("base: a.yaml\n")
    with pytest.raises(InputError, match="loops"):
        load_config(tmp_path / "a.yaml")


@pytest.mark.parametrize("over, msg", [
    (["w_algn=0.1"], "loss.w_align"),  # unknown key: named, with the close match
    (["loss.w_algn=0.1"], "loss.w_align"),
    (["no_such_thing=1"], "no_such_thing"),
    (["geometry.tangential_lambda=1.5"], r"\[0, 1\]"),
    (["loss.w_style=-1"], ">= 0"),
    (["loss.style_loss=l2"], "fast, nnfm, gram"),
    (["iterations=abc"], "cannot use"),
    (["iterations"], "key=value"),
    (["loss=3"], "section"),
    (["density.phases=[pre, bogus]"], "bogus"),
])
def test_bad_overrides_are_input_errors(over, msg):
    with pytest.raises(InputError, match=msg):
        load_config(None, over)


def test_unknown_key_and_bad_value_name_their_file(tmp_path):
    (tmp_path / "c.yaml").write_text("base: " + str(CONFIGS / "tlvg.yaml") + "\nlr:\n  mean: 1\n")
    with pytest.raises(InputError, match=r"c\.yaml: unknown config key 'lr\.mean'.*lr\.means"):
        load_config(tmp_path / "c.yaml")
    (tmp_path / "d.yaml").write_text("base: c.yaml\n")  # the culprit is the base, named as such
    with pytest.raises(InputError, match=r"c\.yaml: unknown config key"):
        load_config(tmp_path / "d.yaml")
    (tmp_path / "e.yaml").write_text("geometry: {tangential_lambda: 3}\n")  # a rule, traced to its file
    with pytest.raises(InputError, match=r"e\.yaml: config geometry\.tangential_lambda must be in \[0, 1\]"):
        load_config(tmp_path / "e.yaml")


def test_lab_schedule_values():
    c = StylizeConfig().loss
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
    c = load_config(CONFIGS / "abcgs.yaml", ["loss.w_align=0.3", "background=[1, 1, 1]"])
    (tmp_path / "r.yaml").write_text(config_yaml(c))
    assert load_config(tmp_path / "r.yaml") == c
    assert config_from_dict(yaml.safe_load(config_yaml(c))) == c
