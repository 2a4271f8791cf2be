"""``magstack calibrate``: calibration without a coil or a reference, from turning the board by hand.

Two ways in: record live (``--chip C --bus 1`` on a Raspberry Pi, ``--bus sim`` on a host with a simulated
hand-rotation programme) with a terminal view of the field-sphere coverage, or fit recorded session files
(``magstack calibrate SESSION.csv ...``). The fit is attitude-independent (the local field's magnitude:
``--site LAT,LON[,ALT_KM] --date YYYY-MM-DD`` for IGRF-14, ``--field-uT F``, ``--magnitude-from-ref``, or
estimated), with the chip's priors, held-out blocks and a table in the flight format (``--out``); exports with
``--px4 FILE`` / ``--ardupilot FILE``. Ctrl-C while recording stops the recording and fits what was recorded;
a second Ctrl-C interrupts at once. Poor coverage: the report says why and no table is written (exit 3) unless
``--allow-poor-coverage``.
"""
from __future__ import annotations

import argparse
import datetime as _dt
import logging
import math
import sys

import numpy as np

from magstack.cli.interrupt import graceful_stop
from magstack.cli.options import finite_float, float_list, int_range, nonempty_path, nonempty_text
from magstack.cli.output import CommandResult, say
from magstack.drivers.errors import ConfigurationError
from magstack.firmware.errors import CalTableInvalid, FitError

log = logging.getLogger(__name__)
#: The optional extra this command needs (cli/extras.py): the fit and the site's IGRF field.
EXTRA = "ground"
CHIPS = ("lis3mdl", "hmc5983", "lsm303dlhc")
MAX_SECONDS = 3600.0


def _date(text: str) -> float:
    try:
        d = _dt.datetime.strptime(text, "%Y-%m-%d").replace(tzinfo=_dt.UTC)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a date YYYY-MM-DD, got {text!r}") from None
    return d.timestamp()


def _site(text: str) -> tuple[float, float, float]:
    vals = float_list((2, 3), -180.0, 180.0, unit="deg, deg[, km]")(text)
    lat, lon = vals[0], vals[1]
    alt = vals[2] if len(vals) == 3 else 0.0
    if not -90.0 <= lat <= 90.0:
        raise argparse.ArgumentTypeError(f"latitude must be -90..90 deg, got {lat:g}")
    if not -1.0 <= alt <= 100.0:
        raise argparse.ArgumentTypeError(f"altitude must be -1..100 km, got {alt:g}")
    return (lat, lon, alt)


