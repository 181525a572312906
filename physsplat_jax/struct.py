"""Immutable pytree dataclasses: ``PyTreeNode`` and ``field``.

The package's state and data types (``Gaussians``, ``Camera``,
``PreparedScene``, ``MPMState``...) are frozen dataclasses registered as
pytrees, written as with ``flax.struct``::

  class State(struct.PyTreeNode):
    x: jax.Array                                # a leaf: traced, mapped
    res: int = struct.field(pytree_node=False)  # static: part of the tree

``replace(**changes)`` returns a copy. The registration is JAX's own
(``jax.tree_util.register_dataclass``, flattened in C++), the same as
``flax.struct`` does, without importing Flax: a run that uses no network
does not pay Flax's import (0.08 s on the 2-core VM, about three times that
on the GPU hosts). What differs from ``flax.struct``: these classes are not
registered with ``flax.serialization`` (use ``jax.tree`` functions, or
``physsplat_jax.io.save_tree`` / ``load_tree`` for files: orbax refuses
zero-size arrays such as the ``forces`` of a scene without forces).
"""

from __future__ import annotations

import dataclasses
from typing import Any, TypeVar

import jax
import jax.numpy as jnp

from physsplat_jax.errors import PhysSplatError

try:  # Python >= 3.11 (typing_extensions not needed)
  from typing import dataclass_transform
except ImportError:  # pragma: no cover
  def dataclass_transform(**_):
    return lambda c: c

_T = TypeVar('_T')


def field(pytree_node: bool = True, *, metadata: dict | None = None,
          **kwargs) -> Any:
  """A dataclass field; ``pytree_node=False`` makes it static (hashable,
  part of the tree's structure: another value is another compiled
  program)."""
  return dataclasses.field(
    metadata={**(metadata or {}), 'pytree_node': pytree_node}, **kwargs)


def dataclass(cls: type[_T] | None = None, **kwargs):
  """Makes ``cls`` a frozen dataclass registered as a pytree (fields are
  leaves unless declared with ``field(pytree_node=False)``), with a
  ``replace`` method. ``kwargs`` go to ``dataclasses.dataclass``."""
  if cls is None:
    return lambda c: dataclass(c, **kwargs)
  if '_pytree_dataclass' in cls.__dict__:
    return cls
  kwargs.setdefault('frozen', True)
  cls = dataclasses.dataclass(**kwargs)(cls)
  data, meta = [], []
  for f in dataclasses.fields(cls):
    (data if f.metadata.get('pytree_node', True) else meta).append(f.name)
  cls.replace = _replace
  jax.tree_util.register_dataclass(cls, data, meta)
  cls._pytree_dataclass = True
  return cls


def _replace(self, **changes):
  """A copy with ``changes`` (field name -> value)."""
  return dataclasses.replace(self, **changes)


@dataclass_transform(field_specifiers=(field,))
class PyTreeNode:
  """Base class: each subclass is a :func:`dataclass` (frozen, a pytree).

  Keyword arguments of the class statement go to ``dataclasses.dataclass``
  (``class A(PyTreeNode, kw_only=True)``).
  """

  def __init_subclass__(cls, **kwargs):
    dataclass(cls, **kwargs)

  def replace(self: _T, **changes) -> _T:  # set on each subclass
    return dataclasses.replace(self, **changes)


class DtypeError(PhysSplatError, ValueError):
  """A float type that cannot be used (float64 without JAX's x64 mode)."""


def cast_floats(tree: _T, dtype) -> _T:
  """``tree`` with its floating leaves cast to ``dtype`` (integer and bool
  leaves kept): ``PreparedScene.astype``, ``Params.astype``."""
  dtype = jnp.dtype(dtype)
  if not jnp.issubdtype(dtype, jnp.floating):
    raise DtypeError(f'dtype {dtype} is not a floating type; use float32 '
                     'or float64')
  if dtype == jnp.float64 and not jax.config.read('jax_enable_x64'):
    raise DtypeError(
      "float64 needs JAX's x64 mode: call jax.config.update("
      "'jax_enable_x64', True) first (or set JAX_ENABLE_X64=1)")
  return jax.tree.map(
    lambda a: jnp.asarray(a, dtype) if jnp.issubdtype(
      jnp.result_type(a), jnp.floating) else a, tree)
