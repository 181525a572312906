"""Training MPDP through a differentiable MLS-MPM rollout.

Loss between a simulated and a target trajectory, with gradients through the
whole simulation into the network weights:

  field = predict(theta, x0, means)                 (N, 3), mean 1
  E_i, nu_i, rho_i = mean * field_i                  (nu clipped < 0.5)
  X(theta) = MPM(x0, E, nu, rho)                     (T, N, 3) frames
  L(theta) = mean_{t, i} |X_ti(theta) - X*_ti|^2 / dx^2

Targets ``X*`` are simulated from the ground-truth synthetic fields
(:mod:`physsplat_jax.mpdp.synthetic`, documented rules); the mean-only
baseline is ``field = 1``, which is exactly what the zero-initialised network
outputs before training.

Simulator: a compact MLS-MPM (Hu et al. 2018, "A moving least squares
material point method"), 3D, quadratic B-splines, APIC transfer, per-particle
compressible neo-Hookean Kirchhoff stress
``tau = mu (F F^T - I) + lam log(J) I`` (no SVD, so gradients stay finite at
F = I), gravity -z, a clamped region (grid nodes with ``x < clamp_x`` have
zero velocity: the cantilever root) and sticky domain walls. It is
self-contained because the package solver (``physsplat_jax.mpm``) was not
available when this was written; ``make_rollout`` is the single point to swap
it in (it takes per-particle E, nu, rho exactly as the package solver's
material params do). Frames are ``jax.checkpoint``-ed so memory is about one
carry per frame.

Scene: an axis-aligned cantilever (:func:`synthetic.make_beam`) scaled to
length ``beam_length`` in the unit cube, root at ``x = root_x``, given an
initial downward velocity ``v0`` (all particles), released under gravity.
"""

from __future__ import annotations

import dataclasses
import itertools

import jax
import jax.numpy as jnp
import numpy as np
import optax

from physsplat_jax.mpdp import model as model_lib
from physsplat_jax.mpdp import synthetic


@dataclasses.dataclass(frozen=True)
class SimConfig:
  """Static configuration of the small rollout (SI units, 1 m domain).

  Attributes:
    grid_res: cells per axis of the unit cube.
    dt: substep [s].
    substeps_per_frame: substeps between recorded frames.
    num_frames: recorded frames T.
    gravity: z acceleration [m/s^2].
    v0: initial z velocity of all particles [m/s].
    beam_length: beam length in the domain [m].
    root_x: x of the clamped root face [m]; nodes with x < root_x + dx are
      fixed.
    E, nu, rho: object mean properties [Pa, -, kg/m^3].
  """

  grid_res: int = 20
  dt: float = 2e-4
  substeps_per_frame: int = 100
  num_frames: int = 10
  gravity: float = -9.8
  v0: float = -1.0
  beam_length: float = 0.5
  root_x: float = 0.2
  E: float = 1e6
  nu: float = 0.3
  rho: float = 1000.0

  @property
  def dx(self) -> float:
    return 1.0 / self.grid_res


def make_beam_scene(seed: int, num_points: int, config: SimConfig):
  """A synthetic cantilever placed in the unit cube.

  Returns:
    dict of jnp arrays: 'x0' (N, 3) [m], 'vol' (N,) [m^3], 'field' (N, 3)
    ground truth, 'means' (MEANS_DIM,), 'mask' (N,).
  """
  o = synthetic.make_beam(seed, num_points, config.E, config.nu, config.rho)
  length = float(o.points[:, 0].max())
  s = config.beam_length / length
  x0 = o.points.astype(np.float64) * s + np.array([config.root_x, 0.5, 0.5])
  # Particle volumes: the beam volume (tapered box) shared equally.
  ext = np.ptp(o.points[:, 1:], axis=0) * s
  taper = o.thickness.min() / o.thickness.max()
  area_ratio = (1 + taper + taper ** 2) / 3.0   # mean of (1 - a u)^2
  vol = ext[0] * ext[1] * config.beam_length * area_ratio / num_points
  return {
    'x0': jnp.asarray(x0, jnp.float32),
    'vol': jnp.full((num_points,), vol, jnp.float32),
    'field': jnp.asarray(o.field),
    'means': o.means,
    'mask': jnp.ones((num_points,), bool),
  }


