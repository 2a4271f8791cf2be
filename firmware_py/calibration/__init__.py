"""Calibration: measurement equation (model), batch fit (fit), streaming fit (streaming)."""
from magstack.firmware.calibration.fit import FitData, FitOptions, FitResult, fit
from magstack.firmware.calibration.model import CAL_TERMS, MODELS, CalModel, resolve_terms

__all__ = ["CAL_TERMS", "MODELS", "CalModel", "FitData", "FitOptions", "FitResult", "fit", "resolve_terms"]
