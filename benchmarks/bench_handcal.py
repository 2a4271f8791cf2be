"""Hand calibration next to PyPI ``magcal`` and a Li-Griffiths ellipsoid fit, on the same simulated sessions.

    python benchmarks/bench_handcal.py [--seeds 10] [--chips lis3mdl] [--programs hand,hand_warm,hand_laptop,hand_flat]
    python benchmarks/bench_handcal.py --part acceptance [--seeds 10]     # 10 seeds x 3 chips, held-out / floor

Each session (:mod:`magstack.ground.studies.hand_calibration`) is split into 10 s blocks: the even blocks fit,
the odd blocks are held out. On held-out rows without the laptop: the magnitude error against the site's field
and the heading error in the level turns (RMS, deg), next to the floor the exact inverse of the forward model
leaves. Methods: ``magstack`` (:func:`magstack.firmware.calibration.handcal.calibrate`, the field magnitude
given), ``magcal`` 1.0.1 (``MagnetometerCalibrator.ellipsoid_fit``: centre = sample mean; its unit-radius
output scaled to the field magnitude here), ``li-griffiths`` (``baselines/li_griffiths.py`` with the field
magnitude). Also what each says about its fit: ours accepts or refuses, magcal's rating (its std/mean bands),
Li-Griffiths its in-sample residual (it has no check). ``magcal`` is not a magstack dependency: install it
into the environment that runs this script (``pip install magcal``). Prints medians over seeds (JSON with
--json FILE).
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from baselines import li_griffiths  # noqa: E402

from magstack.firmware.calibration.handcal import HandCalData, HandCalOptions, calibrate, heading_error_deg  # noqa: E402
from magstack.ground.studies.hand_calibration import rms, simulate_session  # noqa: E402


def _magcal_fit(b):
    import contextlib
    import io

    from magcal.core import MagnetometerCalibrator

    cal = MagnetometerCalibrator()
    cal.raw_data = [tuple(x) for x in b]
    with contextlib.redirect_stdout(io.StringIO()):
        p = cal.calibrate("ellipsoid")
    q = cal.calibration_quality["quality_score"]
    rating = "Excellent" if q < 0.05 else "Good" if q < 0.1 else "Fair" if q < 0.2 else "Poor"
    return p["center"], p["transform_matrix"], rating


def run(chip: str, program: str, seed: int) -> dict:
    s = simulate_session(chip, program, seed)
    F = s.field_uT
    block = np.floor((s.t_s - s.t_s[0]) / 10.0).astype(int)
    train, test = block % 2 == 0, block % 2 == 1
    clean = s.clean()
    truth = s.earth_body_uT()
    exact = s.exact_uT()
    level = s.level() & test & clean
    out = {"floor_mag_nT": rms(np.linalg.norm(exact[test & clean], axis=1) - F) * 1e3}
    if level.any():
        out["floor_heading_deg"] = rms(heading_error_deg(exact[level], truth[level]))

    def figures(name, cal, verdict):
        m = np.linalg.norm(cal[test & clean], axis=1) - F
        out[name] = {"mag_nT": rms(m) * 1e3, "verdict": verdict}
        if level.any():
            out[name]["heading_deg"] = rms(heading_error_deg(cal[level], truth[level]))

    res = calibrate(HandCalData(s.dut_uT[train], s.temp_c[train], s.t_s[train]),
                    HandCalOptions(chip=chip, field_uT=F, holdout=False, allow_poor_coverage=True))
    plain = calibrate(HandCalData(s.dut_uT[train], s.temp_c[train], s.t_s[train]),
                      HandCalOptions(chip=chip, field_uT=F, holdout=False))
    figures("magstack", res.apply(s.dut_uT, s.temp_c), "REFUSED: " + "; ".join(plain.refused) if plain.refused
            else "accepted")
    c, W, rating = _magcal_fit(s.dut_uT[train])
    mc = (s.dut_uT - c) @ W.T
    scale = F / np.mean(np.linalg.norm(mc[train], axis=1))
    figures("magcal", mc * scale, f"rating {rating}")
    W2, c2, insample = li_griffiths.fit(s.dut_uT[train], F)
    figures("li-griffiths", li_griffiths.apply(W2, c2, s.dut_uT), f"no check (in-sample {insample * 1e3:.0f} nT)")
    return out


def acceptance(seeds: int) -> dict:
    """Held-out magnitude error / floor and the hard iron in posterior sds, ``seeds`` x the three chips on the
    guided programme (``calibrate``'s own held-out blocks)."""
    from magstack.ground.studies.hand_calibration import CHIPS, holdout_score

    out = {}
    for chip in CHIPS:
        ratios, zs, hidden = [], [], []
        for seed in range(seeds):
            s = simulate_session(chip, "hand", seed)
            res = calibrate(HandCalData(s.dut_uT, s.temp_c, s.t_s), HandCalOptions(chip=chip, field_uT=s.field_uT))
            h = holdout_score(s, res)
            ratios.append(h["ratio"])
            zs += h["offset_z"]
            hidden.append(h["hidden_rotation_deg"])
            assert "rotation" in res.frame.undetermined
        z = np.abs(zs)
        out[chip] = {"ratio_median": float(np.median(ratios)), "ratio_max": float(np.max(ratios)),
                     "offset_axes_within_2sd": f"{int(np.sum(z <= 2))}/{z.size}", "offset_z_rms": float(rms(zs)),
                     "offset_z_max": float(z.max()), "hidden_rotation_deg_median": float(np.median(hidden))}
        print(chip, out[chip], flush=True)
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--part", choices=("compare", "acceptance"), default="compare")
    ap.add_argument("--seeds", type=int, default=10)
    ap.add_argument("--chips", default="lis3mdl")
    ap.add_argument("--programs", default="hand,hand_warm,hand_laptop,hand_flat")
    ap.add_argument("--json", default=None)
    a = ap.parse_args(argv)
    if a.part == "acceptance":
        res = acceptance(a.seeds)
        if a.json:
            Path(a.json).write_text(json.dumps(res, indent=1) + "\n")
        return 0
    table = {}
    for chip in a.chips.split(","):
        for prog in a.programs.split(","):
            runs = [run(chip, prog, seed) for seed in range(a.seeds)]
            row = {"floor_mag_nT": float(np.median([r["floor_mag_nT"] for r in runs]))}
            if "floor_heading_deg" in runs[0]:
                row["floor_heading_deg"] = float(np.median([r["floor_heading_deg"] for r in runs]))
            for m in ("magstack", "magcal", "li-griffiths"):
                row[m] = {"mag_nT": float(np.median([r[m]["mag_nT"] for r in runs])),
                          "verdicts": sorted({r[m]["verdict"].split(" (")[0] for r in runs})}
                if "heading_deg" in runs[0][m]:
                    row[m]["heading_deg"] = float(np.median([r[m]["heading_deg"] for r in runs]))
            table[f"{chip}/{prog}"] = row
            h = f" / {row['floor_heading_deg']:.2f} deg" if "floor_heading_deg" in row else ""
            print(f"{chip} {prog}: floor {row['floor_mag_nT']:.0f} nT{h}")
            for m in ("magstack", "magcal", "li-griffiths"):
                r = row[m]
                hd = f" / {r['heading_deg']:.2f} deg" if "heading_deg" in r else ""
                print(f"  {m:13s} {r['mag_nT']:9.0f} nT{hd}   {'; '.join(r['verdicts'])[:150]}")
    if a.json:
        Path(a.json).write_text(json.dumps(table, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
