"""What counts as a number in a user's input.

One definition for every check of options, config files and sidecar fields
(perception options, MPDP and training configs, scene sidecars,
PhysGaussian configs), so that they accept and refuse the same values;
each check words its own message. A bool is never a number here
(``True`` for a stiffness is a mistake, not 1), nor is a string.
"""

from __future__ import annotations

import math
import numbers

import numpy as np


def is_number(value) -> bool:
  """A real number of any kind: int, float or NumPy scalar, possibly inf or
  NaN (not a bool, not a string, not an array)."""
  return (isinstance(value, numbers.Real)
          and not isinstance(value, (bool, np.bool_)))


def is_real(value) -> bool:
  """A finite real number (:func:`is_number`, not inf or NaN)."""
  return is_number(value) and math.isfinite(value)


def is_int(value) -> bool:
  """An integer type (Python or NumPy): not a bool, not 2.0, not 2.5."""
  return (isinstance(value, (int, np.integer))
          and not isinstance(value, (bool, np.bool_)))


def is_whole(value) -> bool:
  """A finite number with no fractional part, of any type: 3 or 3.0 (what a
  JSON file may hold for a count)."""
  return is_real(value) and float(value).is_integer()
