"""The product: flow-guided stylization of a 3DGS scene ("Thinking Like Van Gogh" on ABC-GS).

``StylizeConfig`` / ``load_config`` (config.py), ``run_stylize`` (pipeline.py: the three phases),
``write_outputs`` (outputs.py: the run folder). The CLI is ``python -m tlvg_warp stylize``."""
from .config import StylizeConfig, config_yaml, load_config
from .outputs import write_outputs
from .pipeline import StylizeDiverged, StylizeInputs, StylizeResult, load_checkpoint, run_stylize


__all__ = ["StylizeConfig", "config_yaml", "load_config", "StylizeDiverged", "StylizeInputs", "StylizeResult",
           "load_checkpoint", "run_stylize", "write_outputs"]
