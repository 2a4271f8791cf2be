"""Ground and bench side: session files, bench runner, alignment, real-data import, the CLI.

Top of the dependency graph: may use ``drivers``, ``sim`` and ``firmware_py``; nothing
imports ``hil``.
"""
