"""The pure part: ``simulate(params, prepared, config)``, and its default
parameters (:func:`init_params`).

``simulate`` is a pure function of the differentiable ``params``
(:class:`~physsplat_jax.pipeline.Params`: MPDP weights, per-object
log-multipliers of E, nu, rho, initial velocities, force vectors)::

  field   = MPDP(params.mpdp, object drivers, object means)     (N, 3)
  E, nu, rho = means * exp(params.log_scale) * field            per driver
  x, F    = MLS-MPM rollout (lax.scan over frames and substeps,
            one jax.checkpoint per frame)                       (T+1, N, ...)
  means, covariances, rotations of the Gaussians = deform(x, F)
  images  = render(deformed Gaussians)                          (T+1, H, W, 3)

Its static config is the small :class:`SimulateConfig` (a
:class:`PipelineConfig` is accepted and reduced to it before tracing, so
host-side settings such as the seed never recompile it). The rollout is an
argument (``rollout_fn``): ``physsplat_jax.distributed`` passes its
particle-sharded one.
"""

from __future__ import annotations

from typing import Any, Callable

import jax
import jax.numpy as jnp
import numpy as np

from physsplat_jax import deform as deform_lib
from physsplat_jax import mpdp
from physsplat_jax import mpm
from physsplat_jax import struct
from physsplat_jax.mpm import inputs as mpm_inputs
from physsplat_jax.mpm.models import KELVIN_VOIGT_MODELS
from physsplat_jax.mpm.models import MAXWELL_FIELDS
from physsplat_jax.pipeline import capture as capture_lib
from physsplat_jax.pipeline.config import ForceKind
from physsplat_jax.pipeline.config import Ground
from physsplat_jax.pipeline.config import PipelineConfig
from physsplat_jax.pipeline.config import PipelineError
from physsplat_jax.pipeline.config import PrepareConfig
from physsplat_jax.pipeline.config import RenderMode
from physsplat_jax.pipeline.config import SimulateConfig
from physsplat_jax.pipeline.config import as_prepare_config
from physsplat_jax.pipeline.config import as_simulate_config
from physsplat_jax.pipeline.prepare import Params
from physsplat_jax.pipeline.prepare import PreparedScene
from physsplat_jax.pipeline.prepare import SimSpec
from physsplat_jax.render import raster
from physsplat_jax.types import Array
from physsplat_jax.types import device_array


class Trajectory(struct.PyTreeNode):
  """Output of :func:`simulate` (scene coordinates; axis 0 is frames).

  Attributes:
    x: (T+1, N, 3) driving-particle positions.
    means: (T+1, Ks, 3) simulated Gaussians' centres.
    covariances: (T+1, Ks, 3, 3) their covariances ``F Sigma F^T``.
    rotations: (T+1, Ks, 3, 3) their local rotations (SH view direction).
    images: (T+1, H, W, 3) rendered frames, or None (``render='none'``).
    render_overflow: (T+1,) bool, True where a frame dropped Gaussians
      (re-size ``config.render_config`` or use :func:`run`).
    materials: per-driver E, nu, rho actually simulated, each (N,).
    finite: (T+1,) bool, False from the first frame whose particle
      positions are not finite (the run went unstable; nothing inside jit
      can raise: :func:`check_finite` turns it into an error on the host).
    params_finite: ``'velocity'`` and ``'log_scale'`` -> (O,) bool,
      ``'forces'`` -> (len(config.forces),) bool: whether each row of those
      :class:`Params` was finite (:func:`check_finite` names a bad one).
  """

  x: Array
  means: Array
  covariances: Array
  rotations: Array
  images: Array | None
  render_overflow: Array | None
  materials: tuple[Array, Array, Array]
  finite: Array | None = None
  params_finite: dict[str, Array] | None = None


