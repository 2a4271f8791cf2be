"""Calibration: measurement equation (model), batch fit (fit), streaming fit (streaming)."""
from firmware_py.calibration.fit import FitData, FitOptions, FitResult, fit
from firmware_py.calibration.model import CAL_TERMS, MODELS, CalModel, resolve_terms

__all__ = ["CAL_TERMS", "MODELS", "CalModel", "FitData", "FitOptions", "FitResult", "fit", "resolve_terms"]
