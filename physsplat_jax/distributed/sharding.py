"""Batches of simulations sharded over devices (data parallelism).

A batch axis (a parameter sweep, many scenes of equal shapes, a training
batch) is split over a one-axis device mesh with
``NamedSharding(mesh, P(axis))``. The per-item function is ``jax.vmap``-ed
and ``jax.jit``-ed on batch-sharded inputs, so XLA's SPMD partitioner gives
every device ``B / D`` items and inserts no communication; a mean over the
batch, and its gradient with respect to replicated parameters, cost one
all-reduce that XLA adds by itself. Because every item is computed by the
same vmapped program, results equal the unsharded ``vmap`` up to float
rounding (usually bit for bit).

Inputs are placed with :func:`put`, which also builds global arrays in a
multi-process job (every process passes the same host value), and results
come back to the host with :func:`to_host` (an all-gather across processes
when the array spans several).

A batch that does not divide by the device count is padded with copies of
its last item, which are dropped from the results and weighted zero in
batch means.
"""

from __future__ import annotations

import functools
import math
from typing import Any, Callable, Sequence

import jax
import jax.numpy as jnp
import numpy as np
from jax.experimental import multihost_utils
from jax.sharding import AxisType
from jax.sharding import Mesh
from jax.sharding import NamedSharding
from jax.sharding import PartitionSpec as P

from physsplat_jax.distributed.runtime import DistributedError

BATCH_AXIS = 'batch'
PARTICLE_AXIS = 'particles'


# --------------------------------------------------------------------- mesh


def make_mesh(num_devices: int | None = None, axis_name: str = BATCH_AXIS,
              devices: Sequence[jax.Device] | None = None) -> Mesh:
  """A one-axis mesh over the job's devices (all processes).

  Args:
    num_devices: use the first this many devices (None: all).
    axis_name: name of the mesh axis (``BATCH_AXIS`` or
      ``PARTICLE_AXIS`` by convention).
    devices: explicit devices (default ``jax.devices()``, global).

  Returns:
    ``Mesh`` with ``Auto`` axis type (classic ``jit`` sharding
    propagation).
  """
  devices = list(jax.devices() if devices is None else devices)
  if num_devices is not None:
    if not 1 <= num_devices <= len(devices):
      raise DistributedError(
        f'make_mesh: num_devices = {num_devices} but {len(devices)} devices '
        'are available (on one CPU, set XLA_FLAGS=--xla_force_host_platform_'
        'device_count=N before importing jax, or '
        'physsplat_jax.distributed.initialize(cpu_devices=N)).')
    devices = devices[:num_devices]
  return jax.make_mesh((len(devices),), (axis_name,),
                       axis_types=(AxisType.Auto,), devices=devices)


def _axis(mesh: Mesh, axis_name: str | None) -> str:
  if axis_name is None:
    if len(mesh.axis_names) != 1:
      raise DistributedError(
        f'mesh has axes {mesh.axis_names}; name the one to '
        'shard over (axis_name=...).')
    return mesh.axis_names[0]
  if axis_name not in mesh.axis_names:
    raise DistributedError(
      f'axis_name = {axis_name!r} is not an axis of the mesh '
      f'{mesh.axis_names}.')
  return axis_name


def batch_sharding(mesh: Mesh, axis_name: str | None = None
                   ) -> NamedSharding:
  """Sharding of arrays whose axis 0 is split over ``axis_name``."""
  return NamedSharding(mesh, P(_axis(mesh, axis_name)))


def replicated(mesh: Mesh) -> NamedSharding:
  """Sharding of arrays held whole on every device of ``mesh``."""
  return NamedSharding(mesh, P())


# ---------------------------------------------------------- host <-> device


def _put_leaf(a, sharding: NamedSharding):
  if a is None:
    return None
  if jax.process_count() == 1:
    return jax.device_put(a, sharding)
  if isinstance(a, jax.Array) and not a.is_fully_addressable:
    return jax.device_put(a, sharding)  # already global: reshard
  host = np.asarray(a)  # every process holds the same full value
  return jax.make_array_from_callback(host.shape, sharding,
                                      lambda index: host[index])


def put(tree, sharding: NamedSharding | Any):
  """Places a pytree on the devices of a mesh.

  Args:
    tree: pytree of host or device arrays. In a multi-process job every
      process must pass the same values (the global array is assembled
      from each process's addressable slices).
    sharding: one ``NamedSharding`` for every leaf, or a pytree of them
      (a prefix of ``tree``).

  Returns:
    The pytree of (global) ``jax.Array``.
  """
  if isinstance(sharding, jax.sharding.Sharding):
    return jax.tree.map(lambda a: _put_leaf(a, sharding), tree)
  return jax.tree.map(lambda s, t: jax.tree.map(
    lambda a: _put_leaf(a, s), t), sharding, tree,
    is_leaf=lambda s: isinstance(s, jax.sharding.Sharding))


