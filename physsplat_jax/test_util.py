"""Helpers for tests: tolerances and tree assertions (as optax/jax-md keep)."""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

# Named tolerances by dtype (jax-md ``update_test_tolerance`` style).
TOL = {np.dtype(np.float32): 1e-4, np.dtype(np.float64): 1e-10}


def tol(dtype, f32: float | None = None, f64: float | None = None) -> float:
  """Tolerance for ``dtype`` with optional per-dtype overrides."""
  d = np.dtype(dtype)
  if d == np.float64:
    return TOL[d] if f64 is None else f64
  return TOL[np.dtype(np.float32)] if f32 is None else f32


def assert_trees_all_close(a, b, rtol=1e-6, atol=0.0, err_msg=''):
  """Asserts two pytrees have the same structure and close leaves."""
  la, ta = jax.tree.flatten(a)
  lb, tb = jax.tree.flatten(b)
  if ta != tb:
    raise AssertionError(f'tree structures differ: {ta} vs {tb} {err_msg}')
  for i, (x, y) in enumerate(zip(la, lb)):
    np.testing.assert_allclose(
      np.asarray(x), np.asarray(y), rtol=rtol, atol=atol,
      err_msg=f'leaf {i}: {err_msg}',
    )


def assert_tree_all_finite(tree, err_msg=''):
  """Asserts every floating leaf of ``tree`` is finite."""
  for i, x in enumerate(jax.tree.leaves(tree)):
    x = np.asarray(x)
    if np.issubdtype(x.dtype, np.floating) and not np.all(np.isfinite(x)):
      bad = int(np.sum(~np.isfinite(x)))
      raise AssertionError(f'leaf {i} has {bad} non-finite values {err_msg}')


def random_gaussians(key, num: int, sh_degree: int = 0, dtype=jnp.float32,
                     extent: float = 1.0):
  """A random, well-conditioned :class:`~physsplat_jax.types.Gaussians`."""
  return _random_gaussians(key, num, sh_degree, jnp.dtype(dtype),
                           float(extent))


@functools.partial(jax.jit, static_argnums=(1, 2, 3, 4))
def _random_gaussians(key, num, sh_degree, dtype, extent):
  """One program per size: eagerly, each of the five draws compiled its
  own (about 0.2 s each at a new size on the 2-core VM)."""
  from physsplat_jax.types import Gaussians

  k = jax.random.split(key, 5)
  nb = (sh_degree + 1) ** 2
  return Gaussians(
    means=jax.random.uniform(k[0], (num, 3), dtype, -extent, extent),
    log_scales=jax.random.uniform(k[1], (num, 3), dtype, -4.0, -2.0),
    quats=jax.random.normal(k[2], (num, 4), dtype),
    opacity_logits=jax.random.normal(k[3], (num,), dtype),
    sh=0.5 * jax.random.normal(k[4], (num, nb, 3), dtype),
  )
