"""Sub-commands of ``magstack``; one module each, discovered by :mod:`hil.cli`."""
