"""Reproducible studies of published calibration methods (ground-side analysis)."""