def to_host(tree):
  """Brings a pytree back to NumPy on every process.

  Arrays spanning several processes are all-gathered
  (``multihost_utils.process_allgather``), so every process must call this
  at the same point of the program.
  """
  def one(a):
    if isinstance(a, jax.Array) and not a.is_fully_addressable:
      return np.asarray(multihost_utils.process_allgather(a, tiled=True))
    return np.asarray(a)
  return jax.tree.map(one, tree)


# --------------------------------------------------------------- batching


def stack_trees(items: Sequence[Any]):
  """Stacks same-structure pytrees along a new axis 0 (a batch).

  Static fields (e.g. ``PreparedScene.spec``) are part of the structure, so
  only items that would share one compilation can share a batch.

  Raises:
    DistributedError: naming the first item and field that differ.
  """
  if not items:
    raise DistributedError('stack_trees: no items.')
  leaves0, tdef0 = jax.tree_util.tree_flatten_with_path(items[0])
  for i, it in enumerate(items[1:], 1):
    leaves, tdef = jax.tree_util.tree_flatten_with_path(it)
    if tdef != tdef0:
      raise DistributedError(
        f'stack_trees: item {i} differs from item 0 in its structure or '
        f'static fields{_static_diff(items[0], it)}; items of one batch '
        'must compile to one program (same SimSpec: grid, substeps, '
        'colliders, models), so simulate the others in a separate batch.')
    for (path, a), (_, b) in zip(leaves0, leaves):
      if np.shape(a) != np.shape(b) or jnp.result_type(a) != jnp.result_type(
          b):
        raise DistributedError(
          f'stack_trees: item {i} has {jax.tree_util.keystr(path)} of shape '
          f'{np.shape(b)} {jnp.result_type(b)}, item 0 '
          f'{np.shape(a)} {jnp.result_type(a)}; pad to equal sizes (e.g. '
          'one max_particles for every scene) or batch them separately.')
  return jax.tree.map(lambda *xs: jnp.stack(xs), *items)


def _static_diff(a, b) -> str:
  """' (spec.grid_lower: x vs y)' for the first differing static field."""
  import dataclasses  # pylint: disable=g-import-not-at-top

  def walk(x, y, path):
    if dataclasses.is_dataclass(x) and type(x) is type(y):
      for f in dataclasses.fields(x):
        r = walk(getattr(x, f.name), getattr(y, f.name), f'{path}.{f.name}')
        if r:
          return r
      return ''
    if isinstance(x, (jax.Array, np.ndarray)):
      return ''
    try:
      same = bool(x == y)
    except Exception:  # pylint: disable=broad-except
      same = True
    return '' if same else f' ({path.lstrip(".")}: {x!r} vs {y!r})'

  return walk(a, b, '')


def _flat_axes(in_axes, args):
  """Per argument, a list of (axis, subtree) pairs with axis 0 or None."""
  if not isinstance(in_axes, (tuple, list)):
    in_axes = (in_axes,) * len(args)
  if len(in_axes) != len(args):
    raise DistributedError(
      f'in_axes has {len(in_axes)} entries for {len(args)} '
      'arguments.')
  out = []
  for spec, arg in zip(in_axes, args):
    axes, tdef = jax.tree_util.tree_flatten(spec, is_leaf=lambda x: x is None)
    subs = tdef.flatten_up_to(arg)
    for ax in axes:
      if ax not in (0, None):
        raise DistributedError(f'in_axes entries must be 0 or None, got {ax!r} '
                               '(move the batch axis to the front).')
    out.append((axes, tdef, subs))
  return out


def _batch_size(flat) -> int:
  sizes = set()
  for axes, _, subs in flat:
    for ax, sub in zip(axes, subs):
      if ax == 0:
        sizes |= {np.shape(a)[0] for a in jax.tree.leaves(sub)}
  if len(sizes) != 1:
    raise DistributedError(
      f'batched arguments have batch sizes {sorted(sizes)}; '
      'give every batched leaf the same leading size (and at '
      'least one batched argument).')
  return sizes.pop()


def _pad_leaf(a, size):
  n = a.shape[0]
  if n == size:
    return a
  xp = np if isinstance(a, np.ndarray) else jnp
  tail = xp.broadcast_to(a[-1:], (size - n,) + a.shape[1:])
  return xp.concatenate([a, tail])


def _prepare(flat, size, mesh, axis, place):
  """Pads batched leaves to ``size`` and places every argument."""
  bs, rep = NamedSharding(mesh, P(axis)), NamedSharding(mesh, P())
  args = []
  for axes, tdef, subs in flat:
    new = []
    for ax, sub in zip(axes, subs):
      if ax == 0:
        sub = jax.tree.map(functools.partial(_pad_leaf, size=size), sub)
      if place:
        sub = put(sub, bs if ax == 0 else rep)
      new.append(sub)
    args.append(tdef.unflatten(new))
  return args


