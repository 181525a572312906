"""Code chosen by platform, decided when it is traced where it can be.

Some of the solver's and the renderer's steps have a form per platform
with the same values (a loop on the CPU, the same chain unrolled on a GPU;
a Pallas kernel on a CUDA GPU, XLA's fusion elsewhere).
``jax.lax.platform_dependent`` picks one when the program is lowered, so
a trace holds every form, and a gradient linearizes and transposes every
form: tracing the README's three-frame gradient took 11.5 s on a 2-core
CPU, 5.1 s with the CPU's forms alone (docs/benchmarks.md).

:func:`platform_dependent` takes ``lax.platform_dependent``'s arguments.
Where the CPU is the only backend JAX started (no GPU or TPU in this
process) a program runs on the CPU, so it traces the CPU's form alone;
anywhere else it is ``lax.platform_dependent``. The exception is a program
lowered on purpose for a platform the process has no device of
(``.lower(lowering_platforms=('cuda',))``, a deviceless compile for a
GPU): trace it inside :func:`every_platform`, which keeps every form.
(Without it such a program is still correct, with the CPU's forms: every
form gives the same values.)
"""

from __future__ import annotations

import contextlib
import functools
import os
import threading

import jax

_LOCK = threading.Lock()
_EVERY = 0  # how many every_platform() blocks are open, in any thread


def traced_for_cpu_only() -> bool:
  """Whether a program traced now can only be lowered for the CPU (and so
  :func:`platform_dependent` traces the CPU's form alone): the CPU is the
  only backend JAX started (not ``JAX_PLATFORMS=cpu,cuda``, where the CPU
  is the default beside a GPU) and no :func:`every_platform` is open. (The
  default backend is read too: tests stand in a GPU by patching it.)"""
  return (_EVERY == 0 and jax.default_backend() == 'cpu'
          and _cpu_only_backends())


@functools.lru_cache(maxsize=None)
def _cpu_only_backends() -> bool:
  # (The backends are started once per process; cached: called per trace.)
  from jax.extend import backend  # noqa: PLC0415
  return set(backend.backends()) == {'cpu'}


def platform_dependent(*args, default=None, **per_platform):
  """``jax.lax.platform_dependent(*args, default=..., cpu=..., cuda=...)``,
  with the CPU's branch (``cpu``, else ``default``) called directly where
  :func:`traced_for_cpu_only`."""
  if traced_for_cpu_only():
    branch = per_platform.get('cpu', default)
    if branch is None:
      raise ValueError('platform_dependent: no branch for the CPU and no '
                       'default')
    return branch(*args)
  return jax.lax.platform_dependent(*args, default=default, **per_platform)


@functools.lru_cache(maxsize=None)
def pallas_triton():
  """JAX's Pallas Triton module (``jax.experimental.pallas.triton``), or
  None where this JAX has none.

  The GPU compositor and the MPM stress kernel are written for Pallas's
  Triton backend, which JAX 0.12 deprecates in favour of Mosaic GPU. Where
  a JAX has removed it the package still imports and runs: 'auto' picks
  the pure-JAX forms (same values), and asking for the kernels by name
  raises an error that says so.
  """
  try:
    from jax.experimental.pallas import triton  # noqa: PLC0415
  except ImportError:
    return None
  return triton


def triton_missing(fix: str) -> str:
  """The message for a JAX without Pallas's Triton backend, ``fix`` what
  to set instead."""
  return (f'this JAX ({jax.__version__}) has no Pallas Triton backend '
          "(jax.experimental.pallas.triton), which the package's GPU "
          f'kernels are written for: use {fix}, or a JAX that still has it '
          '(0.10 to 0.12)')


# The GPU a program lowered for CUDA on a host without one is lowered for
# (Pallas's Triton lowering reads its compute capability).
ABSTRACT_GPU = 'NVIDIA H100 80GB HBM3'


