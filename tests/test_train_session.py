"""train/session.py, the frame reconstruct and stylize share: loop settings from either config, the checkpoint of
other views refused before the run folder is touched, config.yaml written only by a main rank that has a folder."""
import pytest
import torch

from tlvg_warp import InputError
from tlvg_warp.distributed import Dist
from tlvg_warp.stylize.config import StylizeConfig
from tlvg_warp.train.loop import LoopSettings
from tlvg_warp.train.reconstruct import ReconstructConfig
from tlvg_warp.train.session import Session, loop_settings


def test_loop_settings_take_the_keys_each_config_has():
    rc = ReconstructConfig(log_every=7, checkpoint_every=3, checkpoint_seconds=5.0, views_per_step=2,
                           timing_every=9, final_checkpoint=False, render_headroom=1.5)
    assert loop_settings(rc) == LoopSettings(7, 3, 5.0, 2, 9, False, 1.5)
    sc = StylizeConfig(log_every=11, checkpoint_every=4, checkpoint_seconds=6.0, views_per_step=3, render_headroom=0)
    # stylize has no timing_every / final_checkpoint keys: the loop's defaults
    assert loop_settings(sc) == LoopSettings(11, 4, 6.0, 3, render_headroom=0)


@pytest.mark.parametrize("cls", [ReconstructConfig, StylizeConfig])
@pytest.mark.parametrize("bad", [1.0, 0.5, -1, 17, float("nan"), "2"])
def test_render_headroom_is_zero_or_above_one(cls, bad):
    from tlvg_warp.config_io import ConfigError

    with pytest.raises(ConfigError, match="render_headroom"):
        cls(device="cpu", render_headroom=bad).validate()
    assert cls(device="cpu", render_headroom=0).validate().render_headroom == 0


@pytest.mark.parametrize("cfg", [ReconstructConfig(device="cpu"), StylizeConfig(device="cpu")],
                         ids=["reconstruct", "stylize"])
def test_open_refuses_a_checkpoint_of_other_views_before_writing(cfg, tmp_path):
    out = tmp_path / "run"
    s = Session(cfg)
    assert s.device == torch.device("cpu") and s.dist.is_main
    with pytest.raises(InputError, match="different dataset"):
        s.open(out, ["a.png", "b.png"], resume=tmp_path / "old", read_checkpoint=lambda p: {"names": ["c.png"]},
               run_files=("config.yaml",), config_yaml=lambda c: "x: 1\n")
    assert not out.exists()


def test_open_writes_config_yaml_on_the_main_rank_only(tmp_path):
    cfg = ReconstructConfig(device="cpu")
    s = Session(cfg).open(tmp_path / "main", ["a.png"], read_checkpoint=None, run_files=("config.yaml",),
                          config_yaml=lambda c: f"iterations: {c.iterations}\n")
    assert (tmp_path / "main" / "config.yaml").read_text() == f"iterations: {cfg.iterations}\n"
    assert s.checkpoint is None and s.out == tmp_path / "main"
    Session(cfg, Dist(rank=1, world=2, device="cpu")).open(
        tmp_path / "other", ["a.png"], read_checkpoint=None, config_yaml=lambda c: "x: 1\n")
    assert not (tmp_path / "other").exists()
    Session(cfg).open(None, ["a.png"], read_checkpoint=None, config_yaml=lambda c: "x: 1\n")  # nothing to write
