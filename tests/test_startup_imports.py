"""Start-up pays only for what a command uses. Checked on ``sys.modules`` of a fresh
interpreter (no timing here; benchmarks/bench_startup.py measures the time)."""
from __future__ import annotations

import json
import subprocess
import sys

HEAVY = ("scipy.stats", "matplotlib", "pandas", "dask", "magstack.ground.diagnose")


def heavy_imports(code: str) -> list[str]:
    """The HEAVY modules loaded after running ``code`` in a fresh interpreter."""
    probe = f"{code}\nimport json, sys\nprint(json.dumps(sorted(m for m in {HEAVY!r} if m in sys.modules)))"
    r = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    return json.loads(r.stdout.strip().splitlines()[-1])


def test_the_command_entry_and_top_level_help_import_nothing_heavy():
    code = ("import contextlib, io\nfrom magstack.cli.main import main\n"
            "with contextlib.redirect_stdout(io.StringIO()):\n    main(['--help'])")
    assert heavy_imports(code) == []
    assert heavy_imports("import numpy, sys; from magstack.cli import main, output, options, progress") == []


def test_only_the_named_command_module_is_imported():
    code = ("import contextlib, io, sys\nfrom magstack.cli.main import main\n"
            "with contextlib.redirect_stdout(io.StringIO()):\n    main(['probe', '--help'])\n"
            "assert 'magstack.cli.commands.fit' not in sys.modules\n"
            "assert 'magstack.cli.commands.probe' in sys.modules")
    assert heavy_imports(code) == []


def test_on_board_flight_modules_import_no_scipy_stats():
    # the table and the flight code take the term lists from firmware/cal_terms.py, not the calibration fit
    assert heavy_imports("import magstack.firmware.flight.app, magstack.firmware.corrector") == []


def test_a_refit_run_imports_no_statistics_plotting_demo_or_diagnosis(tmp_path):
    # a whole `magstack refit` process pays for the reader (pandas) and the fit, nothing else
    from magstack.cli.main import main

    tele, out = tmp_path / "t.csv", tmp_path / "c.json"
    assert main(["simulate", "--program", "orbit_tumbling", "--seconds", "3600", "--rate-hz", "1", "--sessions", "1",
                 "--t0", "1780272000", "--out", str(tele), "-q"]) == 0
    code = ("import sys\nfrom magstack.cli.main import main\n"
            f"assert main(['refit', {str(tele)!r}, '--out', {str(out)!r}, '-q']) in (0, 1)\n"
            "assert 'magstack.cli.demo' not in sys.modules and 'magstack.cli.commands.demo' not in sys.modules")
    assert heavy_imports(code) == ["pandas"]
    assert out.exists()


def test_a_simulated_flight_run_imports_no_scipy_pandas_or_matplotlib(tmp_path):
    """`magstack run --sim` is the flight application: with every library installed it still loads none of the
    ground's (tests/test_lean_install.py runs it where they cannot be imported at all)."""
    from magstack.firmware.flight.config import example_config_text

    cfg = tmp_path / "flight.toml"
    cfg.write_text(example_config_text())
    code = ("import contextlib, io, sys\nfrom magstack.cli.main import main\n"
            "with contextlib.redirect_stdout(io.StringIO()):\n"
            f"    rc = main(['run', '--config', {str(cfg)!r}, '--sim', '--duration', '20', '--out', "
            f"{str(tmp_path / 'tlm')!r}, '-q'])\n"
            "assert rc in (0, 1), rc\n"
            "assert not [m for m in ('scipy', 'erfa', 'ppigrf') if m in sys.modules]")
    assert heavy_imports(code) == []
    assert any((tmp_path / "tlm").glob("packets-*.bin"))
