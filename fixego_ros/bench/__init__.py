"""Benchmarks: each module has ``run() -> dict`` of named numbers (also printed)."""