def _lame(E, nu):
  mu = E / (2.0 * (1.0 + nu))
  lam = E * nu / ((1.0 + nu) * (1.0 - 2.0 * nu))
  return mu, lam


def make_rollout(config: SimConfig):
  """Returns ``rollout_fn(x0, vol, E, nu, rho) -> (T, N, 3)`` positions.

  All of x0 (N, 3) [m], vol (N,) [m^3], E (N,) [Pa], nu (N,), rho (N,)
  [kg/m^3] are arguments (differentiable); the config is static.
  """
  res = config.grid_res
  dx = config.dx
  inv_dx = 1.0 / dx
  dt = config.dt
  offsets = jnp.asarray(list(itertools.product(range(3), repeat=3)))  # 27x3
  node = jnp.stack(jnp.meshgrid(*[jnp.arange(res)] * 3, indexing='ij'), -1)
  node = node.reshape(-1, 3)
  clamp = (node[:, 0] * dx < config.root_x + dx)
  wall = jnp.any((node < 2) | (node > res - 3), axis=-1)
  fixed = (clamp | wall)[:, None]
  gravity = jnp.array([0.0, 0.0, config.gravity])

  def substep(state, mat):
    x, v, C, F = state
    mu, lam, mass, vol = mat
    base = jnp.floor(x * inv_dx - 0.5).astype(jnp.int32)
    fx = x * inv_dx - base
    w = jnp.stack([0.5 * (1.5 - fx) ** 2, 0.75 - (fx - 1.0) ** 2,
                   0.5 * (fx - 0.5) ** 2])                    # (3, N, 3)
    J = jnp.linalg.det(F)
    # Neo-Hookean Kirchhoff stress; J floored so log stays finite.
    FFt = jnp.einsum('nij,nkj->nik', F, F)
    eye = jnp.eye(3)
    tau = (mu[:, None, None] * (FFt - eye)
           + (lam * jnp.log(jnp.maximum(J, 1e-3)))[:, None, None] * eye)
    affine = (-dt * 4.0 * inv_dx ** 2) * vol[:, None, None] * tau + (
      mass[:, None, None] * C)
    # Weights and positions for the 27 neighbours: (27, N).
    wk = (w[offsets[:, 0], :, 0] * w[offsets[:, 1], :, 1]
          * w[offsets[:, 2], :, 2])
    dpos = (offsets[:, None, :] - fx[None]) * dx               # (27, N, 3)
    idx = base[None] + offsets[:, None, :]
    flat = (idx[..., 0] * res + idx[..., 1]) * res + idx[..., 2]
    mom = wk[..., None] * (mass[:, None] * v + jnp.einsum(
      'nij,knj->kni', affine, dpos))
    gm = jnp.zeros(res ** 3).at[flat.reshape(-1)].add(
      (wk * mass[None]).reshape(-1))
    gp = jnp.zeros((res ** 3, 3)).at[flat.reshape(-1)].add(mom.reshape(-1, 3))
    has = gm > 1e-12
    gv = gp / jnp.where(has, gm, 1.0)[:, None]
    gv = jnp.where(has[:, None], gv + dt * gravity, 0.0)
    gv = jnp.where(fixed, 0.0, gv)
    # G2P (APIC): velocity, affine C, then positions and F.
    gvk = gv[flat]                                            # (27, N, 3)
    v = jnp.sum(wk[..., None] * gvk, axis=0)
    C = 4.0 * inv_dx ** 2 * jnp.einsum('kn,kni,knj->nij', wk, gvk, dpos)
    x = x + dt * v
    F = F + dt * jnp.einsum('nij,njk->nik', C, F)
    return (x, v, C, F)

  def rollout_fn(x0, vol, E, nu, rho):
    n = x0.shape[0]
    mu, lam = _lame(E, nu)
    mat = (mu, lam, rho * vol, vol)
    state = (x0, jnp.broadcast_to(jnp.array([0.0, 0.0, config.v0]), (n, 3)),
             jnp.zeros((n, 3, 3)), jnp.broadcast_to(jnp.eye(3), (n, 3, 3)))

    @jax.checkpoint
    def frame(s, _):
      s = jax.lax.fori_loop(0, config.substeps_per_frame,
                            lambda i, c: substep(c, mat), s)
      return s, s[0]

    _, xs = jax.lax.scan(frame, state, None, length=config.num_frames)
    return xs

  return rollout_fn