def register(subparsers) -> None:
    p = subparsers.add_parser("calibrate", help="calibrate by turning the board by hand (no coil, no reference)",
                              description="Attitude-independent calibration against the local field's magnitude: "
                                          "record live with a terminal view (--chip, --bus) or fit session files. "
                                          "Ctrl-C while recording stops and fits what was recorded.")
    p.add_argument("sessions", nargs="*", metavar="SESSION.csv", help="recorded session files to fit (no live "
                                                                       "recording)")
    p.add_argument("--chip", choices=CHIPS, default=None, help="part (live: the DUT; files: its priors, default "
                                                               "from the session's dut_chip)")
    p.add_argument("--bus", default=None, help="record live: 'sim' (simulated hand rotations) or an I2C bus "
                                               "('1' or /dev/i2c-1)")
    p.add_argument("--seconds", type=finite_float(0, MAX_SECONDS, lo_open=True, unit="s"), default=300.0,
                   help="longest recording (s, default 300; Ctrl-C stops earlier)")
    p.add_argument("--rate-hz", type=finite_float(0, 150, lo_open=True, unit="Hz"), default=100.0,
                   help="read rate while recording (Hz, default 100)")
    p.add_argument("--record", type=nonempty_path, default=None, metavar="SESSION.csv",
                   help="session file to record into (default: next to --out, .session.csv)")
    p.add_argument("--program", default="hand", help="simulated hand programme (--bus sim): hand, hand_flat, "
                                                     "hand_warm, hand_laptop")
    p.add_argument("--seed", type=int_range(0, 2 ** 31 - 1), default=0, help="simulation seed")
    p.add_argument("--speed", type=finite_float(0, 1000, unit="x"), default=1.0,
                   help="simulation pace relative to wall time (1 = real time; 0 = as fast as possible)")
    p.add_argument("--no-view", action="store_true", help="no terminal view while recording")
    p.add_argument("--site", type=_site, default=None, metavar="LAT,LON[,ALT_KM]",
                   help="where the calibration is done: the field magnitude from IGRF-14 there (with --date)")
    p.add_argument("--date", type=_date, default=None, metavar="YYYY-MM-DD", help="date for --site (default today)")
    p.add_argument("--field-uT", type=finite_float(1, 1000, unit="uT"), default=None,
                   help="the local field magnitude, uT (instead of --site)")
    p.add_argument("--magnitude-from-ref", action="store_true",
                   help="files with a reference instrument: use only its magnitude per row")
    p.add_argument("--soft-iron", choices=("symmetric", "diagonal"), default="symmetric",
                   help="soft-iron matrix: symmetric (6, default) or diagonal (3 scale factors)")
    p.add_argument("--temperature", choices=("auto", "on", "off"), default="auto",
                   help="temperature terms: auto (fitted where the session spans temperature, the chip's prior "
                        "elsewhere), on, off")
    p.add_argument("--frame", choices=("auto", "sensor", "level"), default="auto",
                   help="calibrated frame: level (tilt from a level turn on a table), sensor (the sensor's own "
                        "axes), auto (level when the session has a level turn)")
    p.add_argument("--no-priors", action="store_true", help="no chip priors (unregularised)")
    p.add_argument("--prior", action="append", default=[], metavar="NAME=MEAN+-SD",
                   help="override a parameter's prior, e.g. 'O[z]=0+-5'; repeatable")
    p.add_argument("--allow-poor-coverage", action="store_true",
                   help="write the table even when the coverage is poor (the report names what the data missed)")
    p.add_argument("--no-holdout", action="store_true", help="skip the held-out blocks")
    p.add_argument("--block-s", type=finite_float(0, 1e5, lo_open=True, unit="s"), default=10.0,
                   help="held-out time-block length (s, default 10)")
    p.add_argument("--device-id", type=nonempty_text, default=None, help="device id for the table")
    p.add_argument("--out", type=nonempty_path, required=True, metavar="cal.json", help="calibration table to write")
    p.add_argument("--px4", type=nonempty_path, default=None, metavar="FILE.params", help="also write PX4 parameters")
    p.add_argument("--ardupilot", type=nonempty_path, default=None, metavar="FILE.parm",
                   help="also write ArduPilot parameters")
    p.set_defaults(func=run)


def _field(args) -> tuple[float | None, str]:
    if args.field_uT is not None and args.site is not None:
        raise ConfigurationError("give --site or --field-uT, not both")
    if args.field_uT is not None:
        return float(args.field_uT), "given (--field-uT)"
    if args.site is None:
        if args.date is not None:
            raise ConfigurationError("--date needs --site")
        return None, ""
    from magstack.firmware.reference.geomag import igrf_geodetic_nT

    t = args.date if args.date is not None else _dt.datetime.now(_dt.UTC).timestamp()
    lat, lon, alt = args.site
    b = igrf_geodetic_nT(np.array([t]), lat, lon, alt)[0] / 1e3
    day = _dt.datetime.fromtimestamp(t, _dt.UTC).date().isoformat()
    return float(np.linalg.norm(b)), (f"IGRF-14 at {lat:g}, {lon:g}, {alt:g} km on {day}; inclination "
                                      f"{math.degrees(math.atan2(b[2], math.hypot(b[0], b[1]))):.1f} deg")


