"""Sub-commands of ``magstack``; one module each, discovered by :mod:`magstack.cli.main`."""
