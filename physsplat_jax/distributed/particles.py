"""One large simulation across devices: particles sharded, grid summed.

MLS-MPM particles interact only through the background grid (and, for rigid
bodies, through their bodies' momentum sums). Split the N particles into D
equal shards, one per device of a mesh axis, and run every substep inside
``jax.shard_map`` (Hu et al. 2018 step; PhysGaussian ordering)::

  1. particle rules, constitutive update   local to each shard
  2. P2G    each device scatters its particles into a full (4, G^3) grid;
            lax.psum over the axis sums the partial grids (one all-reduce)
  3. grid update (momentum -> velocity, gravity, damping, colliders)
            replicated: every device updates the same summed grid
  4. G2P    local: each device gathers its particles from its grid copy
  5. rigid bodies: per-body mass, momentum, angular momentum and inertia
            sums are psum-ed too (as is the mass under a total PointForce)

The reductions are ``mpm``'s ``reduce_fn`` hook (identity by default), set
here to ``functools.partial(lax.psum, axis_name=axis)``.

Why a replicated grid update: a reduce-scatter, a sharded grid update and
an all-gather move the same bytes as one all-reduce, and would need every
grid boundary condition to work on slabs; the grid update is O(G^3) against
O(27 N) for the transfers, so replicating it costs little while N >> G^3.
Every device holds the whole grid: this scales the particle count, not the
grid size (a spatial decomposition with halo exchange would be the next
step for grids that do not fit one device).

Particles never move between devices. The per-frame cell sort
(``SimConfig.sort_particles``) therefore runs inside each shard: it is
shard-local by construction and undone at the end of the frame as before.

A particle count not divisible by D is padded with *ghost* particles:
copies of one ordinary particle (not rigid, no boundary-condition
selection) whose mass and volume are scaled by ``GHOST_FRACTION`` (1e-20).
Their share of every grid sum is far below float resolution, they ride
along with the material (so they stay finite), and they are cut from the
results. Results equal the single-device run up to float summation order.
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
from jax.sharding import Mesh
from jax.sharding import PartitionSpec as P

from physsplat_jax import mpm
from physsplat_jax import pipeline as pl
from physsplat_jax.distributed import sharding as sh
from physsplat_jax.distributed.runtime import DistributedError

GHOST_FRACTION = 1e-20


def pad_particles(state: mpm.MPMState, materials: mpm.Materials,
                  multiple: int):
  """Pads particles with ghosts to a multiple of ``multiple`` (jit-safe).

  Args:
    state: ``MPMState`` with N particles.
    materials: their ``Materials``.
    multiple: the device count D of the particle axis.

  Returns:
    ``(state, materials)`` with ``ceil(N / D) D`` particles, the first N
    unchanged. Ghosts copy the first particle that is not rigid and not
    selected by a particle boundary condition (particle 0 if none is), with
    mass and volume times ``GHOST_FRACTION``, body id -1 and no
    boundary-condition selection.
  """
  n = state.x.shape[0]
  k = -n % multiple
  if k == 0:
    return state, materials
  ok = state.body_id < 0
  for b in state.bc_data:
    # Unselected: a 0 mask, or a SequentialRelease time of -inf.
    ok = ok & ((b == 0) | jnp.isneginf(b))
  src = jnp.argmax(ok)

  def rep(a, scale=None):
    tail = jnp.broadcast_to(a[src], (k,) + a.shape[1:])
    if scale is not None:
      tail = tail * scale
    return jnp.concatenate([a, tail])

  def const(a, value):
    return jnp.concatenate([a, jnp.full((k,) + a.shape[1:], value, a.dtype)])

  state = state.replace(
    x=rep(state.x), v=rep(state.v), F=rep(state.F), C=rep(state.C),
    Jp=rep(state.Jp), ep=rep(state.ep),
    vol0=rep(state.vol0, GHOST_FRACTION), mass=rep(state.mass, GHOST_FRACTION),
    body_id=const(state.body_id, -1),
    bc_data=tuple(const(b, 0) for b in state.bc_data),
    F_N=None if state.F_N is None else rep(state.F_N))
  materials = jax.tree.map(rep, materials)
  return state, materials


def _state_specs(state: mpm.MPMState, axis: str) -> mpm.MPMState:
  p = P(axis)
  return state.replace(
    x=p, v=p, F=p, C=p, Jp=p, ep=p, vol0=p, mass=p, body_id=p,
    bc_data=tuple(p for _ in state.bc_data), t=P(), step=P(),
    F_N=None if state.F_N is None else p)


def rollout_sharded(state: mpm.MPMState, materials: mpm.Materials,
                    forces: mpm.Forces | None, config: mpm.SimConfig,
                    mesh: Mesh, num_frames: int | None = None,
                    axis_name: str | None = None):
  """``mpm.rollout`` with the particles split over a mesh axis.

  Pure, jit-able and differentiable like ``mpm.rollout`` (gradients pass
  through the psums). Jit it with ``config``, ``mesh``, ``num_frames`` and
  ``axis_name`` static.

  Args:
    state: initial state (N particles; any placement: ``shard_map``
      slices replicated inputs for free).
    materials: per-particle materials.
    forces: boundary-condition parameters (None: defaults), replicated.
    config: static ``mpm.SimConfig``.
    mesh: device mesh.
    num_frames: frames T (default ``config.num_frames``).
    axis_name: the mesh axis that splits the particles (default: the only
      axis). Other mesh axes hold replicas.

  Returns:
    ``(final_state, xs, Fs)`` as ``mpm.rollout``: xs (T+1, N, 3) and Fs
    (T+1, N, 3, 3) sharded along N.
  """
  axis = sh._axis(mesh, axis_name)  # noqa: SLF001
  # Each shard holds its own mix of models: no static per-model slices.
  config = dataclasses.replace(config, model_counts=None)
  num_frames = config.num_frames if num_frames is None else num_frames
  if num_frames is None or num_frames < 0:
    raise DistributedError('rollout_sharded: pass num_frames (or set '
                           'config.num_frames).')
  if forces is None:
    forces = mpm.make_forces(config, state.x.dtype)
  n = state.x.shape[0]
  state_p, mat_p = pad_particles(state, materials, mesh.shape[axis])
  reduce_fn = functools.partial(jax.lax.psum, axis_name=axis)

  def local(s, m, f):
    return mpm.rollout(s, m, f, config, num_frames, reduce_fn=reduce_fn)

  sspec = _state_specs(state_p, axis)
  fn = jax.shard_map(
    local, mesh=mesh,
    in_specs=(sspec, jax.tree.map(lambda _: P(axis), mat_p),
              jax.tree.map(lambda _: P(), forces)),
    out_specs=(sspec, P(None, axis), P(None, axis)))
  final, xs, Fs = fn(state_p, mat_p, forces)
  if state_p.x.shape[0] != n:
    cut = lambda a: a[:n] if a.ndim and a.shape[0] > n else a  # noqa: E731
    final = jax.tree.map(cut, final)
    xs, Fs = xs[:, :n], Fs[:, :n]
  return final, xs, Fs


def simulate_sharded(params: pl.Params, prepared: pl.PreparedScene,
                     config: pl.SimulateConfig | pl.PipelineConfig,
                     mesh: Mesh, field: jax.Array | None = None,
                     axis_name: str | None = None) -> pl.Trajectory:
  """``pipeline.simulate`` with the driving particles split over devices.

  Same inputs and outputs as :func:`physsplat_jax.pipeline.simulate`, which
  it calls with :func:`rollout_sharded` as its ``rollout_fn``; everything
  else (MPDP field, deformation, rendering) is left to XLA's sharding
  propagation. Jit with ``config``, ``mesh`` and ``axis_name`` static
  (``simulate_sharded_jit``).
  """
  def rollout_fn(state, materials, forces, sim_config, num_frames):
    return rollout_sharded(state, materials, forces, sim_config, mesh,
                           num_frames, axis_name)

  return pl.simulate(params, prepared, config, field, rollout_fn=rollout_fn)


simulate_sharded_jit = jax.jit(simulate_sharded,
                               static_argnames=('config', 'mesh', 'axis_name'))
