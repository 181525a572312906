"""The MPM solver's errors (re-exported by :mod:`physsplat_jax.mpm`)."""

from __future__ import annotations

from physsplat_jax.errors import PhysSplatError


class MPMInputError(PhysSplatError, ValueError):
  """Bad input to the MPM solver (config, grid, materials, state, forces);
  the message names the field and the fix."""


class SimulationError(PhysSplatError, RuntimeError):
  """A simulation blew up or was set up unstably.

  Attributes:
    frame: index of the frame at which it was detected (None: before the
      run).
    reason: short machine-readable cause ('nan', 'wall', 'F', 'J', 'dt').
  """

  def __init__(self, message: str, frame: int | None = None,
               reason: str = ''):
    super().__init__(message)
    self.frame = frame
    self.reason = reason