def init_params(prepared: PreparedScene,
                config: PrepareConfig | PipelineConfig,
                mpdp_params: Any = None, use_mpdp: bool | None = None
                ) -> Params:
  """Default :class:`Params`: pretrained MPDP, perceived means, the config's
  initial velocities and force vectors, in the prepared scene's float type
  (``prepared.astype(jnp.float64)`` first for float64 params).

  ``use_mpdp`` defaults to the config's (a PipelineConfig's field; a
  PrepareConfig has none: True); with False the
  params hold no network (``mpdp=None``). ``mpdp_params`` replaces the
  pretrained weights."""
  if use_mpdp is None:
    use_mpdp = getattr(config, 'use_mpdp', True)
  mp = None
  if use_mpdp:
    mp = mpdp.load_pretrained() if mpdp_params is None else mpdp_params
  names = prepared.spec.object_names
  vel = np.zeros((len(names), 3), np.float32)
  config = as_prepare_config(config)  # (a SimulateConfig has no velocities)
  for name, v in config.initial_velocity:
    if name:
      vel[names.index(name)] = v
    else:
      vel[:] = v
  forces = np.array([f.vector for f in config.forces], np.float32).reshape(
    len(config.forces), 3)
  params = Params(
    mpdp=mp, log_scale=device_array(np.zeros((len(names), 3), np.float32)),
    velocity=device_array(vel), forces=device_array(forces))
  return params.astype(prepared.x0.dtype)  # MPDP weights given too


def make_sim_config(spec: SimSpec, config: SimulateConfig | PipelineConfig,
                    dtype: str = 'float32') -> mpm.SimConfig:
  """The static MPM config of a prepared scene (``dtype``: 'float32' or
  'float64', that of the prepared arrays)."""
  config = as_simulate_config(config)
  col = spec.colliders
  bcs = []
  if config.ground is not Ground.NONE and col.ground_z is not None:
    bcs.append(mpm.SurfaceCollider(
      point=(0.0, 0.0, col.ground_z), normal=(0.0, 0.0, 1.0),
      surface='separate' if config.ground is Ground.SLIP else 'sticky',
      friction=config.friction))
  for lo, hi in col.anchors:
    c = tuple(0.5 * (a + b) for a, b in zip(lo, hi))
    h = tuple(0.5 * (b - a) + 0.5 * spec.dx for a, b in zip(lo, hi))
    bcs.append(mpm.Cuboid(point=c, size=h))
  for f, p in zip(config.forces, spec.force_points):
    start, end = f.window(spec.frame_dt)
    radius = 1e9 if f.kind is ForceKind.IMPULSE else f.radius
    bcs.append(mpm.PointForce(
      point=p, radius=radius, force=(0.0, 0.0, 0.0), start_time=start,
      end_time=end, per_particle=False))
  nb = int(sum(spec.rigid))
  models = tuple(dict.fromkeys(spec.models))
  counts = [0] * len(models)
  for m, (_, c) in zip(spec.models, spec.object_ranges):
    counts[models.index(m)] += c
  # A solid object given a viscosity is damped by it (Kelvin-Voigt), one
  # given a Maxwell branch's modulus is viscoelastic.
  solid = [dict(ps) for ps, m in zip(spec.object_params, spec.models)
           if m in KELVIN_VOIGT_MODELS]
  damped = any(ps.get('viscosity', 0.0) > 0 for ps in solid)
  maxwell = any(ps.get('maxwell_E', 0.0) > 0 for ps in solid)
  return mpm.SimConfig(
    grid=mpm.GridSpec(res=spec.grid_res, lower=spec.grid_lower,
                      size=spec.grid_size),
    dt=spec.dt, substeps_per_frame=spec.substeps_per_frame,
    num_frames=config.num_frames, gravity=(0.0, 0.0, -config.gravity),
    models=models, boundary_conditions=tuple(bcs),
    num_bodies=nb, body_fixed=(False,) * nb,
    remat_frames=config.remat_frames, dtype=str(np.dtype(dtype)),
    model_counts=tuple(counts),
    constitutive_kernel=config.constitutive_kernel,
    gpu_graphs=config.gpu_graphs, solid_viscosity=damped, maxwell=maxwell)


