"""Studies, figures and benchmarks built on fojax, run from a clone:
``python -m experiments.NAME`` (not installed)."""
