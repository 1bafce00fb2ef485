"""Experiments: bin-search rollouts, the benchmark harness, result files, statistics and plots."""