def driver_materials(params: Params, prepared: PreparedScene,
                     config: SimulateConfig | PipelineConfig,
                     field: Array | None = None) -> tuple[Array, Array, Array]:
  """Per-driver (E, nu, rho): MPDP field times the (scaled) object means.

  ``field``, if given, is an (N, 3) array of per-driver multipliers of
  (E, nu, rho) (driver order, e.g. a ground-truth or a fitted field) used
  instead of the MPDP prediction; gradients flow into it as into
  ``params``. Rigid objects keep their means either way.
  """
  config = as_simulate_config(config)
  spec = prepared.spec
  means = prepared.means * jnp.exp(params.log_scale)  # (O, 3)
  if field is not None:
    if tuple(field.shape) != (prepared.num_particles, 3):
      raise PipelineError(
        f'field has shape {tuple(field.shape)}; give (N, 3) = '
        f'({prepared.num_particles}, 3) multipliers of (E, nu, rho) per '
        'driving particle, in driver order.')
    flat = field.astype(prepared.x0.dtype)
  elif config.use_mpdp and params.mpdp is not None:
    pts = prepared.x0[prepared.mpdp_index]
    # (O, Nmax, 3); each object's volume-weighted mean is 1 (its mass and
    # mean stiffness are the means', however PGAS spaced its particles).
    field = mpdp.predict(params.mpdp, pts, prepared.mpdp_means,
                         prepared.mpdp_mask,
                         prepared.volume[prepared.mpdp_index])
    flat = jnp.concatenate([field[o, :c] for o, (_, c) in
                            enumerate(spec.object_ranges)])
    # (weights of another float type than the scene: the scene's)
    flat = flat.astype(prepared.x0.dtype)
  else:
    flat = jnp.ones((prepared.num_particles, 3), prepared.x0.dtype)
  per = means[prepared.driver_object] * flat
  # Rigid objects keep uniform properties (only their mass matters).
  rigid = jnp.asarray(spec.rigid)[prepared.driver_object]
  per = jnp.where(rigid[:, None], means[prepared.driver_object], per)
  nu = jnp.clip(per[:, 1], 0.0, mpdp.NU_MAX)
  return per[:, 0], nu, per[:, 2]


def _mpm_materials(E, nu, rho, prepared: PreparedScene,
                   sim_config: mpm.SimConfig) -> mpm.Materials:
  """Per-driver ``mpm.Materials`` from per-object tables (jit-safe)."""
  spec = prepared.spec
  obj = prepared.driver_object
  model_of_obj = [sim_config.models.index(m) for m in spec.models]
  fields = {}
  extra = MAXWELL_FIELDS if sim_config.maxwell else ()
  for k in mpm.base.FLOAT_FIELDS[3:] + extra:
    table = [dict(ps).get(k, mpm.MODEL_DEFAULTS[m].get(
      k, mpm.base._GENERIC[k]))  # noqa: SLF001
      for ps, m in zip(spec.object_params, spec.models)]
    fields[k] = jnp.asarray(table, E.dtype)[obj]
  return mpm.Materials(E=E, nu=nu, rho=rho,
                       model_id=jnp.asarray(model_of_obj, jnp.int32)[obj],
                       **fields)


def _check_params(params, prepared: PreparedScene, config) -> None:
  """Types of the arguments, shapes of :class:`Params` (static: safe under
  ``jit``)."""
  order = ('the arguments are (params, prepared, config): '
           'pipeline.init_params(prepared, config) makes params, '
           'pipeline.prepare_scene(key, scene, materials, config) prepared')
  if not isinstance(params, Params):
    raise PipelineError(f'params must be a pipeline.Params, got '
                        f'{type(params).__name__}; {order}')
  if not isinstance(prepared, PreparedScene):
    raise PipelineError(f'prepared must be a pipeline.PreparedScene, got '
                        f'{type(prepared).__name__}; {order}')
  spec = prepared.spec
  # Forces are placed when the scene is prepared (their objects and ball
  # centres are in the spec): a config with other forces than those was
  # simulated without them, silently, with a zero gradient for them.
  given = tuple(f.placement() for f in config.forces)
  if given != spec.force_placements:
    raise PipelineError(
      f'config.forces are placed at {list(given) or "nothing"} (object, '
      f"point; '' = every movable object, None = its centre), but the scene "
      f'was prepared with {list(spec.force_placements) or "nothing"}; '
      'forces are placed by prepare_scene: prepare the scene with the same '
      'forces as the config you simulate (their vectors are Params.forces)')
  O = len(spec.object_names)
  dtype = prepared.x0.dtype
  for name, want in (('log_scale', (O, 3)), ('velocity', (O, 3)),
                     ('forces', (len(config.forces), 3))):
    value = getattr(params, name)
    if not hasattr(value, 'dtype'):
      raise PipelineError(
        f'Params.{name} is a {type(value).__name__}; give an array '
        f'(jnp.asarray), as init_params makes it')
    got = tuple(np.shape(value))
    if got != want:
      raise PipelineError(
        f'Params.{name} has shape {got}; expected {want} (one row per '
        + ('movable object' if name != 'forces' else 'ForceSpec')
        + ' of the prepared scene, as init_params makes it)')
    # (a crash deep in the solver's loop; canonical: NumPy's float64 is
    # float32 to JAX without x64 mode)
    if jax.dtypes.canonicalize_dtype(value.dtype) != dtype:
      raise PipelineError(
        f'Params.{name} is {value.dtype} but the prepared scene is {dtype}:'
        ' cast both alike, prepared.astype(...) and params.astype(...), or '
        'init_params of the cast scene (docs/pipeline.md, float64)')


