"""One self-contained HTML page: headings, paragraphs, tables and PNG figures embedded as base64.

Figures come from matplotlib with the Agg backend (no display needed; a core dependency). The page
is written whole or not at all (:func:`magstack.data.io.atomic_write_text`: exclusive temp file,
fsync, rename). Text is HTML-escaped.
"""
from __future__ import annotations

import base64
import html
import io
from pathlib import Path

from magstack.data.io import atomic_write_text
from magstack.drivers.errors import ConfigurationError

_CSS = ("body{font-family:sans-serif;max-width:1100px;margin:2em auto;color:#222}"
        "table{border-collapse:collapse;margin:1em 0}td,th{border:1px solid #bbb;padding:3px 8px;text-align:right}"
        "th{background:#eee}td:first-child,th:first-child{text-align:left}img{max-width:100%}"
        ".verdict{font-size:1.3em;padding:.5em;background:#eef5ff;border-left:4px solid #36c}")


def require_matplotlib():
    """pyplot with the Agg backend; ConfigurationError (exit 2) naming the extra when it is missing."""
    try:
        import matplotlib
    except ImportError:
        raise ConfigurationError("the HTML report needs matplotlib: pip install 'magstack[plot]'") from None
    matplotlib.use("Agg", force=True)
    import matplotlib.pyplot as plt
    return plt


def figure(width_in: float = 9.0, height_in: float = 3.5, nrows: int = 1, ncols: int = 1):
    """A new (fig, axes) on the Agg backend."""
    plt = require_matplotlib()
    return plt.subplots(nrows, ncols, figsize=(width_in, height_in), squeeze=False)


class Report:
    """Build a page with :meth:`heading`, :meth:`text`, :meth:`table`, :meth:`image`; :meth:`write` it."""

    def __init__(self, title: str) -> None:
        self.title = title
        self._parts: list[str] = []

    def heading(self, text: str, level: int = 2) -> None:
        self._parts.append(f"<h{level}>{html.escape(text)}</h{level}>")

    def text(self, text: str, css_class: str | None = None) -> None:
        cls = f' class="{css_class}"' if css_class else ""
        self._parts.append(f"<p{cls}>{html.escape(text)}</p>")

    def preformatted(self, text: str) -> None:
        self._parts.append(f"<pre>{html.escape(text)}</pre>")

    def table(self, header: list[str], rows: list[list[object]]) -> None:
        h = "".join(f"<th>{html.escape(str(c))}</th>" for c in header)
        body = "".join("<tr>" + "".join(f"<td>{html.escape(str(c))}</td>" for c in r) + "</tr>" for r in rows)
        self._parts.append(f"<table><tr>{h}</tr>{body}</table>")

    def image(self, fig, alt: str) -> None:
        """Embed a matplotlib figure as a PNG (the figure is closed)."""
        plt = require_matplotlib()
        buf = io.BytesIO()
        fig.tight_layout()
        fig.savefig(buf, format="png", dpi=90)
        plt.close(fig)
        b64 = base64.b64encode(buf.getvalue()).decode("ascii")
        self._parts.append(f'<img alt="{html.escape(alt)}" src="data:image/png;base64,{b64}">')

    def render(self) -> str:
        return (f"<!DOCTYPE html><html><head><meta charset='utf-8'><title>{html.escape(self.title)}</title>"
                f"<style>{_CSS}</style></head><body><h1>{html.escape(self.title)}</h1>"
                + "\n".join(self._parts) + "</body></html>\n")

    def write(self, path) -> Path:
        """Write the page atomically; returns the path."""
        return atomic_write_text(path, self.render())
