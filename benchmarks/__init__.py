"""Benchmark suite: ADS-B truth, radar simulation, the product's estimators against Stone Soup
and FilterPy baselines on the same plots, metrics, report and figures.

Run ``python -m benchmarks.run`` (``--quick`` for a two-minute smoke run)."""
