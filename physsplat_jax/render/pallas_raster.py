"""Pallas (Triton) tile compositor for the GPU, with a hand-written VJP.

Projection, binning and sorting are those of :mod:`~physsplat_jax.render.raster`
(plain JAX); this module replaces only its compositing stage
(``raster._rasterize``), on GPUs by default (``RenderConfig.backend``).

Layout. One Pallas program per compositing sub-tile (``st x st`` pixels,
``P = st^2``, a power of two; 8x8 with the default config). The per-slot
features are gathered once in sorted order and transposed to ``(10,
capacity + B)`` rows (mean x, y; conic a, b, c; opacity; r, g, b; depth), so a
program loads each feature of ``B`` consecutive slots with one contiguous
row load ``feat_ref[f, pl.ds(base, B)]`` (Triton lowers ref indexing, not
indexing of loaded values, and needs power-of-two shapes). The sub-tile's
slot range ``[start, end)`` comes from ``ranges``.

Forward (per program): a ``lax.while_loop`` over batches of ``B`` slots,
front to back, stopping when the list ends or every pixel has stopped. Per
batch a ``(P, B)`` block of alphas, exactly gsplat ``rasterize_to_pixels``::

  sigma = 0.5 (a dx^2 + c dy^2) + b dx dy,  alpha = min(0.999, o e^-sigma),
  skipped if sigma < 0 or alpha < 1/255; the pixel stops (exclusively) at
  the first Gaussian whose next_T <= 1e-4.

The transmittance in the batch is ``T0 exp(cumsum(log(1 - alpha)))`` (as the
JAX path). Outputs per pixel: ``sum w (r, g, b, z)``, ``log T_final`` and the
``stop`` slot (first slot not blended; ``end`` if the pixel never
saturated), which is all the backward pass keeps: nothing per (pixel,
Gaussian) pair.

Backward (per program, as gsplat ``rasterize_to_pixels_bwd``): the batches
are walked back to front from the last batch any pixel used. The
transmittance is recovered from the end, ``log T_start = log T_after - sum
log(1 - alpha)``, and the colour behind each Gaussian is the running
suffix sum ``S``::

  dL/dalpha_i = T_i g_i - (S_i + dL/dlogT) / (1 - alpha_i),
  g_i = c_i . dL/dC + z_i dL/dD,  S_i = sum_{j > i} w_j g_j,

then chained to the opacity, the conic and the 2D mean. Each (Gaussian,
sub-tile) slot belongs to exactly one program, so the per-slot gradients are
written without atomics into a ``(10, capacity + B)`` buffer; a
``segment_sum`` over the slots' Gaussian ids gives the per-Gaussian
gradient of the 10 features, and the JAX projection carries it on to means,
scales, quaternions, covariances, SH and view rotations.

On a CPU the kernels run in Pallas interpret mode
(``RenderConfig.interpret``): same code, same images, slow; this is how the
tests check them without a GPU.
"""

from __future__ import annotations

import functools
import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
from jax import lax
from jax.experimental import pallas as pl
from jax.experimental.pallas import triton as plgpu

from physsplat_jax.types import Array

_NUM_FEATURES = 10  # mean x, y; conic a, b, c; opacity; r, g, b; depth


class _Static(NamedTuple):
  """Hashable static settings of the kernels."""

  tiles_x: int
  tile: int  # tile edge [px]
  st: int  # sub-tile edge [px]
  block: int  # Gaussians per batch (B)
  alpha_max: float
  alpha_min: float
  t_min: float
  interpret: bool
  num_warps: int | None


def is_power_of_two(n: int) -> bool:
  """True for 1, 2, 4, ..."""
  return n >= 1 and (n & (n - 1)) == 0


