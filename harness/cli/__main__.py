"""``python -m physbench.harness.cli``: the ``physbench`` command."""

import sys

from physbench.harness.cli import main

sys.exit(main())