def initial_state(params: Params, prepared: PreparedScene,
                  config: SimulateConfig | PipelineConfig,
                  field: Array | None = None):
  """``(state, materials, forces, sim_config)`` at frame 0 (pure);
  ``field`` as in :func:`driver_materials`."""
  config = as_simulate_config(config)
  _check_params(params, prepared, config)
  spec = prepared.spec
  sim_config = make_sim_config(spec, config, prepared.x0.dtype)
  E, nu, rho = driver_materials(params, prepared, config, field)
  materials = _mpm_materials(E, nu, rho, prepared, sim_config)
  v_obj = prepared.frame.vector_to_sim(params.velocity)  # (O, 3)
  v0 = v_obj[prepared.driver_object]
  state = mpm.init_state(prepared.x0, v0, prepared.volume, materials,
                         sim_config, body_id=prepared.body_id)
  # Forces act on whole objects (or ball & object): replace the box/ball
  # selections made by init_state with object masks.
  sel = list(state.bc_data)
  values = list(mpm.make_forces(sim_config, prepared.x0.dtype).values)
  first = len(sim_config.boundary_conditions) - len(config.forces)
  pbc = sim_config.particle_bcs
  for i, (f, oi) in enumerate(zip(config.forces, spec.force_objects)):
    bc_index = first + i
    slot = pbc.index(bc_index)
    in_obj = (prepared.driver_object == oi) if oi >= 0 else jnp.ones(
      prepared.num_particles, bool)
    if f.kind is ForceKind.IMPULSE:
      mask = in_obj
    else:
      d = prepared.x0 - jnp.asarray(spec.force_points[i], prepared.x0.dtype)
      mask = in_obj & (jnp.sum(d * d, 1) < f.radius**2)
    sel[slot] = mask.astype(sel[slot].dtype)
    m_sel = jnp.sum(jnp.where(mask, state.mass, 0.0))
    vec = prepared.frame.vector_to_sim(params.forces[i])
    if f.kind is ForceKind.IMPULSE:  # velocity change over one frame
      values[bc_index] = vec * m_sel / spec.frame_dt
    else:  # acceleration of every selected particle
      values[bc_index] = vec * m_sel
  state = state.replace(bc_data=tuple(sel))
  return state, materials, mpm.Forces(values=tuple(values)), sim_config


def deformed_gaussians(prepared: PreparedScene,
                       config: SimulateConfig | PipelineConfig,
                       x: Array, F: Array | None = None):
  """Simulated Gaussians of one frame, in scene coordinates.

  Args:
    prepared: the prepared scene.
    config: static settings (``use_driver_F``).
    x: (N, 3) driver positions [m, simulation frame].
    F: (N, 3, 3) driver deformation gradients (used with ``use_driver_F``).

  Returns:
    (means (Ks, 3), covariances (Ks, 3, 3), rotations (Ks, 3, 3)).
  """
  dF = F if as_simulate_config(config).use_driver_F else None
  means, covs, rots = deform_lib.deform(
    prepared.binding, (prepared.rest_means, prepared.rest_covs), x, dF)
  fr = prepared.frame
  return (fr.to_scene(means), fr.covariance_to_scene(covs),
          fr.rotation_to_scene(rots))


def render_frame(prepared: PreparedScene,
                 config: SimulateConfig | PipelineConfig, means,
                 covs, rots, differentiable: bool = False,
                 render_config: raster.RenderConfig | None = None,
                 frame: Array | int = 0):
  """Renders the whole scene with the simulated rows replaced (pure), from
  the camera of frame ``frame`` (``camera_path``; may be traced)."""
  g_all, covs_all, rots_all = assemble_scene(prepared, means, covs, rots)
  fn = raster.render_differentiable if differentiable else raster.render
  camera = capture_lib.frame_camera(prepared.camera, prepared.orbit, frame,
                                    as_simulate_config(config).num_frames)
  return fn(g_all, camera, background=prepared.background,
            covariances=covs_all, view_rotations=rots_all,
            config=render_config or as_simulate_config(config).render_config)