def _pixels(t, s: _Static, dtype):
  """Pixel-centre coordinates (P,) of sub-tile ``t`` (raster's numbering)."""
  i32 = jnp.int32
  sub = s.tile // s.st
  tile_id = lax.div(t, i32(sub * sub))
  q = lax.rem(t, i32(sub * sub))
  ty = lax.div(tile_id, i32(s.tiles_x))
  tx = lax.rem(tile_id, i32(s.tiles_x))
  p = lax.broadcasted_iota(i32, (s.st * s.st,), 0)
  st = i32(s.st)
  j = lax.rem(q, i32(sub)) * st + lax.rem(p, st)
  i = lax.div(q, i32(sub)) * st + lax.div(p, st)
  px = (tx * i32(s.tile) + j).astype(dtype) + 0.5
  py = (ty * i32(s.tile) + i).astype(dtype) + 0.5
  return px, py


def _load_batch(feat_ref, base, B):
  """The 10 feature rows (B,) of slots ``[base, base + B)``."""
  return [feat_ref[f, pl.ds(base, B)] for f in range(_NUM_FEATURES)]


def _alphas(f, px, py, s: _Static):
  """Per (pixel, slot) quantities of one batch, all (P, B).

  Returns (dx, dy, ok, ex, raw, a): ``ok = sigma >= 0``, ``ex =
  exp(-sigma)`` (1 where not ok), ``raw = o ex``; ``a`` the blended alpha (0
  where gsplat skips the Gaussian).
  """
  mx, my, ca, cb, cc, op = (v[None, :] for v in f[:6])
  dx = mx - px[:, None]
  dy = my - py[:, None]
  sigma = 0.5 * (ca * dx * dx + cc * dy * dy) + cb * dx * dy
  ok = sigma >= 0.0
  ex = jnp.exp(-jnp.where(ok, sigma, 0.0))
  raw = op * ex
  alpha = jnp.minimum(raw, s.alpha_max)
  a = jnp.where(ok & (alpha >= s.alpha_min), alpha, 0.0)
  return dx, dy, ok, ex, raw, a


def _forward_kernel(ranges_ref, feat_ref, acc_ref, logt_ref, stop_ref, *,
                    s: _Static):
  t = pl.program_id(0)
  start = ranges_ref[t]
  end = ranges_ref[t + 1]
  B = s.block
  P = s.st * s.st
  dtype = feat_ref.dtype
  log_t_min = math.log(s.t_min)
  px, py = _pixels(t, s, dtype)
  lane = lax.broadcasted_iota(jnp.int32, (1, B), 1)

  def cond(c):
    base, _, stop, *_ = c
    return (base < end) & (jnp.max(stop) >= end)

  def body(c):
    base, log_t, stop, r, g, b, d = c
    f = _load_batch(feat_ref, base, B)
    inside = (base + lane) < end  # (1, B)
    _, _, _, _, _, a = _alphas(f, px, py, s)
    a = jnp.where(inside, a, 0.0)
    la = jnp.log1p(-a)
    incl = log_t[:, None] + jnp.cumsum(la, axis=1)
    excl = incl - la
    done = (stop < end)[:, None]
    live = jnp.logical_not(done) & (incl > log_t_min)
    w = jnp.where(live, a * jnp.exp(excl), 0.0)
    r = r + jnp.sum(w * f[6][None, :], axis=1)
    g = g + jnp.sum(w * f[7][None, :], axis=1)
    b = b + jnp.sum(w * f[8][None, :], axis=1)
    d = d + jnp.sum(w * f[9][None, :], axis=1)
    log_t = log_t + jnp.sum(jnp.where(live, la, 0.0), axis=1)
    # T only decreases, so the live slots form a prefix of the batch: the
    # first slot not blended is base + (their number).
    n_live = jnp.sum(live.astype(jnp.int32), axis=1, dtype=jnp.int32)
    stop = jnp.where((stop >= end) & (n_live < B), base + n_live, stop)
    return base + B, log_t, stop, r, g, b, d

  zero = jnp.zeros((P,), dtype)
  init = (start, zero, jnp.full((P,), end, jnp.int32), zero, zero, zero,
          zero)
  _, log_t, stop, r, g, b, d = lax.while_loop(cond, body, init)
  acc_ref[0, :] = r
  acc_ref[1, :] = g
  acc_ref[2, :] = b
  acc_ref[3, :] = d
  logt_ref[...] = log_t
  stop_ref[...] = stop