def make_trajectory_loss(config: SimConfig,
                         model_config=model_lib.ModelConfig()):
  """Returns ``loss_fn(params, scene, target) -> scalar`` (units of dx^2).

  ``target`` is (T, N, 3) positions; ``params=None`` evaluates the mean-only
  baseline (field = 1).
  """
  rollout_fn = make_rollout(config)
  predict_fn = model_lib.make_predict(model_config)

  def loss_fn(params, scene, target):
    if params is None:
      field = jnp.ones_like(scene['field'])
    else:
      field = predict_fn(params, scene['x0'], scene['means'], scene['mask'])
    E, nu, rho = model_lib.material_from_field(field, config.E, config.nu,
                                               config.rho)
    xs = rollout_fn(scene['x0'], scene['vol'], E, nu, rho)
    return jnp.mean(jnp.sum((xs - target) ** 2, -1)) / config.dx ** 2

  return loss_fn


def target_trajectory(scene, config: SimConfig):
  """(T, N, 3) trajectory simulated with the ground-truth field."""
  E, nu, rho = model_lib.material_from_field(scene['field'], config.E,
                                             config.nu, config.rho)
  return jax.jit(make_rollout(config))(scene['x0'], scene['vol'], E, nu, rho)


def train_through_simulator(params, train_scenes, config: SimConfig,
                            num_steps: int, learning_rate: float = 1e-3,
                            model_config=model_lib.ModelConfig(),
                            log_fn=None):
  """Adam on the trajectory loss summed over scenes.

  Args:
    params: initial network params.
    train_scenes: list of (scene, target) pairs.
    config: simulator config.
    num_steps: optimisation steps (one gradient over all scenes each).
    learning_rate: Adam step size.
    model_config: network architecture.
    log_fn: optional ``log_fn(step, loss)`` callback on the host.

  Returns:
    (params, list of per-step mean losses).
  """
  loss_fn = make_trajectory_loss(config, model_config)

  def total(p):
    return sum(loss_fn(p, s, t) for s, t in train_scenes) / len(train_scenes)

  tx = optax.chain(optax.clip_by_global_norm(1.0), optax.adam(learning_rate))
  opt_state = tx.init(params)

  @jax.jit
  def step(p, o):
    loss, g = jax.value_and_grad(total)(p)
    u, o = tx.update(g, o, p)
    return optax.apply_updates(p, u), o, loss

  history = []
  for i in range(num_steps):
    params, opt_state, loss = step(params, opt_state)
    history.append(float(loss))
    if log_fn is not None:
      log_fn(i, float(loss))
  return params, history


def make_scenes(seeds, num_points: int, config: SimConfig):
  """[(scene, target trajectory)] for the given beam seeds."""
  out = []
  for seed in seeds:
    scene = make_beam_scene(seed, num_points, config)
    out.append((scene, target_trajectory(scene, config)))
  return out


def trajectory_errors(params, scenes, config: SimConfig,
                      model_config=model_lib.ModelConfig()):
  """Per-scene trajectory loss [dx^2] of ``params`` (None: baseline)."""
  loss_fn = jax.jit(make_trajectory_loss(config, model_config))
  return [float(loss_fn(params, s, t)) for s, t in scenes]


def run_demo(num_steps: int = 30, learning_rate: float = 3e-3,
             train_seeds=(0, 1, 2), eval_seeds=(10, 11),
             num_points: int = 128, config: SimConfig = SimConfig(),
             init_params=None, log_fn=None):
  """Through-the-simulator training from the mean-only baseline.

  Starts from the zero-initialised network (field = 1, i.e. the baseline)
  unless ``init_params`` is given, trains on ``train_seeds`` beams and
  reports trajectory errors on train and held-out beams.

  Returns:
    dict with 'history', 'train_baseline', 'train_trained',
    'eval_baseline', 'eval_trained' (per-scene losses in dx^2) and
    'params'.
  """
  train_scenes = make_scenes(train_seeds, num_points, config)
  eval_scenes = make_scenes(eval_seeds, num_points, config)
  params = init_params
  if params is None:
    params = model_lib.init_params(jax.random.key(0))
  result = {
    'train_baseline': trajectory_errors(None, train_scenes, config),
    'eval_baseline': trajectory_errors(None, eval_scenes, config),
    'train_initial': trajectory_errors(params, train_scenes, config),
    'eval_initial': trajectory_errors(params, eval_scenes, config),
  }
  params, history = train_through_simulator(
    params, train_scenes, config, num_steps, learning_rate, log_fn=log_fn)
  result.update(
    history=history, params=params,
    train_trained=trajectory_errors(params, train_scenes, config),
    eval_trained=trajectory_errors(params, eval_scenes, config))
  return result