def simulate(params: Params, prepared: PreparedScene,
             config: SimulateConfig | PipelineConfig,
             field: Array | None = None, *,
             rollout_fn: Callable | None = None) -> Trajectory:
  """MPDP -> materials -> MLS-MPM rollout -> deformed Gaussians -> frames.

  Pure and jit-able (:func:`simulate_jit`); differentiable with respect to
  ``params`` (``render='differentiable'`` for gradients through the images,
  ``'none'`` to stop at the Gaussians).

  Args:
    params: :class:`Params` (e.g. :func:`init_params`).
    prepared: from :func:`prepare_scene`.
    config: a :class:`SimulateConfig` (or a :class:`PipelineConfig`).
    field: optional (N, 3) per-driver multipliers of (E, nu, rho) that
      replace the MPDP prediction (see :func:`driver_materials`), e.g.
      ``prepared.field`` to reuse the field evaluated at preparation.
    rollout_fn: ``(state, materials, forces, sim_config, num_frames) ->
      (state, xs, Fs)``; default ``mpm.rollout`` (the distributed package
      passes its particle-sharded rollout).

  Returns:
    :class:`Trajectory` with ``config.num_frames + 1`` frames.
  """
  config = as_simulate_config(config)
  rollout_fn = mpm.rollout if rollout_fn is None else rollout_fn
  state, materials, forces, sim_config = initial_state(params, prepared,
                                                       config, field)
  _, xs, Fs = rollout_fn(state, materials, forces, sim_config,
                         config.num_frames)
  per_frame = jax.vmap(lambda x, F: deformed_gaussians(prepared, config, x, F))
  means, covs, rots = per_frame(xs, Fs)
  images = overflow = None
  if config.render is not RenderMode.NONE:
    diff = config.render is RenderMode.DIFFERENTIABLE
    try:
      outs = jax.lax.map(
        lambda a: render_frame(prepared, config, *a[:3], differentiable=diff,
                               frame=a[3]),
        (means, covs, rots, jnp.arange(config.num_frames + 1)))
    except TypeError as e:  # JAX's words, from deep inside the renderer
      _raise_forward_mode(e, config)
    images, overflow = outs.image, outs.overflow
  x_scene = prepared.frame.to_scene(xs)
  ok = jnp.all(jnp.isfinite(xs), axis=(1, 2))
  rows_ok = lambda a: jnp.all(jnp.isfinite(a), axis=1)  # noqa: E731
  return Trajectory(x=x_scene, means=means, covariances=covs, rotations=rots,
                    images=images, render_overflow=overflow,
                    materials=(materials.E, materials.nu, materials.rho),
                    finite=jnp.cumprod(ok.astype(jnp.int32)).astype(bool),
                    params_finite={k: rows_ok(getattr(params, k)) for k in
                                   ('velocity', 'log_scale', 'forces')})


_simulate_jit = jax.jit(simulate, static_argnames=('config', 'rollout_fn'))


def _raise_forward_mode(e: TypeError, config: SimulateConfig):
  """JAX's TypeError for forward mode through the renderer's custom VJPs
  as a PipelineError that names the fix; any other TypeError as it is."""
  if 'forward-mode autodiff' not in str(e):
    raise e
  if config.render is RenderMode.DIFFERENTIABLE:
    what = ("the GPU's Pallas compositor has reverse-mode derivatives only: "
            "use render_config=RenderConfig(backend='jax')")
  else:
    what = ("render='fast' (the render-only compositor) has no derivative: "
            "use render='differentiable'")
  raise PipelineError(
    f'forward mode (jax.jvp, jacfwd) through the images: {what}, whose JAX '
    "compositor works in both modes, or render='none' and a loss on the "
    'trajectory (docs/pipeline.md, "Working with params")') from None


def simulate_jit(params: Params, prepared: PreparedScene,
                 config: SimulateConfig | PipelineConfig,
                 field: Array | None = None, *,
                 rollout_fn: Callable | None = None) -> Trajectory:
  """:func:`simulate`, jitted; compiles once per :class:`SimulateConfig`
  and prepared-scene spec (host-side settings never recompile it)."""
  config = as_simulate_config(config)
  _check_params(params, prepared, config)
  try:
    return _simulate_jit(params, prepared, config, field,
                         rollout_fn=rollout_fn)
  except TypeError as e:  # (a jvp of the jitted call: traced outside it)
    _raise_forward_mode(e, config)


