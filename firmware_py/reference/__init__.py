"""Reference field for on-orbit calibration: IGRF-14 (ppigrf) at time-tagged positions,
Earth-fixed to inertial frames (ERFA), Sun direction and eclipse, body frame by attitude."""
