"""Benchmarks that run more than one step of the pipeline (they sit above pipeline.py)."""
