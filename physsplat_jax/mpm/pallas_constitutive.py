"""A substep's whole constitutive update as one Pallas kernel (GPU).

On a GPU the stress update of a scene with several materials is a long
per-particle chain (polar iteration, Jacobi sweeps, every model's return
map, the blend by model id). XLA compiles it as one fusion, but its fusion
passes grow much faster than the chain: of the tabletop's MPM frame
compiled for an H100 (without a GPU), 12 of 17 s went to them, against 3 s
for the one-material block (docs/benchmarks.md). The same code traced as
the body of a Pallas (Triton) kernel skips those passes: one kernel over
blocks of particles, one ``pl.when`` per slice of particles sorted by model
(``constitutive.constitutive_slices``), the plastic state written in place
(an aliased output), nothing per particle kept between substeps.

The kernel computes exactly what :func:`constitutive.constitute_slices`
computes (the same functions, traced in ``linalg.kernel_mode``: forward
code only, the polar iteration and Jacobi sweeps as loops). Its derivative
is that of the pure-JAX path (``jax.custom_jvp``: the tangent is
``constitute_slices``' own, and the reverse pass its transpose), so
gradients are unchanged, in forward and reverse mode. Off a
GPU it runs in Pallas interpret mode (slow; for tests).
"""

from __future__ import annotations

from concurrent import futures
import functools
import hashlib
import os
import threading

from absl import logging
import jax
import jax.numpy as jnp
from jax.experimental import pallas as pl

from physsplat_jax import platforms
from physsplat_jax import program_store
from physsplat_jax.mpm import constitutive
from physsplat_jax.mpm import linalg as la

# None where this JAX has no Triton backend (available() is then False).
plgpu = platforms.pallas_triton()

BLOCK = 128  # particles per program (one per thread with 4 warps)
NUM_WARPS = 4

# Values of the masked-off lanes of the last block: any valid material
# state (they are computed and never stored).
_BENIGN = {'E': 1.0, 'nu': 0.25, 'rho': 1.0}


def _index(lead, start, block):
  # Leading indices as int32 scalars (interpret mode's discharge rules take
  # no Python ints), then the block of particles.
  return tuple(jnp.int32(i) for i in lead) + (pl.ds(start, block),)


def _kernel(slices, dt, visc, n, block, treedef, names, has_body, rows,
            *refs):
  F_ref, C_ref, J_ref = refs[:3]
  k = 3 + len(names)
  mat_refs = refs[3:k]
  body_ref = refs[k] if has_body else None
  Fe_ref, Jo_ref, tau_ref = refs[-3:]
  start = pl.program_id(0) * block
  idx = start + jax.lax.iota(jnp.int32, block)
  inside = idx < n

  def load(ref, lead, other):
    return plgpu.load(ref.at[_index(lead, start, block)], mask=inside,
                      other=other)

  def store(ref, lead, value, mask):
    plgpu.store(ref.at[_index(lead, start, block)], value, mask=mask)

  def lead(k, i, j):  # (i, j) of a (3, 3, N) array, or a packed row
    return (i, j) if rows[k] is None else (rows[k] + 3 * i + j,)

  F = tuple(tuple(load(F_ref, lead(0, i, j), float(i == j))
                  for j in range(3)) for i in range(3))
  C = tuple(tuple(load(C_ref, lead(1, i, j), 0.0) for j in range(3))
            for i in range(3))
  Jp, ep = load(J_ref, (0,), 1.0), load(J_ref, (1,), 0.0)
  mat = jax.tree.unflatten(treedef, [
    load(r, (), 0 if name == 'model_id' else _BENIGN.get(name, 0.0))
    for r, name in zip(mat_refs, names)])
  rigid = load(body_ref, (), -1) >= 0 if has_body else None

  for models, k0, a, b in slices:
    @pl.when((start < b) & (start + block > a))
    def _(models=models, k0=k0, a=a, b=b):
      ids = None if len(models) == 1 else mat.model_id - k0
      with la.kernel_mode():
        Fe, Jp_new, ep_new, tau = constitutive.constitutive_update(
          models, ids, F, C, Jp, ep, mat, dt, zero_stress=rigid,
          solid_viscosity=visc)
      mask = inside & (idx >= a) & (idx < b)
      for i in range(3):
        for j in range(3):
          store(Fe_ref, (i, j), Fe[i][j], mask)
          store(tau_ref, (i, j), tau[i][j], mask)
      if not all(m in constitutive.NO_PLASTIC_STATE for m in models):
        store(Jo_ref, (0,), Jp_new, mask)
        store(Jo_ref, (1,), ep_new, mask)


