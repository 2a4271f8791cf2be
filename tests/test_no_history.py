"""The docs, code and tests describe the product as it is: no work history, no development-machine paths.

History (what changed, when, why) lives in CHANGELOG.md and the git log; this test keeps it out of everything
else. It reads README.md, hil/README.md, every Markdown file under docs/, mkdocs.yml, and every source, test,
benchmark and CI file (``.py``, ``.c``, ``.h``, ``.sh``, ``.toml``, ``.yml``, ``.ci/run``), and fails listing
``file:line: text`` for each line that matches one of :data:`PATTERNS`:

* ``issue`` references to this project's tracker: ``issue N``, ``issues N and M``, ``Issue N item M``,
  ``issue #N``. A reader of the manual cannot follow them; say what the product does instead.
* ``session N`` as a development stage. ``session`` is also a product word (bench sessions, ``session 0`` is the
  frame, ``--sessions``, "session 1 -> 2" in a report), so only the history forms are matched: ``session N``
  followed by a date or commit, ``(..., session N)``, ``(session N: ...)`` or ``session N: 16 s`` labelling a
  measurement, a comment line ``# session N ...``,
  ``since/until/the end of/named in session N``.
* ``round N`` / ``stage N`` (development rounds; the product has no numbered rounds or stages).
* commit hashes (7-40 hex digits with both a digit and a letter) quoted as the provenance of a figure or a
  change.
* narrative of change: ``used to``, ``previously``, ``formerly``, ``no longer`` (as in "the reader used to ...").
  A sentence says what the product does now.
* development-machine paths: the development host's work tree, ``../shared/...``, a helper's virtualenv (``venv-NAME``),
  ``/home/...`` (``/home/pi``, the Raspberry Pi's user, is a target path). A source is cited as the datasheet,
  paper or data set it is (title, section, DOI or URL).

The ``/tmp`` rule: ``/tmp/...`` may appear only where a user or the product writes there at run time - an
option value in an example command (``--out /tmp/x``, ``--workdir /tmp/w``) or the run directory of
``hil/pi-emulated-check.sh`` (``magstack-pi-check``); it is never a source citation. Any other ``/tmp/`` fails.

:data:`ALLOWED` lists the exact lines that match a pattern and are not history, each with its reason.
CHANGELOG.md is exempt: it is where the history goes. This file is exempt as it spells the patterns out."""
from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SKIP_DIRS = {".git", "build", "dist", "site", "node_modules", "__pycache__", ".pytest_cache", ".ruff_cache",
             ".hypothesis", ".venv", "venv"}
SUFFIXES = {".py", ".c", ".h", ".sh", ".toml", ".yml", ".yaml"}

HEX = r"(?<![0-9A-Za-z_./-])(?!0[bx])(?=[0-9a-f]*[a-f])(?=[0-9a-f]*[0-9])[0-9a-f]{7,40}(?![0-9A-Za-z_])"
PATTERNS = {
    "issue reference": re.compile(r"\bissues?\s+#?\d+", re.I),
    "session N as a development stage": re.compile(
        r"\bsession\s+\d+\s*[,(]\s*(?:\d{4}-\d\d-\d\d|code\b|" + HEX + ")"
        r"|\(session\s+\d+:|[,;]\s*session\s+\d+\)"
        r"|^\s*#\s*[-(]*\s*session\s+\d+\b"
        r"|\bsession\s+\d+:\s*\d+(?:\.\d+)?\s*(?:s|ms|MiB|B/row)\b"
        r"|\b(?:since|until|the end of|named in|as of|measured in)\s+session\s+\d+", re.I),
    "round/stage N": re.compile(r"\b(?:round|stage)\s+\d+\b", re.I),
    "commit hash": re.compile(HEX),
    "narrative of change": re.compile(r"\b(?:used to (?!check|de-skew|build|make|find|read|write|tell|run|"
                                      r"decide|compute|set|hold|pick|mark|say|keep|form|scale|draw|test)|"
                                      r"previously|formerly|no longer)\b", re.I),
    "development-machine path": re.compile(r"(?<![\w.])/wor[k]/|\.\./shared/|\bvenv-[a-z]+\b"
                                           r"|(?<![\w.])/home/(?!pi\b)\w"),
    "/tmp outside a run-time path": re.compile(r"(?<![\w.])/tmp/(?!magstack-pi-check)"),
}
#: /tmp/ as an option value of an example command: a path the user's run writes to.
TMP_AS_OPTION = re.compile(r"--[a-z-]+[ =]/tmp/")

