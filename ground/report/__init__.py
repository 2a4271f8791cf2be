"""Self-contained HTML reports with embedded PNG figures (matplotlib Agg): one module, reused by
``magstack diagnose --report`` and (later) the demo."""
from magstack.ground.report.html import Report, figure, require_matplotlib

__all__ = ["Report", "figure", "require_matplotlib"]
