"""Rotation of real spherical-harmonics colour coefficients.

A rotated Gaussian should look, from direction ``d``, as the unrotated one
looks from ``R^T d``: ``f'(d) = f(R^T d)``. Each SH band ``l`` spans a
rotation-invariant space, so ``f'`` has exact coefficients of the same degree.
We find them by least squares on a fixed set of ``S`` well-spread directions
``d_s`` (more than the basis size, so the fit is exact up to rounding):

  Y c' = Y_R c,  Y[s, b] = Y_b(d_s),  Y_R[s, b] = Y_b(R^T d_s)
  =>  c' = pinv(Y) Y_R c.

This is what a Wigner-D rotation computes, without per-band recursions. It is
the alternative to rotating the view direction (``render(...,
view_rotations=R)``, PhysGaussian's ``convert_SH``) when deformed Gaussians
are exported to files that viewers read (per-frame PLY).
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from physsplat_jax import gaussians as gs
from physsplat_jax.types import Array
from physsplat_jax.types import DataError
from physsplat_jax.types import sh_degree_from_bases


@functools.lru_cache(maxsize=None)
def _fit_directions(degree: int) -> tuple[np.ndarray, np.ndarray]:
  """Fibonacci-sphere directions (S, 3) and pinv of their basis (B, S)."""
  nb = (degree + 1) ** 2
  S = max(4 * nb, 8)
  i = np.arange(S) + 0.5
  z = 1.0 - 2.0 * i / S
  phi = np.pi * (1.0 + 5.0**0.5) * i
  r = np.sqrt(1.0 - z * z)
  dirs = np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)
  # Concrete NumPy even when first called while tracing (under jit).
  with jax.ensure_compile_time_eval(), jax.enable_x64(True):
    Y = np.asarray(gs.sh_basis(degree, jnp.asarray(dirs, jnp.float64)))
  return dirs, np.linalg.pinv(Y)


def rotate_sh(sh: Array, rotations: Array) -> Array:
  """SH coefficients of colour functions rotated by ``rotations``.

  Args:
    sh: (K, B, 3) coefficients, B = (d + 1)**2 with d in 0..3.
    rotations: (K, 3, 3) or (3, 3) rotations (or any orthogonal matrices:
      the SH of degree <= d span a space closed under reflections too).

  Returns:
    (K, B, 3) coefficients ``c'`` with ``eval_sh(c', d) == eval_sh(sh, R^T
    d)`` for every direction ``d`` (the DC term is unchanged).
  """
  if sh.ndim != 3 or sh.shape[-1] != 3:
    raise DataError(f'rotate_sh: sh has shape {sh.shape}; expected (K, B, 3)')
  degree = sh_degree_from_bases(sh.shape[1])
  if degree == 0:
    return sh
  if jnp.shape(rotations) not in ((3, 3), (sh.shape[0], 3, 3)):
    raise DataError(
      f'rotate_sh: rotations has shape {jnp.shape(rotations)}; expected '
      f'(3, 3) or (K, 3, 3) = ({sh.shape[0]}, 3, 3), one per Gaussian of sh')
  rotations = jnp.broadcast_to(rotations, (sh.shape[0], 3, 3))
  dirs, pinv = _fit_directions(degree)
  dirs = jnp.asarray(dirs, sh.dtype)
  # R^T d for row vectors d is d @ R.
  rotated = jnp.einsum('sj,kji->ksi', dirs, rotations.astype(sh.dtype))
  Y_R = gs.sh_basis(degree, rotated)  # (K, S, B)
  M = jnp.einsum('bs,ksc->kbc', jnp.asarray(pinv, sh.dtype), Y_R)  # (K,B,B)
  return jnp.einsum('kbc,kcd->kbd', M, sh)