#: (path, regex a matching line must contain, reason). Each entry must still match something.
ALLOWED = [
    ("tests/test_i2c_register_model.py", r"PX4 issue #12514",
     "an upstream tracker's issue cited as a source (PX4-Autopilot), not this project's history"),
    ("docs/i2c-drivers.md", r"PX4 issue #12514", "an upstream tracker's issue cited as a source"),
    ("sim/lis3mdl_model.py", r"issue #12514", "an upstream tracker's issue cited as a source"),
    ("drivers/ads1248.py", r"no longer match a ChannelConfig", "describes the driver's state, not a change"),
    ("sim/i2c_register_model.py", r"no longer (update|change) them", "describes a frozen register, not a change"),
    ("sim/i2c_register_model.py", r"the core can no longer change", "describes a frozen register, not a change"),
    ("tests/test_lsm303dlhc.py", r"RDY timing no longer advances", "describes the stopped chip, not a change"),
]


def scanned_files() -> list[Path]:
    """Every file the rule covers, relative paths sorted."""
    out = [ROOT / "README.md", ROOT / "hil" / "README.md", ROOT / ".ci" / "run"]
    out += sorted((ROOT / "docs").rglob("*.md")) if (ROOT / "docs").is_dir() else []
    for p in sorted(ROOT.rglob("*")):
        rel = p.relative_to(ROOT)
        if any(part in SKIP_DIRS or part.startswith("venv") or part.endswith(".egg-info") for part in rel.parts):
            continue
        if p.is_file() and p.suffix in SUFFIXES:
            out.append(p)
    return [p for p in dict.fromkeys(out) if p.is_file() and p != Path(__file__).resolve()]


def _allowed(rel: str, line: str) -> bool:
    return any(rel == path and re.search(rx, line) for path, rx, _ in ALLOWED)


def violations() -> list[str]:
    """``file:line: [kind] text`` of every line that carries history or a development path."""
    out = []
    for p in scanned_files():
        rel = p.relative_to(ROOT).as_posix()
        for n, line in enumerate(p.read_text(encoding="utf-8", errors="replace").splitlines(), 1):
            for kind, rx in PATTERNS.items():
                if not rx.search(line) or _allowed(rel, line):
                    continue
                if kind.startswith("/tmp") and TMP_AS_OPTION.search(line):
                    continue
                out.append(f"{rel}:{n}: [{kind}] {line.strip()[:160]}")
    return out


def test_no_work_history_or_development_paths():
    found = violations()
    assert not found, ("work history or development-machine paths (history goes to CHANGELOG.md; cite sources "
                       "by title/section/DOI/URL):\n" + "\n".join(found))


def test_every_allowance_is_still_needed():
    """An allowance whose line is gone is removed, so the list stays the list of real exceptions."""
    texts = {}
    unused = []
    for path, rx, _ in ALLOWED:
        if path not in texts:
            f = ROOT / path
            texts[path] = f.read_text(encoding="utf-8") if f.is_file() else ""
        if not re.search(rx, texts[path]):
            unused.append((path, rx))
    assert not unused


def test_the_patterns_catch_history_and_spare_the_product_words():
    """The patterns can fail: history forms are caught, the product's uses of 'session' are not."""
    # the examples are split where a literal would be caught by a plain grep of the tree
    history = ["fixed in issue " "25", "Issues 6 and 13", "Issue " "17 item 3: strict", "(`kept_rows.py`, session 9)",
               "session 9, 2026-11-26 01:23", "session 7: 16.4 s", "since session 9 they are read",
               "the end of session 8", "# (session 4) the hysteresis case", "code 7bbee44", "round 2",
               "cite /wo" "rk/shared/seeds/x.txt", "copy is ../shared/realdata", "/wo" "rk/venv-manual/bin/python",
               "the reader used to take it", "previously 3 s", "no longer shows", "see /tmp/notes.txt"]
    product = ["session 0 = frame", "session 1 -> 2", "mount rotations relative to session 0",
               "room-temperature sweeps (session 1, +-50 uT steps)",
               "sweeps at room temperature (session 1), then", "s.temp_c = 20 + x   # session 1 starts warmer",
               "session 5 left out: the other sessions",
               "--sessions 4", "magstack bench --seconds 60 --out /tmp/s.csv", "0x1E", "0b00001",
               "the bias used to check the sign", "rundir=/tmp/magstack-pi-check", "a 1598371866.645 epoch"]

    def hit(s):
        return any(rx.search(s) for k, rx in PATTERNS.items()
                   if not (k.startswith("/tmp") and TMP_AS_OPTION.search(s)))
    assert [s for s in history if not hit(s)] == []
    assert [s for s in product if hit(s)] == []


def test_the_rule_covers_every_page_of_the_manual_and_its_build():
    """Every Markdown page under docs/ (the how-to, reference and explanation folders included), mkdocs.yml and the
    hooks that generate pages are scanned."""
    scanned = {p.relative_to(ROOT).as_posix() for p in scanned_files()}
    pages = {p.relative_to(ROOT).as_posix() for p in (ROOT / "docs").rglob("*.md")}
    assert {"docs/tutorial.md", "docs/how-to/add-a-sensor.md", "docs/reference/index.md",
            "docs/explanation/index.md"} <= pages
    assert pages <= scanned and {"mkdocs.yml", "tools/mkdocs_hooks.py", "hil/README.md"} <= scanned
