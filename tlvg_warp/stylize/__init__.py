"""The product: flow-guided stylization of a 3DGS scene ("Thinking Like Van Gogh" on ABC-GS).

``StylizeConfig`` / ``load_config`` (config.py), ``run_stylize`` (pipeline.py: the three phases),
``write_outputs`` (outputs.py: the run folder). The CLI is ``python -m tlvg_warp stylize``."""
from .config import StylizeConfig, config_yaml, load_config
from .pipeline import StylizeDiverged, StylizeInputs, StylizeResult, load_checkpoint, run_stylize


def __getattr__(name):  # outputs pulls in matplotlib: only when asked for
    if name == "write_outputs":
        from .outputs import write_outputs
        return write_outputs
    raise AttributeError(name)


__all__ = ["StylizeConfig", "config_yaml", "load_config", "StylizeDiverged", "StylizeInputs", "StylizeResult",
           "load_checkpoint", "run_stylize", "write_outputs"]