def sharded_vmap(fn: Callable, mesh: Mesh, in_axes: Any = 0,
                 axis_name: str | None = None) -> Callable:
  """``jax.vmap(fn)`` with the batch split over ``mesh``, jitted once.

  Args:
    fn: per-item function of positional arguments (pure; close static
      configuration into it).
    mesh: device mesh (e.g. :func:`make_mesh`).
    in_axes: per argument 0 (batched along axis 0) or None (shared,
      replicated), or a pytree prefix of an argument with 0/None leaves
      (e.g. ``Params(mpdp=None, log_scale=0, velocity=0, forces=0)``).
    axis_name: the mesh axis for the batch (default: the only axis).

  Returns:
    ``batch_fn(*args)`` -> pytree with leading batch axis, sharded over the
    mesh. A batch not divisible by the device count is padded with copies
    of its last item, which are cut from the result (the cut result is no
    longer split evenly: give a multiple of the device count to keep it
    sharded). Inputs are placed with :func:`put` (host values are fine, also
    in a multi-process job). ``batch_fn.place(*args) -> (placed_args, B)``
    and ``batch_fn.jitted`` time compilation apart from the run.
  """
  axis = _axis(mesh, axis_name)
  num = mesh.shape[axis]
  if isinstance(in_axes, list):
    in_axes = tuple(in_axes)
  vfn = jax.jit(jax.vmap(fn, in_axes=in_axes),
                out_shardings=NamedSharding(mesh, P(axis)))

  def place(*args):
    flat = _flat_axes(in_axes, args)
    n = _batch_size(flat)
    size = math.ceil(n / num) * num
    return _prepare(flat, size, mesh, axis, place=True), n

  def batch_fn(*args):
    placed, n = place(*args)
    out = vfn(*placed)
    if placed_size(placed) != n:
      out = jax.tree.map(lambda a: a[:n], out)
    return out

  def placed_size(placed):
    return _batch_size(_flat_axes(in_axes, placed))

  # For timing compile apart from run: args, n = batch_fn.place(*args);
  # batch_fn.jitted.lower(*args).compile().
  batch_fn.place = place
  batch_fn.jitted = vfn
  return batch_fn


def sharded_value_and_grad(loss_fn: Callable, mesh: Mesh, in_axes: Any = 0,
                           axis_name: str | None = None) -> Callable:
  """Mean loss over a device-sharded batch and its gradient.

  ``loss_fn(params, *batch_args) -> scalar`` is one item's loss; the
  returned ``grad_fn(params, *batch_args)`` computes ``L = mean_b
  loss_fn(params, item_b)`` with ``params`` replicated and the batch split
  over ``mesh``; XLA sums the per-device partial gradients with one
  all-reduce. It equals the single-device gradient up to float rounding.

  Args:
    loss_fn: per-item scalar loss, differentiated w.r.t. its first argument.
    mesh: device mesh.
    in_axes: for ``batch_args`` only, as in :func:`sharded_vmap`.
    axis_name: the batch mesh axis (default: the only axis).

  Returns:
    ``grad_fn(params, *batch_args) -> ((L, losses), grads)``: the mean
    loss, the (B,) per-item losses and the gradient pytree (replicated).
  """
  axis = _axis(mesh, axis_name)
  num = mesh.shape[axis]
  if not isinstance(in_axes, (tuple, list)):
    in_axes_t = None
  else:
    in_axes_t = tuple(in_axes)

  def total(params, weights, *args):
    axes = in_axes_t if in_axes_t is not None else (in_axes,) * len(args)
    losses = jax.vmap(loss_fn, in_axes=(None,) + axes)(params, *args)
    return jnp.sum(weights * losses) / jnp.sum(weights), losses

  rep, bs = NamedSharding(mesh, P()), NamedSharding(mesh, P(axis))
  vg = jax.jit(jax.value_and_grad(total, has_aux=True),
               out_shardings=((rep, bs), rep))

  def grad_fn(params, *args):
    flat = _flat_axes(in_axes if in_axes_t is None else in_axes_t, args)
    n = _batch_size(flat)
    size = math.ceil(n / num) * num
    batch = _prepare(flat, size, mesh, axis, place=True)
    dtype = jnp.result_type(*[a for a in jax.tree.leaves(params)
                              if jnp.issubdtype(jnp.result_type(a),
                                                jnp.floating)] or [float])
    w = put((np.arange(size) < n).astype(np.dtype(dtype)), bs)
    (loss, losses), grads = vg(put(params, rep), w, *batch)
    if size != n:
      losses = losses[:n]
    return (loss, losses), grads

  grad_fn.jitted = vg
  return grad_fn
