"""Benchmarks: each prints ratios measured side by side and writes JSON a script can read."""