def _struct(shape, dtype, like):
  """An output's shape and dtype, varying over the manual mesh axes as
  ``like`` does (inside ``shard_map``, e.g. particles split over devices,
  Pallas needs that said; outside it is empty)."""
  aval = jax.typeof(like)
  for field in ('manual_axis_type', 'vma'):  # (the name across JAX versions)
    value = getattr(aval, field, None)
    if value is not None:
      try:
        return jax.ShapeDtypeStruct(shape, dtype, **{field: value})
      except TypeError:
        pass
  return jax.ShapeDtypeStruct(shape, dtype)


def _reference(slices, dt, has_body, F, C, Jpep, mat, body_id, visc=False):
  """The pure-JAX update on the same (3, 3, N) arrays."""
  Fm, Cm = la.to_mat(F), la.to_mat(C)
  if has_body:  # one slice, no model_counts (see ``constitute``)
    (models, _, _, _), = slices
    Fe, Jpep, tau = constitutive.constitute_all(
      models, dt, Fm, Cm, Jpep, mat, body_id >= 0, solid_viscosity=visc)
  else:
    Fe, Jpep, tau = constitutive.constitute_slices(
      slices, dt, Fm, Cm, Jpep, mat, solid_viscosity=visc)
  return la.from_mat(Fe), Jpep, la.from_mat(tau)


