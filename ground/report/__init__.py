"""Self-contained HTML reports with embedded PNG figures (matplotlib Agg), used by
``magstack diagnose --report`` and the demo's page; spectra drawn the same way on both."""
from magstack.ground.report.html import Report, clipped_texts, figure, require_matplotlib
from magstack.ground.report.spectra import PSD_LABEL, log_binned_psd

__all__ = ["Report", "clipped_texts", "figure", "require_matplotlib", "PSD_LABEL", "log_binned_psd"]
