"""``python -m magstack``: the same entry point as the ``magstack`` script."""
import sys

from magstack.cli.main import main

sys.exit(main())