def constitute(slices, dt, F, C, Jpep, mat, body_id=None, *,
               interpret: bool = False, block: int = BLOCK,
               num_warps: int = NUM_WARPS, solid_viscosity: bool = False):
  """The constitutive update of every particle in one Pallas kernel.

  Args:
    slices: static ``(models, first_model_index, start, end)`` per slice of
      particles (``constitutive.constitutive_slices``), covering ``[0, N)``;
      or one slice ``(config.models, 0, 0, N)`` with ``body_id`` for a scene
      without ``model_counts``.
    dt: substep [s] (Python float).
    F, C: (3, 3, N) trial deformation gradients and affine velocities, or
      each ``(array, first_row)``: nine rows of an (M, N) array (the
      solver's carry holds F and C as one (18, N) array: one kernel per
      substep fewer on a GPU than two arrays).
    Jpep: (2, N) plastic state ``(Jp, ep)``.
    mat: ``Materials`` with (N,) leaves.
    body_id: (N,) int32 or None; where ``>= 0`` the particle carries no
      stress (rigid bodies, for a scene without ``model_counts``).
    interpret: run the kernel in Pallas interpret mode (any backend).
    block, num_warps: particles per program and warps per program.
    solid_viscosity: the solids' Kelvin-Voigt stress
      (``SimConfig.solid_viscosity``).

  Returns:
    ``(F_e, Jpep, tau)``: (3, 3, N), (2, N), (3, 3, N).
  """
  if plgpu is None:
    raise RuntimeError('pallas_constitutive.constitute: ' +
                       platforms.triton_missing(
                         "SimConfig.constitutive_kernel='jax'"))
  rows = tuple(a[1] if isinstance(a, tuple) else None for a in (F, C))
  F, C = (a[0] if isinstance(a, tuple) else a for a in (F, C))
  n = F.shape[-1]
  has_body = body_id is not None
  leaves, treedef = jax.tree.flatten(mat)
  names = tuple(type(mat).__dataclass_fields__)
  names = tuple(f for f in names if getattr(mat, f) is not None)
  if len(names) != len(leaves) or any(
      jnp.shape(q) != (n,) for q in leaves):
    raise ValueError('pallas_constitutive.constitute: materials need one '
                     f'(N,) = ({n},) array per field')
  if has_body and len(slices) != 1:
    raise ValueError('pallas_constitutive.constitute: body_id goes with one '
                     'slice of every model (a scene without model_counts)')
  bodies = (body_id,) if has_body else ()

  def kernel_call(F, C, Jpep, leaves, bodies):
    kernel = functools.partial(_kernel, slices, dt, solid_viscosity, n,
                               block, treedef, names, has_body, rows)
    dtype = F.dtype
    params = {} if interpret else {
      'compiler_params': plgpu.CompilerParams(num_warps=num_warps,
                                              num_stages=1)}
    return pl.pallas_call(
      kernel,
      out_shape=(_struct((3, 3, n), dtype, F),
                 _struct(Jpep.shape, Jpep.dtype, Jpep),
                 _struct((3, 3, n), dtype, F)),
      grid=(pl.cdiv(n, block),),
      input_output_aliases={2: 1},
      interpret=interpret,
      name='constitutive_update',
      **params,
    )(F, C, Jpep, *leaves, *bodies)

  @jax.custom_jvp
  def update(F, C, Jpep, leaves, bodies):
    return kernel_call(F, C, Jpep, leaves, bodies)

  def reference(F, C, Jpep, leaves, bodies):
    F, C = (a if r is None else a[r:r + 9].reshape(3, 3, n)
            for a, r in zip((F, C), rows))
    return _reference(slices, dt, has_body, F, C, Jpep,
                      jax.tree.unflatten(treedef, leaves),
                      bodies[0] if has_body else None, solid_viscosity)

  @update.defjvp
  def jvp(primals, tangents):
    # The value from the kernel, the tangent from the pure-JAX update's own
    # (JAX transposes it for the reverse pass). The value through update
    # itself: a derivative of this rule (second order) uses the rule again,
    # not pallas_call's JVP (which refuses the aliased plastic state).
    return (update(*primals), jax.jvp(reference, primals, tangents)[1])

  return update(F, C, Jpep, leaves, bodies)


def available(dtype: str = 'float32') -> bool:
  """Whether the kernel builds on this process's GPU, in ``dtype``
  (checked once per dtype, even while a program is traced: every model,
  F and C packed in one array as the solver carries them, with slices and
  the solids' Kelvin-Voigt dashpot, and with ``body_id``). True without a
  GPU (off a GPU 'auto' never runs it; a program lowered for a GPU it
  cannot see is compiled there first). False, with a warning, when this
  JAX's Pallas cannot build it, and on any platform where this JAX has no
  Pallas Triton backend: ``SimConfig.constitutive_kernel = 'auto'`` then
  keeps the pure-JAX update instead of failing the run."""
  key = str(jnp.dtype(dtype))
  with _PROBES_LOCK:
    started = _PROBES.get(key)
  if started is not None:
    started.result()  # the background check (start_probe): done, or wait
  return _available(key)


# Checks started ahead by start_probe, by dtype.
_PROBES: dict = {}
_PROBES_LOCK = threading.Lock()


def start_probe(dtype: str = 'float32') -> None:
  """Starts :func:`available`'s check in the background, so that its
  compiles (two programs with the kernel, seconds on a cold cache) overlap
  other work instead of the frame's compile: ``pipeline.prepare_scene``
  starts it. Nothing off a GPU, or when started before."""
  if jax.default_backend() != 'gpu':
    return
  key = str(jnp.dtype(dtype))
  with _PROBES_LOCK:
    if key not in _PROBES:
      pool = futures.ThreadPoolExecutor(1, thread_name_prefix='mpm-probe')
      _PROBES[key] = pool.submit(_available, key)
      pool.shutdown(wait=False)  # its thread ends with the check


