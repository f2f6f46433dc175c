"""``python -m nhsde.runs …``: the ``nhsde`` command."""

import sys

from ._cli import main

sys.exit(main())
