"""The package's error base class.

Every error the package raises on purpose, bad input or a run that cannot
go on, derives from :class:`PhysSplatError` (and from the built-in class
that fits, ValueError, RuntimeError or OSError). Its message names what is
wrong, where (file, field, value) and how to fix it, so a script can print
it as one line (``experiments/lib/cli.py``) instead of a traceback.
"""


class PhysSplatError(Exception):
  """Base of every deliberate error of physsplat_jax."""
