"""Calibration: find what the declared sensor model lacks in measured data, and report it."""
