"""Reports: the demo page and ``diagnose --report`` render whole: no label outside its
figure, captions are text (no Python reprs), nothing wider than the page, spectra in one unit.

The layout check runs everywhere (matplotlib text extents after layout); the browser check needs a
headless Chromium (``chromium``/``chromium-browser``/``google-chrome`` on PATH) and is skipped, saying
so, where none is installed (Debian: ``apt-get install chromium``).
"""
from __future__ import annotations

import re
import shutil
import subprocess
from html.parser import HTMLParser

import numpy as np
import pytest

from magstack.cli.main import main
from magstack.ground.report import Report, clipped_texts, figure, log_binned_psd

REPR = re.compile(r"\{'[^']*':|\[np\.|array\(|<[a-z_.]+ object at 0x")


class _Text(HTMLParser):
    def __init__(self):
        super().__init__()
        self.texts: list[str] = []
        self.labels: list[str] = []
        self._in = []

    def handle_starttag(self, tag, attrs):
        self._in.append(tag)
        if tag == "img":
            self.labels.append(dict(attrs).get("alt", ""))

    def handle_endtag(self, tag):
        if self._in:
            self._in.pop()

    def handle_data(self, data):
        if self._in and self._in[-1] in ("p", "td", "th", "figcaption", "h2", "h1"):
            self.texts.append(data)


@pytest.fixture(scope="module")
def pages(tmp_path_factory, shared_demo):
    """(demo page, diagnose page, layout problems recorded by Report while writing them). The demo page is the
    shared demo run's (tests/conftest.py), which recorded its own."""
    d = tmp_path_factory.mktemp("pages")
    assert shared_demo["code"] == 0, shared_demo["stderr"]
    problems: list = [tuple(p) for p in shared_demo["layout_problems"]]
    real_write = Report.write

    def write(self, path):
        problems.extend(self.layout_problems)
        return real_write(self, path)

    mp = pytest.MonkeyPatch()
    mp.setattr(Report, "write", write)
    try:
        s = d / "s.csv"
        assert main(["simulate", "--program", "full", "--seconds", "900", "--out", str(s), "-q"]) == 0
        assert main(["diagnose", str(s), "--block-s", "30", "--report", str(d / "rep"), "-q"]) == 0
    finally:
        mp.undo()
    return shared_demo["out"] / "report.html", d / "rep" / "diagnosis.html", problems


def test_no_figure_text_is_cut_off(pages):
    assert pages[2] == []


def test_captions_and_tables_are_text_not_python_reprs(pages):
    for page in pages[:2]:
        p = _Text()
        p.feed(page.read_text())
        bad = [t for t in p.texts + p.labels if REPR.search(t)]
        assert bad == [], (page.name, bad)


def test_both_pages_draw_spectra_as_psd_and_the_demo_has_the_engineers_views(pages):
    demo = pages[0].read_text()
    for alt in ("field magnitude before and after calibration", "field-sphere coverage"):
        assert f'alt="{alt}"' in demo
    assert "<th>std err</th>" in demo and "equal-area cells" in demo
    import inspect

    import magstack.cli.demo.report as demo_report
    import magstack.ground.diagnose.figures as diag_figures
    for mod in (demo_report, diag_figures):
        src = inspect.getsource(mod)
        assert "PSD_LABEL" in src and "nT/sqrt(Hz)" not in src


def test_clipped_texts_finds_a_label_outside_the_figure():
    fig, ax = figure(3, 2)
    ax[0, 0].set_xticks([0, 1], ["session_offset_and_a_very_long_name", "x"], rotation=30, ha="right")
    assert clipped_texts(fig) != []          # without layout the long rotated label is cut
    rep = Report("t")
    rep.image(fig, "long labels")
    assert rep.layout_problems == []          # the report's layout brings it inside


def test_log_binned_psd_keeps_the_white_level():
    f = np.linspace(0.01, 5.0, 5000)
    p = np.random.default_rng(1).exponential(4.0, size=(f.size, 3))
    fb, pb = log_binned_psd(f, p)
    assert fb.size < 60 and pb.shape == (fb.size, 3)
    assert np.allclose(np.median(pb, axis=0), 4.0, rtol=0.15)


_BROWSER = next((b for b in ("chromium", "chromium-browser", "google-chrome") if shutil.which(b)), None)
_OVERFLOW_PROBE = ("<script>window.addEventListener('load',()=>{const w=document.documentElement.clientWidth;"
                   "const bad=[...document.querySelectorAll('body *')].filter(e=>e.getBoundingClientRect().right>w+1)"
                   ".map(e=>e.tagName);document.body.setAttribute('data-overflow',bad.join(','));});</script>")


