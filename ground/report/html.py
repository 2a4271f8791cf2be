"""One self-contained HTML page: headings, paragraphs, tables and PNG figures embedded as base64.

Figures come from matplotlib with the Agg backend (no display needed; the ``ground`` extra). The page
is written whole or not at all (:func:`magstack.data.io.atomic_write_text`: exclusive temp file,
fsync, rename). Text is HTML-escaped.
"""
from __future__ import annotations

import base64
import html
import io
from pathlib import Path

import numpy as np

from magstack.data.io import atomic_write_text
from magstack.drivers.errors import ConfigurationError

#: Resolution of the page's figures (dots per inch).
_DPI = 90

#: Nothing may be wider than the page: long text wraps, wide tables scroll inside themselves, images shrink.
_CSS = ("body{font-family:sans-serif;max-width:1100px;margin:2em auto;padding:0 1em;color:#222}"
        "p{overflow-wrap:anywhere}pre{white-space:pre-wrap;overflow-wrap:anywhere;font-size:.85em}"
        "table{border-collapse:collapse;margin:1em 0;display:block;max-width:100%;overflow-x:auto}"
        "td,th{border:1px solid #bbb;padding:3px 8px;text-align:right}"
        "th{background:#eee}td:first-child,th:first-child{text-align:left}img{max-width:100%;height:auto}"
        "figure{margin:1em 0}figcaption{font-size:.9em;color:#444}"
        ".verdict{font-size:1.3em;padding:.5em;background:#eef5ff;border-left:4px solid #36c}")


def require_matplotlib():
    """pyplot with the Agg backend; ConfigurationError (exit 2) naming the extra when it is missing."""
    try:
        import matplotlib
    except ImportError:
        raise ConfigurationError("the HTML report needs matplotlib (the ground extra): "
                                 "pip install 'magstack[ground]'") from None
    matplotlib.use("Agg", force=True)
    import matplotlib.pyplot as plt
    return plt


def figure(width_in: float = 9.0, height_in: float = 3.5, nrows: int = 1, ncols: int = 1):
    """A new (fig, axes) on the Agg backend."""
    plt = require_matplotlib()
    return plt.subplots(nrows, ncols, figsize=(width_in, height_in), squeeze=False)


def clipped_texts(fig) -> list[str]:
    """What of ``fig`` is drawn outside the figure after layout (1 pixel tolerance): per axes its
    title (or "axes N") when its drawn extent (labels, tick labels, legend, annotations) reaches
    beyond the figure, and the figure's own texts (suptitle, figure legends)."""
    fig.canvas.draw()
    renderer = fig.canvas.get_renderer()
    box = fig.bbox

    def outside(e) -> bool:
        return e is not None and (e.x0 < box.x0 - 1 or e.y0 < box.y0 - 1 or e.x1 > box.x1 + 1 or e.y1 > box.y1 + 1)

    out = [ax.get_title() or ax.get_xlabel() or f"axes {i}" for i, ax in enumerate(fig.axes)
           if outside(ax.get_tightbbox(renderer))]
    out += [t.get_text() for t in fig.texts if t.get_visible() and outside(t.get_window_extent(renderer))]
    out += ["figure legend" for lg in fig.legends if outside(lg.get_window_extent(renderer))]
    return out


class Report:
    """Build a page with :meth:`heading`, :meth:`text`, :meth:`table`, :meth:`image`; :meth:`write` it."""

    def __init__(self, title: str) -> None:
        self.title = title
        self._parts: list[str] = []
        #: Text of figures that did not fit inside the figure after layout (image alt, text); such a
        #: figure is saved with a tight bounding box instead, so nothing is cut off on the page.
        self.layout_problems: list[tuple[str, str]] = []

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

    def image(self, fig, alt: str, caption: str | None = None) -> None:
        """Embed a matplotlib figure as a PNG (the figure is closed), with an optional text caption.

        Layout: matplotlib's constrained layout, then everything drawn is checked to lie inside the
        figure (:func:`clipped_texts`); anything still outside is recorded in :attr:`layout_problems`
        and the PNG is saved with a tight bounding box so it is not cut off."""
        plt = require_matplotlib()
        buf = io.BytesIO()
        fig.set_layout_engine("constrained")
        fig.set_dpi(_DPI)
        out = clipped_texts(fig)          # draws the figure once, at the page's resolution
        self.layout_problems += [(alt, t) for t in out]
        if out:
            fig.savefig(buf, format="png", dpi=_DPI, bbox_inches="tight", pad_inches=0.1)
        else:                             # the drawing is the page's image: encode it instead of drawing again
            from matplotlib.image import imsave

            imsave(buf, np.asarray(fig.canvas.buffer_rgba()), format="png")
        plt.close(fig)
        b64 = base64.b64encode(buf.getvalue()).decode("ascii")
        cap = f"<figcaption>{html.escape(caption)}</figcaption>" if caption else ""
        self._parts.append(f'<figure><img alt="{html.escape(alt)}" src="data:image/png;base64,{b64}">{cap}</figure>')

    def render(self) -> str:
        return (f"<!DOCTYPE html><html><head><meta charset='utf-8'><title>{html.escape(self.title)}</title>"
                f"<style>{_CSS}</style></head><body><h1>{html.escape(self.title)}</h1>"
                + "\n".join(self._parts) + "</body></html>\n")

    def write(self, path) -> Path:
        """Write the page atomically; returns the path."""
        return atomic_write_text(path, self.render())
