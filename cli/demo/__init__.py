"""``magstack demo``: the whole stack end to end on the simulated bench, no hardware needed.

An orchestrator (:func:`run_demo`, cli/demo/run.py) of seven steps, one module each; each step
returns its measured figures (tests assert on them) and prints short lines through ``say``.
What another command needs lives in the library layers, not here:

1. ``probe.py`` - scan the simulated I2C buses (:func:`magstack.drivers.i2c_probe.probe`, lines
   from :func:`~magstack.drivers.i2c_probe.format_probe_result`), bring up the HMC1053 front end
   and read every chip through :func:`magstack.drivers.registry.open_chip`.
2. ``bench.py`` - a bench session from :func:`magstack.hil.bench.record_sim_session` (the recipe of
   ``magstack bench --bus sim``): HMC1053 DUT through the register-level ADC + bridge + error
   model, FVM400 reference over ``fvm400sim://``; coil program ``full``.
3. ``bench.py`` - clock offset, per-axis skew, axis map (:mod:`magstack.ground.alignment`), paired session.
4. ``fit.py`` - Eq. 3 plus the optional terms that help held out
   (:func:`magstack.ground.term_selection.select_terms`), the fit-vs-simulator check
   (:func:`magstack.ground.preset_recovery.recovery_vs_preset`), and the same fit on a thermally
   flat slice to show what is held / refused when the data cannot determine a parameter.
5. ``table.py`` - save, validate, load + activate in a :class:`~magstack.firmware.cal_table.CalTableStore`;
   corrupted copies are refused while the active table stays in force.
6. ``holdout.py`` - an independent session calibrated with the fixed-point applier
   (:func:`magstack.ground.apply_session.calibrate_session`, as ``magstack apply``).
7. ``loop.py`` - the flight executive (:mod:`magstack.firmware.flight`) running a channel with the
   on-board :class:`~magstack.firmware.corrector.TableCorrector`; an SPI fault and a stuck DRDY are
   injected and must show up once each in the health counters and the event log.

``summary.py`` renders the closing table and summary.json. Everything runs in virtual time and
is deterministic for a seed (wall times aside). Units: field uT, temperature degC, time s.
"""
from magstack.cli.demo.config import ARTEFACTS, DEVICE_ID, MAX_SECONDS, MIN_SECONDS, DemoConfig
from magstack.cli.demo.run import STEPS, DemoResult, run_demo
from magstack.cli.demo.summary import figures, summary_lines

__all__ = ["ARTEFACTS", "DEVICE_ID", "MAX_SECONDS", "MIN_SECONDS", "STEPS", "DemoConfig", "DemoResult", "figures",
           "run_demo", "summary_lines"]
