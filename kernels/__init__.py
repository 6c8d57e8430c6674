"""Warp kernels only (installed as ``tlvg_warp.kernels``). Ops that bridge them to torch live in tlvg_warp."""