def probe_record(dtype: str, folder: str | None = None) -> str | None:
  """Where a passed check is recorded, or None (no compilation cache).

  In ``folder`` (default the persistent compilation cache's), named by
  what decides the check's outcome: JAX and jaxlib's versions, the GPU's
  kind, the dtype and the package's source (``program_store``'s digest). A
  later process with all of these equal skips the check (two programs
  traced, loaded and run: seconds of host work at the start of every
  run)."""
  if folder is None:
    folder = program_store.folder()
  if not folder:
    return None
  import jaxlib  # noqa: PLC0415

  parts = (jax.__version__, jaxlib.__version__, jax.devices()[0].device_kind,
           str(jnp.dtype(dtype)), program_store.source_digest())
  h = hashlib.sha256('\0'.join(parts).encode())
  return os.path.join(folder, 'physsplat_checks',
                      f'stress_kernel_{h.hexdigest()[:32]}')


@functools.lru_cache(maxsize=None)
def _available(dtype: str) -> bool:
  if plgpu is None:
    if jax.default_backend() == 'gpu':
      logging.warning('The MPM stress kernel does not run here: %s; the '
                      'pure-JAX update runs instead.',
                      platforms.triton_missing(
                        "SimConfig.constitutive_kernel='jax' to silence "
                        'this'))
    return False
  if jax.default_backend() != 'gpu':
    return True
  try:
    record = probe_record(dtype)
  except OSError:
    record = None
  if record is not None and os.path.exists(record):
    return True
  from physsplat_jax.mpm import base  # noqa: PLC0415

  def build():
    models = base.CANONICAL_MODELS
    deformable = tuple(m for m in models if m != 'rigid')
    n, m = 128, 96
    names = [deformable[i % len(deformable)] for i in range(m)]
    mat = base.make_materials(names + ['rigid'] * (n - m), 1e5, 0.3, 1000.0,
                              config_models=models, dtype=dtype)
    eye = jnp.eye(3, dtype=dtype).reshape(9, 1)
    FC = jnp.concatenate([jnp.broadcast_to(eye, (9, n)),
                          jnp.zeros((9, n), dtype)])
    Jpep = jnp.stack([jnp.ones(n, dtype), jnp.zeros(n, dtype)])
    body = jnp.where(jnp.arange(n) < m, -1, 0).astype(jnp.int32)
    sliced = ((deformable, 0, 0, m), (('rigid',), models.index('rigid'), m,
                                     n))
    one = ((models, 0, 0, n),)
    # The sliced form with the solids' dashpot on (SimConfig.
    # solid_viscosity: its terms in the kernel), the other without.
    for slices, body_id, visc in ((sliced, None, True), (one, body, False)):
      out = jax.jit(lambda FC, J, mt, b, s=slices, v=visc: constitute(
        s, 1e-4, (FC, 0), (FC, 9), J, mt, b, solid_viscosity=v))(
          FC, Jpep, mat, body_id)
      jax.block_until_ready(out)

  def in_thread():
    with jax.enable_x64(dtype == 'float64'):
      build()

  try:
    # On a thread of its own: JAX's tracing state is per thread, so this
    # runs (compiles and executes) even while the caller traces a program.
    with futures.ThreadPoolExecutor(1) as pool:
      pool.submit(in_thread).result()
  except Exception as e:  # noqa: BLE001 (any failure: fall back)
    logging.warning(
      'The MPM stress kernel (Pallas) does not build with this JAX in %s '
      '(%s: %s); the pure-JAX update runs instead (SimConfig.'
      "constitutive_kernel='jax' silences this).", dtype, type(e).__name__,
      e)
    return False
  if record is not None:
    try:
      os.makedirs(os.path.dirname(record), exist_ok=True)
      with open(record, 'w') as f:
        f.write('passed\n')
    except OSError:  # a read-only cache: check again next time
      pass
  return True
