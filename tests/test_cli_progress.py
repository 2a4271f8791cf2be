"""`simulate`'s progress bar advances by rows written, not by finished blocks (no 0 % while rows are
already on disk)."""
from __future__ import annotations

import contextlib

from magstack.cli.main import main


def test_simulate_progress_follows_rows_written(tmp_path, monkeypatch):
    import magstack.cli.commands.simulate as sim

    updates: list[int] = []

    class Bar:
        def update(self, n):
            updates.append(int(n))

    @contextlib.contextmanager
    def fake_bar(total, desc, unit="it", **kw):
        yield Bar()
    monkeypatch.setattr(sim, "bar", fake_bar)
    assert main(["simulate", "--program", "steps_x", "--seconds", "1500", "--rate-hz", "2", "--out",
                 str(tmp_path / "s.csv"), "-q"]) == 0
    assert sum(updates) == 3001
    assert max(updates) <= sim.PROGRESS_ROWS and len([u for u in updates if u]) >= 3
