"""The MPDP network in Flax linen: :class:`PointNet` (see :mod:`.model`).

Kept apart from :mod:`physsplat_jax.mpdp.model` so that importing the
package does not import Flax: :func:`~physsplat_jax.mpdp.model.predict`
and :func:`~physsplat_jax.mpdp.model.init_params` import this module when
they first trace the network.
"""

from __future__ import annotations

import functools
from typing import Sequence

import flax.linen as nn
from flax.linen.dtypes import promote_dtype
import jax
import jax.numpy as jnp

from physsplat_jax.mpdp import knn as knn_lib
from physsplat_jax.mpdp.model import ModelConfig


def _mlp(x, features: Sequence[int]):
  for f in features:
    x = nn.gelu(nn.Dense(f)(x))
  return x


# Points per chunk of the EdgeConv above this size (static): the edge
# tensors are (chunk, k, 2 F + 3) instead of (N, k, 2 F + 3).
EDGE_CHUNK = 16384


def _edge_conv(dense_a, dense_b, h, points, idx, rows=None):
  """EdgeConv of the points ``rows`` (default all; ``idx`` their (R, k)
  neighbours): ``gelu(max_j dense_b(gelu(dense_a([h_i, h_j - h_i, p_j -
  p_i]))))``."""
  hr, pr = (h, points) if rows is None else (h[rows], points[rows])
  hj = h[idx]
  hi = jnp.broadcast_to(hr[:, None, :], hj.shape)
  rel = points[idx] - pr[:, None, :]
  e = jnp.concatenate([hi, hj - hi, rel], axis=-1)
  e = nn.gelu(dense_a(e))
  e = dense_b(e)
  return nn.gelu(jnp.max(e, axis=1))


def _dense(p, x):
  """``nn.Dense`` with params ``p``, as a pure function (same ops)."""
  x, kernel, bias = promote_dtype(x, p['kernel'], p['bias'])
  y = jax.lax.dot_general(x, kernel, (((x.ndim - 1,), (0,)), ((), ())))
  return y + jnp.reshape(bias, (1,) * (y.ndim - 1) + (-1,))


def _chunked_edge_conv(pa, pb, h, points, idx):
  """:func:`_edge_conv` of all points, :data:`EDGE_CHUNK` at a time."""
  n = points.shape[0]
  nb = -(-n // EDGE_CHUNK)
  size = -(-n // nb)
  rows = jnp.arange(nb * size).reshape(nb, size) % n  # pad: repeat rows

  def chunk(pa, pb, r):
    return _edge_conv(functools.partial(_dense, pa),
                      functools.partial(_dense, pb), h, points, idx[r], r)

  # Rematerialised: the backward pass keeps one chunk's edges at a time.
  chunk = jax.checkpoint(chunk)
  out = jax.lax.map(lambda r: chunk(pa, pb, r), rows)
  return out.reshape(nb * size, -1)[:n]


class PointNet(nn.Module):
  """PointNet/DGCNN-lite producing per-point logits (see module docstring)."""

  config: ModelConfig = ModelConfig()
  # Neighbour search (not part of the weights): 'auto', 'grid' or 'brute'
  # (see physsplat_jax.mpdp.knn); all give the same neighbours.
  knn_method: str = 'auto'

  @nn.compact
  def __call__(self, points, means, mask, knn_points=None):
    """Per-point bounded logits.

    Args:
      points: (N, 3) normalised points.
      means: (MEANS_DIM,) encoded mean properties.
      mask: (N,) bool validity.
      knn_points: (N, 3) where the EdgeConv's neighbours are searched
        (default ``points``); :func:`~physsplat_jax.mpdp.model.make_predict`
        passes the raw points' int32 ``knn.lattice_coordinates``, whose
        exact distances give the same neighbours on every backend.

    Returns:
      (N, 3) logits in [-r, r] per channel (E, nu, rho).
    """
    cfg = self.config
    n = points.shape[0]
    h = _mlp(points, cfg.features)
    feats = [h]
    if cfg.edge_features > 0 and cfg.k_neighbors > 0:
      idx = knn_lib.knn_indices(
        points if knn_points is None else knn_points, mask, cfg.k_neighbors,
        self.knn_method)
      dense_a = nn.Dense(cfg.edge_features)
      dense_b = nn.Dense(cfg.edge_features)
      if n <= EDGE_CHUNK:
        feats.append(_edge_conv(dense_a, dense_b, h, points, idx))
      else:
        # One point binds the two layers (and creates them at init); then
        # the same ops run over chunks of points, so the (N, k, F) edge
        # tensors never exist at once.
        _edge_conv(dense_a, dense_b, h, points, idx[:1], jnp.arange(1))
        pa, pb = dense_a.variables['params'], dense_b.variables['params']
        feats.append(_chunked_edge_conv(pa, pb, h, points, idx))
    local = jnp.concatenate(feats, axis=-1)
    g = nn.Dense(cfg.global_features)(local)
    g = jnp.max(jnp.where(mask[:, None], g, -jnp.inf), axis=0)
    g = jnp.where(jnp.isfinite(g), g, 0.0)
    c = _mlp(means, (cfg.cond_features, cfg.cond_features))
    z = jnp.concatenate([
      local, jnp.broadcast_to(g, (n, g.shape[-1])),
      jnp.broadcast_to(c, (n, c.shape[-1])), points,
    ], axis=-1)
    z = _mlp(z, cfg.head_features)
    raw = nn.Dense(3, kernel_init=nn.initializers.zeros)(z)
    r = jnp.asarray(cfg.log_range, raw.dtype)
    return r * jnp.tanh(raw / r)