def poly_basis(x0, degree: int = 2):
  """(N, D) monomials of the normalised coordinates, without the constant.

  Degree 1: x, y, z; degree 2 adds x^2, y^2, z^2, xy, xz, yz (D = 9).
  """
  p = model_lib.normalize_points(x0, jnp.ones(x0.shape[:1], bool))
  cols = [p]
  if degree >= 2:
    i, j = np.triu_indices(3)
    cols.append(p[:, i] * p[:, j])
  return jnp.concatenate(cols, axis=-1)


def fit_material(scene, target, config: SimConfig, num_steps: int = 60,
                 learning_rate: float = 0.05, E_init: float | None = None,
                 field_degree: int = 2, log_fn=None):
  """Recovers E (mean and a smooth field) from an observed trajectory.

  Parameters: ``log E_mean`` and the coefficients ``c`` of a polynomial
  log-field ``l = B(x0) c`` (monomials of the normalised rest positions up
  to ``field_degree``; 0 fits only the mean), ``m_E = exp(l) / mean
  exp(l)`` (mean exactly 1, as in MPDP). A free per-particle field is
  ill-posed at this resolution (it overfits the trajectory, and Adam drives
  unobservable particles anywhere), so the field is kept smooth. nu and rho
  stay at the scene's true values (only E is unknown). Adam with cosine
  decay on the trajectory loss.

  Args:
    scene: dict from :func:`make_beam_scene`.
    target: (T, N, 3) observed positions.
    config: simulator config (``config.E`` is the true mean; the default
      initial guess is 0.3 * config.E).
    num_steps: Adam steps.
    learning_rate: peak Adam step size (on log E and the coefficients).
    E_init: initial mean E guess [Pa].
    field_degree: 0 (mean only), 1 or 2.
    log_fn: optional ``log_fn(step, loss, E_mean)``.

  Returns:
    dict: 'E_mean' [Pa], 'field_E' (N,), 'history' (losses [dx^2]),
    'final_loss'.
  """
  rollout_fn = make_rollout(config)
  n = scene['x0'].shape[0]
  E_init = 0.3 * config.E if E_init is None else E_init
  _, nu, rho = model_lib.material_from_field(scene['field'], config.E,
                                             config.nu, config.rho)
  basis = (poly_basis(scene['x0'], field_degree) if field_degree > 0
           else jnp.zeros((n, 0)))
  theta = {'log_E': jnp.log(jnp.asarray(E_init, jnp.float32)),
           'coef': jnp.zeros((basis.shape[1],), jnp.float32)}

  def field_of(th):
    return model_lib.normalize_field((basis @ th['coef'])[:, None],
                                     scene['mask'])[:, 0]

  def loss_fn(th):
    E = jnp.exp(th['log_E']) * field_of(th)
    xs = rollout_fn(scene['x0'], scene['vol'], E, nu, rho)
    return jnp.mean(jnp.sum((xs - target) ** 2, -1)) / config.dx ** 2

  tx = optax.adam(optax.cosine_decay_schedule(learning_rate, num_steps,
                                              alpha=0.05))
  opt = tx.init(theta)

  @jax.jit
  def step(th, o):
    loss, g = jax.value_and_grad(loss_fn)(th)
    u, o = tx.update(g, o, th)
    return optax.apply_updates(th, u), o, loss

  history = []
  for i in range(num_steps):
    theta, opt, loss = step(theta, opt)
    history.append(float(loss))
    if log_fn is not None:
      log_fn(i, float(loss), float(jnp.exp(theta['log_E'])))
  return {'E_mean': float(jnp.exp(theta['log_E'])),
          'field_E': field_of(theta), 'history': history,
          'final_loss': float(jax.jit(loss_fn)(theta))}
