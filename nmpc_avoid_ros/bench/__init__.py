"""Benchmarks: our solver paths and their Python peers on the same scenarios, in one process."""
