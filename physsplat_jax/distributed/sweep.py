"""Parameter sweeps and scene batches of the pipeline, sharded over devices.

A sweep is a batch of :class:`physsplat_jax.pipeline.Params` (axis 0 =
item) for one prepared scene: the material means scaled per item (E, nu,
rho multipliers through ``Params.log_scale``), initial velocities, force
vectors. The MPDP network weights, when present, are shared by every item
(replicated). A scene batch stacks prepared scenes of equal shapes and
equal static ``SimSpec`` (:func:`physsplat_jax.distributed.stack_trees`).
Both run as one ``jax.vmap`` of ``pipeline.simulate`` split over the mesh
(:func:`physsplat_jax.distributed.sharded_vmap`).
"""

from __future__ import annotations

import dataclasses
import itertools
from typing import Any, Callable, Sequence

import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh

from physsplat_jax import pipeline as pl
from physsplat_jax.distributed import sharding as sh
from physsplat_jax.distributed.runtime import DistributedError
from physsplat_jax.values import is_number
from physsplat_jax.values import is_real

# vmap axes of a batch of Params: the MPDP weights are shared.
PARAMS_AXES = pl.Params(mpdp=None, log_scale=0, velocity=0, forces=0)


def _multipliers(name: str, vals) -> list[float]:
  """``vals`` as a list of finite floats > 0 (a scalar is one item)."""
  items = [vals] if is_number(vals) else vals
  try:
    out = [float(v) for v in items]
    ok = bool(out) and all(is_real(v) and v > 0 for v in items)
  except (TypeError, ValueError):
    ok = False
  if not ok:
    raise DistributedError(
      f'sweep_params: {name} = {vals!r}; give one or more finite '
      'multipliers > 0 (a number or a list of numbers).')
  return out


def _velocities(velocity) -> list[tuple[float, float, float]]:
  """``velocity`` as a list of 3-tuples of finite floats (one 3-vector is
  one item)."""
  items = np.asarray(velocity, dtype=object)
  if items.ndim == 1 and items.size == 3 and all(is_number(c)
                                                  for c in items):
    velocity = [velocity]
  if is_number(velocity) or isinstance(velocity, (str, bytes)):
    velocity = [velocity]  # (refused below, with the item named)
  if len(velocity) == 0:
    raise DistributedError('sweep_params: velocity = []; give one or more '
                           'velocities, or None to keep params.velocity.')
  out = []
  for v in velocity:
    try:
      ok = len(v) == 3 and all(is_real(c) for c in v)
    except TypeError:
      ok = False
    if not ok:
      raise DistributedError(
        f'sweep_params: velocity {v!r} must be 3 finite numbers [m/s] '
        '(e.g. (0, 0, 1)); give a list of them for several items.')
    out.append(tuple(float(c) for c in v))
  return out


def sweep_params(
  params: pl.Params,
  E_scale: Sequence[float] = (1.0,),
  nu_scale: Sequence[float] = (1.0,),
  rho_scale: Sequence[float] = (1.0,),
  velocity: Sequence[Sequence[float]] | None = None,
) -> tuple[pl.Params, list[dict[str, Any]]]:
  """The Cartesian product of material multipliers and velocities.

  Args:
    params: base parameters (one scene; e.g. ``pipeline.init_params``).
    E_scale, nu_scale, rho_scale: multipliers of every movable object's
      perceived mean Young's modulus, Poisson ratio and density (> 0).
    velocity: initial velocities [m/s, scene axes] given to every movable
      object, each 3 numbers; None keeps ``params.velocity``.

  Returns:
    ``(batch, table)``: ``Params`` whose ``log_scale``, ``velocity`` and
    ``forces`` have a leading axis of ``B = len(E_scale) * len(nu_scale) *
    len(rho_scale) * len(velocity)`` items (``mpdp`` shared: vmap with
    ``PARAMS_AXES``), and one dict per item with its settings.

  A single number for a multiplier, or a single 3-vector for
  ``velocity``, is a sweep of one value.

  Raises:
    DistributedError: a multiplier that is not a finite number > 0, no
      velocities, or a velocity that is not 3 finite numbers.
  """
  E_scale, nu_scale, rho_scale = (
    _multipliers(name, vals) for name, vals in (
      ('E_scale', E_scale), ('nu_scale', nu_scale),
      ('rho_scale', rho_scale)))
  vels = [None] if velocity is None else _velocities(velocity)
  base_ls = np.asarray(params.log_scale)
  base_v = np.asarray(params.velocity)
  ls, vs, table = [], [], []
  for e, n, r, v in itertools.product(E_scale, nu_scale, rho_scale, vels):
    ls.append(base_ls + np.log([float(e), float(n), float(r)]))
    vs.append(base_v if v is None else np.broadcast_to(v, base_v.shape))
    table.append(dict(E_scale=float(e), nu_scale=float(n),
                      rho_scale=float(r),
                      velocity=None if v is None else list(v)))
  B = len(table)
  forces = np.broadcast_to(np.asarray(params.forces),
                           (B,) + tuple(np.shape(params.forces)))
  batch = params.replace(
    log_scale=jnp.asarray(np.stack(ls), base_ls.dtype),
    velocity=jnp.asarray(np.stack(vs), base_v.dtype),
    forces=jnp.asarray(forces))
  return batch, table


def make_simulate_batch(config: pl.PipelineConfig, mesh: Mesh,
                        batch_scenes: bool = False,
                        select: Callable[[pl.Trajectory], Any] | None = None,
                        axis_name: str | None = None) -> Callable:
  """A sharded batch of ``pipeline.simulate`` runs (compiled once).

  Args:
    config: the pipeline config every item shares (static).
    mesh: device mesh; the batch is split over ``axis_name``.
    batch_scenes: the prepared scenes are batched too (a stacked
      ``PreparedScene``, see ``stack_trees``); otherwise one scene is
      shared (replicated) by every item.
    select: keeps part of each ``Trajectory`` (e.g. ``lambda t: t.means``)
      so that less comes back from the devices; default: all of it.
    axis_name: the mesh axis (default: the only one).

  Returns:
    ``simulate_batch_fn(params_batch, prepared) -> pytree`` with a leading
    batch axis, sharded over the mesh (see ``sharded_vmap`` for padding).
  """
  if mesh.size > 1 and config.constitutive_kernel == 'auto':
    # A Pallas kernel has no partitioning rule: under the batch's sharding
    # XLA would gather every item to every device for it.
    config = dataclasses.replace(config, constitutive_kernel='jax')
  select = select or (lambda t: t)

  def one(params, prepared):
    return select(pl.simulate(params, prepared, config))

  return sh.sharded_vmap(one, mesh, in_axes=(PARAMS_AXES,
                                             0 if batch_scenes else None),
                         axis_name=axis_name)
