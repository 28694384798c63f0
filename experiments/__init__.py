"""Studies, figures and benchmarks built on fojax and optimize."""