def _abstract_gpu():
  """A context giving JAX an abstract GPU device where this process has
  none (JAX 0.12's Pallas lowering for CUDA refuses to run without a GPU
  to target, 'No supported GPU devices found'; earlier versions assumed
  one); a null context where it has one, or where JAX cannot take one."""
  try:
    from jax.sharding import (  # noqa: PLC0415
      AbstractDevice, AbstractMesh, get_abstract_mesh, use_abstract_mesh)
    if any(d.platform == 'gpu' for d in jax.devices()) or (
        get_abstract_mesh().abstract_device is not None):
      return contextlib.nullcontext()
    device = AbstractDevice(device_kind=ABSTRACT_GPU, num_cores=None,
                            platform='gpu')
    return use_abstract_mesh(AbstractMesh((), (), abstract_device=device))
  except (ImportError, AttributeError, TypeError, RuntimeError):
    return contextlib.nullcontext()


@contextlib.contextmanager
def every_platform():
  """While open (in any thread), traces keep every platform's form, for a
  program lowered for a platform this process has no device of. JAX's
  trace caches are cleared on entry: a trace made before would hold the
  CPU's forms only. (Traces made inside stay valid after: they hold every
  form.) In a process without a GPU, lowerings for CUDA in this thread
  target :data:`ABSTRACT_GPU` (an abstract device, empty mesh)."""
  global _EVERY
  with _LOCK:
    _EVERY += 1
  jax.clear_caches()
  try:
    with _abstract_gpu():
      yield
  finally:
    with _LOCK:
      _EVERY -= 1


# XLA:CPU hands reductions (and element-wise chains) to YNNPACK by default;
# on the solver's small, odd-shaped reductions (the transposed B-spline
# weights: (N, 3, 3, 3) summed over the stencil) XLA's own loops are about
# twice as fast: the tabletop's two-frame gradient 4.41-4.43 s against
# 5.65-5.72 s, MPDP's field on 50k points 0.43 against 0.55 s; the forward
# substep and the renderer unchanged (docs/benchmarks.md). Dots stay with
# YNNPACK. The flag exists in the jaxlib versions listed (an unknown flag
# in XLA_FLAGS aborts the process, so others are left alone); jaxlib
# 0.12.0.1 accepts it too, but gained nothing from it (docs/benchmarks.md).
_CPU_FLAG_NAME = 'xla_cpu_experimental_ynn_fusion_type'
_CPU_FLAG = f'--{_CPU_FLAG_NAME}=dot,individual_dot'
_CPU_FLAG_JAXLIB = ('0.10.2',)
OPT_OUT = 'PHYSSPLAT_JAX_XLA_CPU_TUNING'


def tune_xla_cpu(environ=None) -> bool:
  """Adds the package's XLA:CPU setting to ``XLA_FLAGS`` (reductions
  compiled by XLA itself instead of YNNPACK: gradients through the solver
  about 20 % faster on the CPU, GPUs unaffected).

  Called when ``physsplat_jax`` is imported. It changes nothing (and
  returns False) where ``PHYSSPLAT_JAX_XLA_CPU_TUNING=0``, where
  ``XLA_FLAGS`` already sets that flag (the user's choice stands), with a
  jaxlib it was not checked against, or once JAX's backends have started
  (XLA reads ``XLA_FLAGS`` when the first backend starts: import
  ``physsplat_jax`` before the first JAX computation for it to apply).
  The setting is process-wide: it applies to every program this process
  compiles for the CPU afterwards, and to subprocesses, which inherit
  ``XLA_FLAGS``. Returns whether it was added.
  """
  env = os.environ if environ is None else environ
  if env.get(OPT_OUT, '1').strip().lower() in ('0', 'off', 'false', 'no'):
    return False
  flags = env.get('XLA_FLAGS', '')
  if _CPU_FLAG_NAME in flags:
    return False
  import jaxlib  # noqa: PLC0415
  if str(getattr(jaxlib, '__version__', '')) not in _CPU_FLAG_JAXLIB:
    return False
  try:
    from jax._src import xla_bridge  # noqa: PLC0415
    if xla_bridge._backends:  # noqa: SLF001 - started: too late
      return False
  except (ImportError, AttributeError):
    return False
  env['XLA_FLAGS'] = f'{flags} {_CPU_FLAG}'.strip()
  return True