@pytest.mark.skipif(_BROWSER is None, reason="no headless Chromium on PATH (Debian: apt-get install chromium)")
@pytest.mark.parametrize("which", [0, 1])
def test_pages_render_in_a_headless_browser_without_overflow(pages, tmp_path, which):
    page = pages[which]
    probe = tmp_path / page.name
    probe.write_text(page.read_text().replace("</body>", _OVERFLOW_PROBE + "</body>"))
    common = [_BROWSER, "--headless", "--no-sandbox", "--disable-gpu", "--window-size=1280,900"]
    shot = tmp_path / "shot.png"
    r = subprocess.run([*common, f"--screenshot={shot}", probe.as_uri()], capture_output=True, timeout=120)
    assert r.returncode == 0 and shot.stat().st_size > 10_000, r.stderr[-500:]
    dom = subprocess.run([*common, "--virtual-time-budget=5000", "--dump-dom", probe.as_uri()],
                         capture_output=True, text=True, timeout=120).stdout
    m = re.search(r'data-overflow="([^"]*)"', dom)
    assert m is not None and m.group(1) == "", (page.name, m and m.group(1))


def test_interrupted_report_leaves_no_empty_folder(tmp_path, monkeypatch):
    """A report stopped before it is written leaves no empty folder behind."""
    import magstack.ground.diagnose.figures as figs

    s = tmp_path / "s.csv"
    assert main(["simulate", "--program", "steps_xyz", "--seconds", "600", "--out", str(s), "-q"]) == 0

    def stop(*a, **k):
        raise KeyboardInterrupt
    monkeypatch.setattr(figs, "_spectrum", stop)   # interrupted while drawing
    assert main(["diagnose", str(s), "--block-s", "30", "--report", str(tmp_path / "rep"), "-q"]) == 130
    assert not (tmp_path / "rep").exists()


def test_page_titles_name_their_inputs(pages):
    demo_title = re.search(r"<h1>(.*?)</h1>", pages[0].read_text()).group(1)
    assert re.search(r"seed 1, 300 s of coil program &#x27;full_in_range&#x27;, held-out 300 s", demo_title), demo_title
    diag_title = re.search(r"<h1>(.*?)</h1>", pages[1].read_text()).group(1)
    assert diag_title.startswith("magstack diagnose s.csv: "), diag_title


def test_demo_residual_axes_are_linear_and_show_the_bulk_with_spikes_counted_on_the_edge():
    """A few coil-step pairing spikes of 8 uT must neither set the scale (the 30 nT residual would be a flat line)
    nor call for a symlog axis nobody can read: linear axes at 8 robust sigmas, the spikes drawn on the edge."""
    from magstack.cli.demo import report as demo_report
    from magstack.data.session import Session

    rng = np.random.default_rng(5)
    n = 2000
    t = np.arange(n) * 0.25
    ref = 40.0 * np.stack([np.sin(t / 30), np.cos(t / 30), np.sin(t / 70)], axis=1)
    res_uT = rng.normal(0.0, 0.030, (n, 3))
    res_uT[[100, 700, 1500], 1] = 8.0
    cal = Session(t, ref, ref + res_uT, np.full(n, 25.0), np.zeros(n, int))
    raw = Session(t, ref, 1.05 * ref + 0.4, np.full(n, 25.0), np.zeros(n, int))
    figs = [demo_report._holdout_error_figure(raw, cal), demo_report._residual_vs_figure(cal),
            demo_report._magnitude_figure(raw, cal)]
    checked = 0
    for fig in figs:
        for ax in fig.axes:
            assert ax.get_yscale() == "linear" and ax.get_xscale() == "linear"
            if "nT" in ax.get_ylabel():
                lo, hi = ax.get_ylim()
                assert -hi == pytest.approx(lo) and 4 * 30.0 < hi < 400.0, (ax.get_ylabel(), lo, hi)
                notes = [tx.get_text() for tx in ax.texts if "drawn on the edge" in tx.get_text()]
                assert notes and re.match(r"\d+ points beyond", notes[0])
                checked += 1
    assert checked == 4
    assert demo_report.residual_limit_nT(res_uT * 1e3) == pytest.approx(8 * 30.0, rel=0.1)
