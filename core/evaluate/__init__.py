"""Metrics, budget sweeps, reports and plots. Reporting tier (numpy, matplotlib, numba render)."""