def run(args: argparse.Namespace) -> CommandResult:
    from magstack.data.session import load_sessions, refuse_overwriting_inputs

    live = args.bus is not None
    if live == bool(args.sessions):
        raise ConfigurationError("give session files to fit, or --bus (and --chip) to record live, not both")
    if live and args.chip is None:
        raise ConfigurationError("recording live needs --chip")
    if args.magnitude_from_ref and (live or args.site is not None or args.field_uT is not None):
        raise ConfigurationError("--magnitude-from-ref takes the magnitude from the files' reference only")
    field_uT, source = _field(args)
    outputs = [p for p in (args.out, args.px4, args.ardupilot) if p is not None]
    if len({str(p) for p in outputs}) != len(outputs):
        raise ConfigurationError("--out, --px4 and --ardupilot must be different files")
    data: dict = {"out": str(args.out), "written": False, "recording": None, "exports": {}, "notes": []}
    lines: list[str] = []
    if live:
        record = args.record or args.out.with_name(args.out.stem + ".session.csv")
        if str(record) in {str(p) for p in outputs}:
            raise ConfigurationError("--record must differ from the outputs")
        rec = _record(args, record, field_uT)
        data["recording"] = rec
        lines += rec.pop("_lines")
        paths = [str(record)]
    else:
        for o in outputs:
            refuse_overwriting_inputs(o, args.sessions)
        paths = list(args.sessions)
    session, notes = load_sessions(paths)
    data["notes"] += notes
    chip = args.chip or session.metadata.get("dut_chip")
    res = _fit(args, session, chip, field_uT, source)
    data["stats"] = res.stats()
    data["device_id"] = device_id = args.device_id or session.metadata.get("device_id") or chip or "unknown"
    lines += [res.report()]
    truth = data["recording"].get("_truth") if data["recording"] else None
    if truth is not None:
        lines += _truth_lines(res, session, truth)
    if data["recording"]:
        data["recording"].pop("_truth", None)
    if res.refused:
        say("\n".join(lines))
        raise FitError("calibration refused, no table written: " + "; ".join(res.refused) +
                       " (--allow-poor-coverage writes it anyway)")
    from magstack.firmware.cal_table import save_table, validate

    table = res.table(device_id, description=f"hand calibration of {', '.join(paths)}")
    v = validate(table)
    if not v.ok:
        say("\n".join(lines))
        raise CalTableInvalid(f"fitted table fails validation, {args.out} not written: " + "; ".join(v.problems))
    exports = _exports(args, table, session, res)
    save_table(table, args.out)
    for name, (path, ex) in exports.items():
        from magstack.data.io import atomic_write_text

        atomic_write_text(path, ex.text)
        data["exports"][name] = {"path": str(path), "params": ex.params,
                                 "dropped": [d.__dict__ for d in ex.dropped], "notes": ex.notes}
        lines += [f"wrote {path}"] + ex.lines()
    data["written"] = True
    data["crc32"] = table.to_document()["crc32"]
    box = (f"{table.validity_temp_c[0]:g}..{table.validity_temp_c[1]:g} degC" if table.validity_temp_c else
           "any temperature")
    lines += [f"wrote {args.out} (device {device_id}, crc32 {data['crc32']}); validity {box}, "
              f"|B_i| <= {table.validity_field_uT:g} uT"]
    return CommandResult("calibrate", data, lines)


def _fit(args, session, chip, field_uT, source):
    from magstack.cli.commands.fit import prior_overrides
    from magstack.firmware.calibration.handcal import HandCalData, HandCalOptions, calibrate

    dut = session.dut_uT
    rows = np.all(np.isfinite(dut), axis=1)
    r = None
    if args.magnitude_from_ref:
        rows &= np.all(np.isfinite(session.ref_uT), axis=1)
        r = np.linalg.norm(session.ref_uT[rows], axis=1)
    opts = HandCalOptions(chip=chip, soft_iron=args.soft_iron, field_uT=field_uT, field_source=source,
                          temperature=args.temperature, use_priors=not args.no_priors,
                          priors=prior_overrides(args.prior), holdout=not args.no_holdout, block_s=args.block_s,
                          frame=args.frame, allow_poor_coverage=args.allow_poor_coverage)
    return calibrate(HandCalData(dut[rows], session.temp_c[rows], session.t_s[rows], r, session.session[rows],
                                 None if session.flag is None else session.flag[rows]), opts)


