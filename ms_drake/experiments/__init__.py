"""Experiments: bin-search rollouts and the demo, the benchmark harness (result files, statistics,
plots), full-fidelity picks, scene images and grasp figures: the entry points of `ms-drake`."""