def check_finite(traj: Trajectory, prepared: PreparedScene) -> Trajectory:
  """Returns ``traj`` or raises ``SimulationError`` naming the first frame
  whose positions are not finite, the objects and the likely fix (host
  side, after a jitted :func:`simulate`).

  Bad inputs are named before the time step is blamed: non-finite
  ``Params`` rows (velocity, log_scale, forces), materials that no time
  step can simulate (the checks of ``mpm.run``: finite, rho > 0, E > 0 and
  -1 < nu < 0.5 but for rigid objects), non-finite initial positions.
  Non-finite ``Params`` rows or materials raise even when every position
  stayed finite: a particle of NaN mass drops out of the grid and stands
  still (its NaN is masked out), which is no simulation either.
  """
  finite = np.asarray(traj.finite)
  spec = prepared.spec
  dobj = np.asarray(prepared.driver_object)
  if finite.all():
    fault = _input_fault(traj, spec, dobj, nonfinite_only=True)
    if fault is not None:
      raise mpm.SimulationError(
        f'the positions stayed finite but the inputs are not: {fault}.')
    return traj
  f = int(np.argmin(finite))
  x = np.asarray(traj.x[f])
  bad = ~np.all(np.isfinite(x), axis=1)
  objs = sorted({spec.object_names[i] for i in dobj[bad]})
  fault = _input_fault(traj, spec, dobj)
  if fault is not None:
    raise mpm.SimulationError(
      f'non-finite particle positions from frame {f} (objects {objs}), '
      f'caused by the inputs, not the time step: {fault}.')
  raise mpm.SimulationError(
    f'the simulation went unstable at frame {f} (first non-finite particle '
    f'positions, objects {objs}): the time step is too large for the '
    'stiffest material or the speeds reached: raise substeps_per_frame (or '
    'lower cfl), lower E or the initial velocities and forces.')


def _input_fault(traj: Trajectory, spec: SimSpec, dobj: np.ndarray,
                 nonfinite_only: bool = False) -> str | None:
  """What is wrong with the inputs of ``traj``'s run, or None
  (``nonfinite_only``: only non-finite ``Params`` rows and materials)."""
  names = spec.object_names

  def rows_of(ok):
    return [int(i) for i in np.flatnonzero(~np.asarray(ok))]

  fixes = dict(
    velocity='give every movable object a finite initial velocity [m/s]',
    log_scale='give finite log-multipliers of (E, nu, rho)',
    forces='give every ForceSpec a finite vector')
  for k, ok in (traj.params_finite or {}).items():
    rows = rows_of(ok)
    if rows:
      which = (f'forces {rows}' if k == 'forces' else
               f'objects {[names[i] for i in rows]}')
      return f'Params.{k} is not finite for {which}; {fixes[k]}'
  E, nu, rho = (np.asarray(a, np.float64) for a in traj.materials)
  for label, v in (('E', E), ('nu', nu), ('rho', rho)):
    nonfinite = ~np.isfinite(v)
    if nonfinite.any():
      objs = sorted({names[i] for i in dobj[nonfinite]})
      return (f'material {label} is not finite for {int(nonfinite.sum())} '
              f'of {v.size} drivers (objects {objs}); check Params.log_scale, '
              'the MPDP params and the field')
  if nonfinite_only:
    return None
  stressed = np.asarray(spec.models)[dobj] != 'rigid'
  fault = mpm_inputs.material_fault(E, nu, rho, stressed)
  if fault is not None:
    label, mask, fix = fault
    objs = sorted({names[i] for i in dobj[mask]})
    return (f'{label} for {int(mask.sum())} of {mask.size} drivers (objects '
            f'{objs}); give each {fix}')
  x0 = np.asarray(traj.x[0])
  if not np.isfinite(x0).all():
    return 'the initial particle positions are not finite; prepare again'
  return None


def assemble_scene(prepared: PreparedScene, means, covs, rots):
  """All Gaussians with the simulated rows replaced (means, covs, rots)."""
  g = prepared.gaussians
  rows = prepared.sim_rows
  dt = g.means.dtype
  all_means = g.means.at[rows].set(means.astype(dt))
  all_covs = g.covariances.at[rows].set(covs.astype(dt))
  eye = jnp.broadcast_to(jnp.eye(3, dtype=dt), all_covs.shape)
  all_rots = eye.at[rows].set(rots.astype(dt))
  return g.replace(means=all_means), all_covs, all_rots


