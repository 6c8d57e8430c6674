"""Evaluation (SPEC §4, paper §4.3): the VLM judge panel and the speed–quality (Pareto) chart."""
