"""Metrics: the paper's error measures, metrics.json from stored predictions, and the paper's
numbers and findings as checks."""
