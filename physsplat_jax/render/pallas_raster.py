"""Pallas (Triton) tile compositor for the GPU, with a hand-written VJP.

Projection, binning and sorting are those of :mod:`~physsplat_jax.render.raster`
(plain JAX); this module replaces only its compositing stage
(``raster._rasterize``), on GPUs by default (``RenderConfig.backend``).

Layout. One Pallas program per compositing sub-tile (``st x st`` pixels,
``P = st^2``, a power of two; 8x8 with the default config). The per-slot
features are gathered once in sorted order and transposed to ``(10,
capacity + B)`` rows (mean x, y; conic a, b, c; opacity; r, g, b; depth).
The sub-tile's slot range ``[start, end)`` comes from ``ranges``. Triton
lowers ref indexing, not indexing of loaded values, and needs power-of-two
block shapes.

Forward (per program, two pixels per thread by default, see
``RenderConfig.resolved_pallas``): the slots are walked front to back one at a
time, each thread loading the slot's 10 features as scalars
``feat_ref[f, idx]`` (one address across the warp: a broadcast) and
blending it into its own pixel::

  sigma = 0.5 (a dx^2 + c dy^2) + b dx dy,  alpha = min(0.999, o e^-sigma),
  skipped if sigma < 0 or alpha < 1/255; the pixel stops (exclusively) at
  the first Gaussian whose next_T = T (1 - alpha) <= 1e-4.

No work crosses threads except a ``lax.while_loop`` check, every ``B``
slots, that the list has ended or every pixel has stopped. Outputs per
pixel: ``sum w (r, g, b, z)``, ``log T_final`` and the ``stop`` slot (first
slot not blended; ``end`` if the pixel never saturated), which is all the
backward pass keeps: nothing per (pixel, Gaussian) pair. (The first
version blended ``(P, B)`` blocks with a ``cumsum`` across the batch, as the
JAX path, in both kernels: 227 and 255 registers per thread, the backward
spilling, 2-3x the instructions per pair; docs/rendering.md.)

Backward (per program, as gsplat ``rasterize_to_pixels_bwd``; two pixels
per thread, so an 8x8 sub-tile is one warp): the slots are walked back to
front from the last one any pixel blended, one at a time. Per pixel the
transmittance in front of a slot is recovered from the one behind it,
``T_i = T_{i+1} / (1 - alpha_i)`` (from ``T_final``), and the colour behind
it is a running suffix sum ``S``::

  dL/dalpha_i = T_i g_i - (S_i + dL/dlogT) / (1 - alpha_i),
  g_i = c_i . dL/dC + z_i dL/dD,  S_i = sum_{j > i} w_j g_j,

then chained to the opacity, the conic and the 2D mean and summed over the
program's pixels (inside the warp: shuffles, no shared memory or
barriers). Each (Gaussian, sub-tile) slot belongs to exactly one program,
so the per-slot gradients are written without atomics into a ``(10,
capacity + B)`` buffer; a ``segment_sum`` over the slots' Gaussian ids
gives the per-Gaussian gradient of the 10 features, and the JAX projection
carries it on to means, scales, quaternions, covariances, SH and view
rotations.

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

from physsplat_jax import platforms
from physsplat_jax.types import Array

# None where this JAX has no Triton backend (RenderConfig then picks JAX).
plgpu = platforms.pallas_triton()

_NUM_FEATURES = 10  # mean x, y; conic a, b, c; opacity; r, g, b; depth
_FORWARD_UNROLL = 4  # slots per iteration of the forward's inner loop
_LOG2E = 1.4426950408889634


class _Static(NamedTuple):
  """Hashable static settings of the kernels."""

  tiles_x: int
  tile: int  # tile edge [px]
  st: int  # sub-tile edge [px]
  block: int  # forward: slots between two stop checks (B)
  alpha_max: float
  alpha_min: float
  t_min: float
  interpret: bool
  forward_warps: int
  backward_warps: int


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


def _slot(feat_ref, idx, px, py, s: _Static):
  """Slot ``idx`` at every pixel of the program (one or two per thread).

  The slot's 10 features are scalar loads (one address across a warp: a
  broadcast). Returns ``(features, dx, dy, ok, ex, raw, alpha)``, pixel
  vectors but for the features: ``ok = sigma >= 0``, ``ex = exp(-sigma)``
  (1 where not ok; ``exp2``, one instruction on NVIDIA), ``raw = o ex`` and
  ``alpha = min(raw, alpha_max)``.
  """
  f = [feat_ref[k, idx] for k in range(_NUM_FEATURES)]
  mx, my, ca, cb, cc, op = f[:6]
  dx = mx - px
  dy = my - py
  sigma = 0.5 * (ca * dx * dx + cc * dy * dy) + cb * dx * dy
  ok = sigma >= 0.0
  ex = jnp.exp2(_LOG2E * -jnp.where(ok, sigma, 0.0))
  raw = op * ex
  return f, dx, dy, ok, ex, raw, jnp.minimum(raw, s.alpha_max)


def _forward_kernel(ranges_ref, feat_ref, acc_ref, logt_ref, stop_ref, *,
                    s: _Static):
  t = pl.program_id(0)
  start = ranges_ref[t]
  end = ranges_ref[t + 1]
  B = s.block
  P = s.st * s.st
  dtype = feat_ref.dtype
  px, py = _pixels(t, s, dtype)

  def gaussian(idx, c):
    # One slot for every pixel of the program (two per thread by default), no
    # work across threads.
    T, stop, r, g, b, d = c
    f, _, _, ok, _, _, alpha = _slot(feat_ref, idx, px, py, s)
    cr, cg, cb_, cz = f[6:]
    inside = idx < end
    a = jnp.where(ok & (alpha >= s.alpha_min) & inside, alpha, 0.0)
    next_t = T * (1.0 - a)
    running = stop >= end
    live = running & (next_t > s.t_min)
    w = jnp.where(live, a * T, 0.0)
    r = r + w * cr
    g = g + w * cg
    b = b + w * cb_
    d = d + w * cz
    T = jnp.where(live, next_t, T)
    stop = jnp.where(running & jnp.logical_not(live) & inside, idx, stop)
    return T, stop, r, g, b, d

  unroll = math.gcd(B, _FORWARD_UNROLL)

  def steps(j, c):
    for u in range(unroll):  # lax.fori_loop(unroll=) has no Triton lowering
      c = gaussian(c[-1] + j * unroll + u, c[:-1]) + (c[-1],)
    return c

  def cond(c):
    base, _, stop, *_ = c
    return (base < end) & (jnp.max(stop) >= end)

  def body(c):
    base, *rest = c
    *rest, _ = lax.fori_loop(0, B // unroll, steps, (*rest, base))
    return (base + B, *rest)

  zero = jnp.zeros((P,), dtype)
  init = (start, jnp.ones((P,), dtype), jnp.full((P,), end, jnp.int32), zero,
          zero, zero, zero)
  _, T, stop, r, g, b, d = lax.while_loop(cond, body, init)
  acc_ref[0, :] = r
  acc_ref[1, :] = g
  acc_ref[2, :] = b
  acc_ref[3, :] = d
  logt_ref[...] = jnp.log(T)
  stop_ref[...] = stop


def _backward_kernel(ranges_ref, feat_ref, logt_ref, stop_ref, dacc_ref,
                     dlogt_ref, _, dslot_ref, *, s: _Static):
  t = pl.program_id(0)
  start = ranges_ref[t]
  dtype = feat_ref.dtype
  px, py = _pixels(t, s, dtype)
  stop = stop_ref[...]
  dr, dg, db, dd = (dacc_ref[k, :] for k in range(4))
  last = jnp.max(stop)  # slots [start, last) were blended by some pixel

  def slot(k, c):
    # Slot ``last - 1 - k``, back to front, for every pixel of the program.
    # Per pixel: T is the transmittance behind the slot, ``behind`` the
    # colour behind it plus dL/dlogT (gsplat's running suffix sum).
    T, behind = c
    idx = last - 1 - k
    f, dx, dy, ok, ex, raw, alpha = _slot(feat_ref, idx, px, py, s)
    ca, cb, cc = f[2:5]
    cr, cg, cb_, cz = f[6:]
    a = jnp.where((idx < stop) & ok & (alpha >= s.alpha_min), alpha, 0.0)
    inv = 1.0 / (1.0 - a)
    t_i = T * inv  # transmittance in front of the slot
    w = a * t_i
    gi = cr * dr + cg * dg + cb_ * db + cz * dd
    dalpha = t_i * gi - behind * inv
    # Through alpha = min(o e^-sigma, alpha_max), skipped where gsplat skips.
    draw = jnp.where((a > 0.0) & (raw < s.alpha_max), dalpha, 0.0)
    dsig = -draw * raw
    sx = dsig * dx
    sy = dsig * dy
    grads = (ca * sx + cb * sy, cc * sy + cb * sx, 0.5 * sx * dx, sx * dy,
             0.5 * sy * dy, draw * ex, w * dr, w * dg, w * db, w * dd)
    for f, gv in enumerate(grads):
      dslot_ref[f, idx] = jnp.sum(gv).astype(dtype)
    return t_i, behind + w * gi

  init = (jnp.exp(logt_ref[...]), dlogt_ref[...])
  lax.fori_loop(0, last - start, slot, init)


def _params(num_warps: int, interpret: bool):
  # Triton compiler params select the Triton lowering on NVIDIA (newer jax
  # defaults to Mosaic GPU, which these kernels are not written for). The
  # interpreter takes none (and runs where this JAX has no Triton).
  if interpret:
    return {}
  return {'compiler_params': plgpu.CompilerParams(num_warps=num_warps)}


def _sorted_features(feat, gid, s: _Static):
  """(10, capacity + B) features of the sorted slots (zero-padded)."""
  fs = jnp.transpose(feat[gid])
  return jnp.pad(fs, ((0, 0), (0, s.block)))


def _forward(feat, gid, ranges, s: _Static):
  num_sub = ranges.shape[0] - 1
  P = s.st * s.st
  dtype = feat.dtype
  fs = _sorted_features(feat, gid, s)
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
    **_params(s.forward_warps, s.interpret),
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
    **_params(s.backward_warps, s.interpret),
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
  block, fwd_warps, bwd_warps = config.resolved_pallas()
  s = _Static(tiles_x=tiles_x, tile=config.tile_size, st=st,
              block=block, alpha_max=config.alpha_max,
              alpha_min=config.alpha_min, t_min=config.t_min,
              interpret=config.interpret,
              forward_warps=fwd_warps, backward_warps=bwd_warps)
  acc, log_t = _composite(feat, gid.astype(jnp.int32),
                          ranges.astype(jnp.int32), s)
  T = tiles_x * tiles_y
  log_t = log_t.reshape(T, S, P)
  acc = jnp.transpose(acc).reshape(T, S, P, 4)
  return log_t, acc