def _backward_kernel(ranges_ref, feat_ref, logt_ref, stop_ref, dacc_ref,
                     dlogt_ref, _, dslot_ref, *, s: _Static):
  t = pl.program_id(0)
  start = ranges_ref[t]
  end = ranges_ref[t + 1]
  B = s.block
  dtype = feat_ref.dtype
  px, py = _pixels(t, s, dtype)
  stop = stop_ref[...]
  dr, dg, db, dd = (dacc_ref[k, :][:, None] for k in range(4))
  lane = lax.broadcasted_iota(jnp.int32, (1, B), 1)
  lane1 = lax.broadcasted_iota(jnp.int32, (B,), 0)
  # Batches that any pixel blended: [start, max(stop)) in steps of B.
  num = lax.div(jnp.max(stop) - start + B - 1, jnp.int32(B))

  def body(k, c):
    log_t_after, s_after = c
    base = start + (num - 1 - k) * B
    idx = base + lane
    f = _load_batch(feat_ref, base, B)
    dx, dy, ok, ex, raw, a = _alphas(f, px, py, s)
    live = (idx < end) & (idx < stop[:, None])
    a = jnp.where(live, a, 0.0)
    la = jnp.log1p(-a)
    cs = jnp.cumsum(la, axis=1)
    log_t_start = log_t_after - jnp.sum(la, axis=1)
    t_i = jnp.exp(log_t_start[:, None] + cs - la)  # exclusive T
    w = a * t_i
    gi = (f[6][None, :] * dr + f[7][None, :] * dg + f[8][None, :] * db
          + f[9][None, :] * dd)
    wg = w * gi
    cwg = jnp.cumsum(wg, axis=1)
    tot = jnp.sum(wg, axis=1)
    behind = s_after[:, None] + (tot[:, None] - cwg)  # S_i + dL/dlogT
    dalpha = t_i * gi - behind / (1.0 - a)
    # Through alpha = min(o e^-sigma, alpha_max), skipped where gsplat skips.
    pass_ = live & ok & (a > 0.0) & (raw < s.alpha_max)
    draw = jnp.where(pass_, dalpha, 0.0)
    dsig = -draw * raw
    ca, cb, cc = (v[None, :] for v in f[2:5])
    grads = (
      jnp.sum(dsig * (ca * dx + cb * dy), axis=0),
      jnp.sum(dsig * (cc * dy + cb * dx), axis=0),
      jnp.sum(0.5 * dsig * dx * dx, axis=0),
      jnp.sum(dsig * dx * dy, axis=0),
      jnp.sum(0.5 * dsig * dy * dy, axis=0),
      jnp.sum(draw * ex, axis=0),
      jnp.sum(w * dr, axis=0),
      jnp.sum(w * dg, axis=0),
      jnp.sum(w * db, axis=0),
      jnp.sum(w * dd, axis=0),
    )
    mask = (base + lane1) < end
    for fi, gv in enumerate(grads):
      plgpu.store(dslot_ref.at[jnp.int32(fi), pl.ds(base, B)], gv.astype(dtype),
                  mask=mask)
    return log_t_start, s_after + tot

  init = (logt_ref[...], dlogt_ref[...])
  lax.fori_loop(0, num, body, init)


def _params(s: _Static):
  # Triton compiler params select the Triton lowering on NVIDIA (newer jax
  # defaults to Mosaic GPU, which these kernels are not written for).
  return {'compiler_params': plgpu.CompilerParams(num_warps=s.num_warps)}


def _sorted_features(feat, gid, B):
  """(10, capacity + B) features of the sorted slots (zero-padded)."""
  fs = jnp.transpose(feat[gid])
  return jnp.pad(fs, ((0, 0), (0, B)))


