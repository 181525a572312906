"""Sorts in the form a GPU runs fast: CUB radix sort of unsigned keys.

On NVIDIA GPUs XLA replaces a sort by CUB's ``DeviceRadixSort``
(``SortRewriter``) only when it is a single array, or a (keys, values)
pair whose keys are *unsigned integers* (or float32 with a plain
comparison) compared by a plain less-than. JAX's own ``argsort`` of
floats uses NumPy order (NaNs last, -0 = +0: a comparator CUB cannot take
for a pair) and signed integer keys have no CUB pair kernel: both fall
back to XLA's sorting network, O(n log^2 n) with a pass over the whole
array per step. For the renderer's slot sort (millions of slots) that is
the difference between a fraction of a millisecond and several.

These helpers sort (unsigned key, int32 index) pairs stably. On the CPU
they give exactly ``jnp.argsort(keys, stable=True)``'s order; there XLA
runs the same comparison sort either way.
"""

from __future__ import annotations

import jax.numpy as jnp
from jax import lax

from physsplat_jax.types import Array


def radix_key(x: Array) -> Array:
  """Unsigned integer keys ordered as ``x``.

  ``x``: non-negative integers, or floats of which only the non-negative
  ones are ordered (negatives and -0 map to +0's key; +inf and NaN sort
  last, NaN after +inf). Non-negative IEEE floats order as their bit
  patterns read as unsigned integers of the same width.
  """
  x = jnp.asarray(x)
  if jnp.issubdtype(x.dtype, jnp.floating):
    u = {2: jnp.uint16, 4: jnp.uint32, 8: jnp.uint64}[x.dtype.itemsize]
    x = jnp.where(jnp.isnan(x) | (x > 0), x, jnp.zeros_like(x))
    return lax.bitcast_convert_type(x, u)
  if jnp.issubdtype(x.dtype, jnp.unsignedinteger):
    return x
  return x.astype(jnp.uint64 if x.dtype.itemsize > 4 else jnp.uint32)


def _radix_sort(keys: Array, values: Array) -> tuple[Array, Array]:
  """(radix keys, values) stably sorted by the keys: one CUB pair sort."""
  return lax.sort((radix_key(keys), values), num_keys=1, is_stable=True)


def sort_pairs(keys: Array, values: Array) -> tuple[Array, Array]:
  """``(keys, values)`` stably sorted by non-negative integer ``keys``;
  the sorted keys come back in their own dtype."""
  k, v = _radix_sort(keys, values)
  return k.astype(keys.dtype), v


def argsort(keys: Array) -> Array:
  """Stable ``argsort`` (int32) of 1-D ``keys`` (see :func:`radix_key`)."""
  return _radix_sort(keys, jnp.arange(keys.shape[0], dtype=jnp.int32))[1]


def inverse_permutation(perm: Array) -> Array:
  """``argsort(perm)`` of a permutation, by one scatter instead of a sort."""
  n = perm.shape[0]
  return jnp.zeros((n,), jnp.int32).at[perm].set(
    jnp.arange(n, dtype=jnp.int32), unique_indices=True)
