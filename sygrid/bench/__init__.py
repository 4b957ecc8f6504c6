"""Benchmarks: each sweeps its stage's knobs in one run, writes a JSON of figures and a PNG chart, and prints
medians. Speed targets live here, not in timed tests, because these machines are noisy."""