def _exports(args, table, session, res) -> dict:
    from magstack.ground.export import load_exporters

    ex = load_exporters()
    out = {}
    rows = res.used if res.used is not None else np.ones(len(session), bool)
    dut = session.dut_uT[np.all(np.isfinite(session.dut_uT), axis=1)][rows] if res.used is not None else None
    temp = session.temp_c[np.all(np.isfinite(session.dut_uT), axis=1)][rows] if res.used is not None else None
    for name in ("px4", "ardupilot"):
        path = getattr(args, name)
        if path is not None:
            out[name] = (path, ex[name].build(table, dut, temp))
    return out


def _truth_lines(res, session, truth) -> list[str]:
    """Simulation only: the calibration against the truth programme (never used by the fit)."""
    from magstack.firmware.calibration.handcal import heading_error_deg

    ok = np.all(np.isfinite(session.dut_uT), axis=1)
    t = session.t_s[ok] - session.t_s[ok][0]
    cal = res.apply(session.dut_uT[ok], session.temp_c[ok])
    e = truth.earth_body_series_uT(t)
    F = float(np.linalg.norm(truth.field_world_uT))
    mag = np.linalg.norm(cal, axis=1) - F
    out = ["", "simulation truth (not used by the fit):",
           f"  |B| error against the site's field: {np.sqrt(np.mean(mag ** 2)) * 1e3:.1f} nT RMS"]
    lv = truth.level_turn_series(t)
    if lv.any():
        h = heading_error_deg(cal[lv], e[lv])
        out.append(f"  heading error in the level turns: {np.sqrt(np.mean(h ** 2)):.2f} deg RMS ({np.std(h):.2f} deg "
                   f"about the mean offset {np.mean(h):+.2f} deg, the undetermined rotation about z)")
    return out


def _record(args, record, field_uT) -> dict:
    from magstack.cli.calibrate_view import TerminalView
    from magstack.drivers.clock import SystemClock
    from magstack.firmware.calibration.live_coverage import LiveCoverage
    from magstack.hil.hand_session import FAST_ODR_HZ, SampleStats, record_hand_session

    cov = LiveCoverage()
    wall = SystemClock()
    show = not args.no_view and sys.stdout.isatty()
    view = TerminalView(sys.stdout, wall, 0.1) if show else None
    expected = field_uT
    def on_sample(sample) -> None:
        cov.add(sample.b_uT)

    holder = {"stats": SampleStats(1.0 / args.rate_hz)}

    def progress(elapsed_s, res, final=False) -> None:
        if view is None:
            return
        st = holder["stats"]
        info = {"title": f"magstack calibrate: {args.chip} on {args.bus} (Ctrl-C: stop and fit)",
                "elapsed_s": elapsed_s, "rate_hz": st.rate_hz(), "gaps": st.gaps, "expected_uT": expected}
        view.maybe_draw(cov.state, info, force=final)

    with graceful_stop() as stop:
        if view is not None:
            view.start()
        try:
            sess = record_hand_session(args.chip, args.bus, record, seconds=args.seconds, rate_hz=args.rate_hz,
                                       program=args.program, seed=args.seed, speed=args.speed, site=args.site,
                                       epoch_unix_s=args.date, on_sample=on_sample, progress=progress, stop=stop,
                                       wall=wall, stats=holder["stats"])
        finally:
            if view is not None:
                view.stop()
    st = sess.stats
    state = cov.state()
    rec = {"path": str(record), **st.to_dict(), "stopped_by": stop.signal_name if stop.is_set() else None,
           "redraws": None if view is None else view.frames,
           "redraw_hz": None if view is None else view.rate_hz(),
           "coverage_cells": state.cells_filled, "coverage_enough": state.enough}
    odr = f"{FAST_ODR_HZ[args.chip]:g} Hz"
    lines = [f"recorded {st.n} samples at {st.rate_hz():.1f} Hz into {record} ({st.gaps} gaps, largest interval "
             f"{st.largest_gap_s * 1e3:.1f} ms; the chip's {odr} output rate overwrote {st.overwritten} samples "
             "between reads)"
             + (f"; view redrawn {view.frames} times ({view.rate_hz():.1f} Hz)" if view is not None else "")
             + ("; stopped by " + stop.signal_name + ": fitting what was recorded" if stop.is_set() else "")]
    rec["_lines"] = lines
    rec["_truth"] = sess.truth
    return rec
