"""The fast path of the step: compiled calls that run whole steps (see steady.py, loop.py)."""
