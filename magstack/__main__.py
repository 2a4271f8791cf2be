"""``python -m magstack``: the same entry point as the ``magstack`` script."""
import sys

try:
    from magstack.cli.main import main
except KeyboardInterrupt:           # Ctrl-C while the command line loads: no traceback (exit 130)
    print("magstack: interrupted", file=sys.stderr)
    sys.exit(130)

sys.exit(main())
