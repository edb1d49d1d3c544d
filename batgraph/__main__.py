"""``python -m batgraph ...``: the same as the ``batgraph`` command."""

import sys

from .cli import entry

sys.exit(entry())
