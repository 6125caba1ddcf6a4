"""``python -m harness.cli``: the ``physbench`` command."""

import sys

from harness.cli import main

sys.exit(main())