def _forward(feat, gid, ranges, s: _Static):
  num_sub = ranges.shape[0] - 1
  P = s.st * s.st
  dtype = feat.dtype
  fs = _sorted_features(feat, gid, s.block)
  full = lambda x: pl.BlockSpec(x.shape, lambda t: (0,) * x.ndim)
  acc, log_t, stop = pl.pallas_call(
    functools.partial(_forward_kernel, s=s),
    grid=(num_sub,),
    in_specs=[full(ranges), full(fs)],
    out_specs=[
      pl.BlockSpec((4, P), lambda t: (0, t)),
      pl.BlockSpec((P,), lambda t: (t,)),
      pl.BlockSpec((P,), lambda t: (t,)),
    ],
    out_shape=[
      jax.ShapeDtypeStruct((4, num_sub * P), dtype),
      jax.ShapeDtypeStruct((num_sub * P,), dtype),
      jax.ShapeDtypeStruct((num_sub * P,), jnp.int32),
    ],
    interpret=s.interpret,
    name='splat_forward',
    **_params(s),
  )(ranges, fs)
  return acc, log_t, stop, fs


def _backward(fs, ranges, log_t, stop, dacc, dlog_t, s: _Static):
  num_sub = ranges.shape[0] - 1
  P = s.st * s.st
  full = lambda x: pl.BlockSpec(x.shape, lambda t: (0,) * x.ndim)
  pix = pl.BlockSpec((P,), lambda t: (t,))
  zeros = jnp.zeros_like(fs)
  return pl.pallas_call(
    functools.partial(_backward_kernel, s=s),
    grid=(num_sub,),
    in_specs=[full(ranges), full(fs), pix, pix,
              pl.BlockSpec((4, P), lambda t: (0, t)), pix, full(zeros)],
    out_specs=full(zeros),
    out_shape=jax.ShapeDtypeStruct(fs.shape, fs.dtype),
    input_output_aliases={6: 0},
    interpret=s.interpret,
    name='splat_backward',
    **_params(s),
  )(ranges, fs, log_t, stop, dacc, dlog_t, zeros)


@functools.partial(jax.custom_vjp, nondiff_argnums=(3,))
def _composite(feat, gid, ranges, s: _Static):
  acc, log_t, _, _ = _forward(feat, gid, ranges, s)
  return acc, log_t


def _composite_fwd(feat, gid, ranges, s: _Static):
  acc, log_t, stop, fs = _forward(feat, gid, ranges, s)
  return (acc, log_t), (fs, gid, ranges, log_t, stop, feat.shape[0])


def _composite_bwd(s: _Static, res, cot):
  fs, gid, ranges, log_t, stop, K = res
  dacc, dlog_t = cot
  dslot = _backward(fs, ranges, log_t, stop, dacc.astype(fs.dtype),
                    dlog_t.astype(fs.dtype), s)
  cap = gid.shape[0]
  dfeat = jax.ops.segment_sum(jnp.transpose(dslot[:, :cap]), gid,
                              num_segments=K)
  return dfeat, None, None


_composite.defvjp(_composite_fwd, _composite_bwd)


def rasterize(feat: Array, gid: Array, ranges: Array, tiles_x: int,
              tiles_y: int, config) -> tuple[Array, Array]:
  """Pallas compositing stage; drop-in for ``raster._rasterize``.

  Args:
    feat: (K, 10) per-Gaussian features (``raster._features``).
    gid: (capacity,) Gaussian of each sorted slot.
    ranges: (num_subtiles + 1,) slot range of each sub-tile.
    tiles_x, tiles_y: tile grid.
    config: the ``RenderConfig`` (static).

  Returns:
    ``log_t`` (T, S, P) and ``acc`` (T, S, P, 4) as ``raster._rasterize``;
    differentiable w.r.t. ``feat`` (custom VJP, back-to-front kernel).
  """
  st = config.resolved_subtile
  sub = config.tile_size // st
  S = sub * sub
  P = st * st
  s = _Static(tiles_x=tiles_x, tile=config.tile_size, st=st,
              block=config.pallas_block, alpha_max=config.alpha_max,
              alpha_min=config.alpha_min, t_min=config.t_min,
              interpret=config.interpret,
              num_warps=config.pallas_num_warps)
  acc, log_t = _composite(feat, gid.astype(jnp.int32),
                          ranges.astype(jnp.int32), s)
  T = tiles_x * tiles_y
  log_t = log_t.reshape(T, S, P)
  acc = jnp.transpose(acc).reshape(T, S, P, 4)
  return log_t, acc
