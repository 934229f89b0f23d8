"""Scoring against ground truth, results and reports: ``needletrack eval`` and ``needletrack
results``, the graphs they run, the live graph's speed. May import every package above it in
docs/architecture.md's table (not ``bench``, ``robustness`` or ``adapt``).
"""
