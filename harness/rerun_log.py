"""Former home of the rerun traces; they live in :mod:`harness.trace` now
(this name stays for existing imports)."""

from harness.trace import *  # noqa: F401,F403
from harness.trace import __all__  # noqa: F401
