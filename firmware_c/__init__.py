"""The on-board calibration applier in C99 (``magstack_cal.c``, ``magstack_cal.h``), shipped as package data.

No Python code: ``magstack table export --c DIR`` writes these sources out beside a table image
(:mod:`magstack.firmware.cal_image`); docs/c-applier.md describes the library.
"""
