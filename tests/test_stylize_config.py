"""StylizeConfig: YAML `base:` inheritance, key=value overrides (dotted keys; old flat names with a note), bad
keys/values naming their file, the Lab chroma schedule and the phase split. Oracles: the YAML files as written
(read with plain yaml), hand-computed schedule values."""
import re
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
    # the colour preservation: the style term's input AND the Lab chroma loss
    "ablation_rgb_loss": {"loss.luminance_only", "loss.w_lab_start", "loss.w_lab_end"},
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
    # the object preset holds the positions and changes nothing else (its comment's figures are for that one change)
    obj = flatten(load_config(CONFIGS / "tlvg_object.yaml"))
    assert {k for k, v in obj.items() if v != tlvg[k]} == {"geometry.lock_xyz"} and obj["geometry.lock_xyz"] is True
    # the light preset: the default without the deep Gram term and the tone hold and with the flow terms halved,
    # nothing else (its figures are for those); the swd and contrast presets sit on it (measured without either)
    light = flatten(load_config(CONFIGS / "tlvg_light.yaml"))
    assert {k: v for k, v in light.items() if v != tlvg[k]} == {
        "loss.w_style_deep": 0.0, "loss.w_align": tlvg["loss.w_align"] / 2, "loss.w_orient": tlvg["loss.w_orient"] / 2,
        "loss.w_tone_hold": 0.0}
    assert tlvg["loss.w_tone_hold"] > 0 and tlvg["loss.tone_margin"] > 0  # the default holds the tone, as a hinge
    assert tlvg["loss.deep_loss"] == "gram" and tlvg["loss.w_style_deep"] > 0
    # the contrast preset changes the Lab term's target spread and its blocks, nothing else (its figures are for those)
    contrast = flatten(load_config(CONFIGS / "tlvg_contrast.yaml"))
    assert {k for k, v in contrast.items() if v != light[k]} == {"loss.lab_sigma", "loss.lab_block"}
    assert (contrast["loss.lab_sigma"], contrast["loss.lab_block"]) == ("painting", 0.03)
    swd = flatten(load_config(CONFIGS / "tlvg_swd.yaml"))
    assert {k for k, v in swd.items() if v != light[k]} == {"loss.w_style_swd", "loss.w_color_swd"}
    from tlvg_warp.train.reconstruct import load_config as load_reconstruct

    for p in CONFIGS.glob("*.yaml"):  # the shipped files use the current names only (no deprecation note)
        if not p.stem.startswith("study_"):  # study files are not stylize configs
            (load_reconstruct if p.stem == "reconstruct" else load_config)(p)
    assert "note" not in capsys.readouterr().err


FILE_NAMED = re.compile(r"[\w./-]+\.(py|yaml)\b")  # a file of the released repository, e.g. gs/scene/gaussian_model.py


def _value_comments(path):
    """{dotted key: its comment} of every value line of a YAML file, the comment being the line's own plus the
    comment-only lines that continue it; and {section: the comment lines just above its header}."""
    comments, sections, section, above, last = {}, {}, "", [], None
    for line in path.read_text().splitlines():
        stripped = line.strip()
        if not stripped:
            continue
        if stripped.startswith("#"):
            if last is not None and line.startswith(" " * 2) and line.index("#") > 4:  # continuation of a value
                comments[last] += " " + stripped
            else:
                above.append(stripped)
                last = None
            continue
        head, _, comment = line.partition("#")
        key, _, value = head.partition(":")
        if not line.startswith(" "):
            section = key.strip()
        if not value.strip():  # a section header
            sections[section], above = " ".join(above), []
            continue
        last = f"{section}.{key.strip()}" if line.startswith(" ") else key.strip()
        comments[last] = comment.strip()
        above = []
    return comments, sections


def test_abcgs_values_each_name_their_source_file():
    """Every value of abcgs.yaml says where in the released code it comes from: its comment names a file, or
    continues the comment of the value just above it in the same section, which names one ("(same)";
    "position_lr_final x 0" under "position_lr_init x 0 (gs/scene/gaussian_model.py)"), or the section's header
    comment names the file the section follows. A value without a comment never passes. Oracle: the file's text
    (a value added without a source fails)."""
    comments, sections = _value_comments(CONFIGS / "abcgs.yaml")
    assert len(comments) >= 30
    prev_key, prev_named = None, False
    for key, c in comments.items():
        section = key.split(".")[0] if "." in key else ""
        same_section = prev_key is not None and prev_key.split(".")[0] == section and section != ""
        named = bool(c) and (bool(FILE_NAMED.search(c)) or (same_section and prev_named)
                             or bool(section and FILE_NAMED.search(sections.get(section, ""))))
        assert named, (key, c)
        prev_key, prev_named = key, named


def test_abcgs_loads_as_written_and_runs_with_its_values(tmp_path):
    """abcgs.yaml read by plain yaml.safe_load (the oracle) against the config loader: every key it states is the
    value the loader hands the run, nothing inherited (no `base:`). Then a short run: its phases split as
    400/600/400 do (here 4/6/4 of 14 steps), xyz never moves (lr 0, no hook, density not due), the Lab and flow
    terms stay 0, and the optimizer's xyz learning rate is 0 at every step of the real 1400-step schedule."""
    import json

    import torch

    from _demo_helpers import demo_stylize_inputs
    from tlvg_warp.stylize import run_stylize
    from tlvg_warp.train.optim import GaussianOptimizer, GaussianParams

    raw = yaml.safe_load((CONFIGS / "abcgs.yaml").read_text())
    assert "base" not in raw  # not TLVG with parts switched off
    cfg = load_config(CONFIGS / "abcgs.yaml")
    loaded = flatten(cfg)
    for k, v in _dotted(raw).items():
        assert loaded[k] == v, (k, loaded[k], v)
    steps = cfg.phase_steps()
    assert steps == tuple(raw["phases"]) and sum(steps) == raw["iterations"]
    _, inp = demo_stylize_inputs(3, 24, 18, every=8)
    opt = GaussianOptimizer(GaussianParams(inp.gaussians), cfg.lr, 2.0, cfg.lr.means_steps or cfg.iterations)
    assert all(opt.set_step(k) == 0.0 and opt.lr("means") == 0.0 for k in range(0, raw["iterations"], 50))
    short = load_config(CONFIGS / "abcgs.yaml", ["iterations=14", "device=cpu", "vgg_weights=random",
                                                 "log_every=1", "orbit_frames=0", "comparison_views=1"])
    assert short.phase_steps() == (4, 6, 4)
    res = run_stylize(inp, short, tmp_path / "run", progress=False, quiet=True)
    phases = [r["phase"] for r in res.log]
    assert phases == ["pre"] * 4 + ["stylize"] * 6 + ["post"] * 4
    assert res.gaussians.num == inp.gaussians.num
    assert torch.equal(res.gaussians.means.cpu(), inp.gaussians.means)
    assert all(r["lab"] == 0.0 and r["align"] == 0.0 and r["aniso"] == 0.0 for r in res.log), json.dumps(res.log[5])


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
    (["loss.content_on=lum"], "rgb, luminance"),
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
