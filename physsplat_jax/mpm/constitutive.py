"""Constitutive models: plastic return maps and Kirchhoff stresses.

Every model maps the trial deformation gradient of a particle (after the
latest G2P, ``F_tr``) and its plastic state to an elastic ``F_e``, an updated
plastic state and the Kirchhoff stress ``tau = P F_e^T`` that MLS-MPM
scatters (Hu et al. 2018). Fields are structure-of-arrays nested tuples
(``linalg``); ``mu, lam`` are the Lame parameters from (E, nu).

Elastic models:

- ``fixed_corotated``: ``tau = 2 mu (F - R) F^T + lam J (J - 1) I`` with the
  polar rotation R (Newton iteration, ``linalg.polar_mat``). For an
  inverted particle (``det F < 0``) that R is a reflection, whereas the
  spectral form (used next to an SVD model) takes Stomakhin et al.'s
  rotation-variant SVD: the two differ there. Only a particle crushed
  through zero volume gets there (``mpm.run`` stops at ``det F < 0.01``).
- ``neo_hookean`` (compressible, Bonet & Wood):
  ``tau = mu (F F^T - I) + lam log(J) I``.
- ``stvk``: St. Venant-Kirchhoff with the *Hencky* (logarithmic) strain, the
  model PhysGaussian calls "StVK": ``tau = U diag(2 mu eps + lam tr(eps))
  U^T`` with ``eps = log(s)`` from ``F = U diag(s) V^T``, the Kirchhoff
  stress of the Hencky energy. (PhysGaussian's ``kirchoff_stress_StVK``
  returns ``U diag(...) V^T F^T = U diag((2 mu eps + lam tr eps) s) U^T``,
  one factor ``s`` more per principal direction; its own Drucker-Prager
  stress divides it out, as here. von_mises and foam use this stress too.)

Plastic models (return maps on the log singular values ``eps``; ``eps^`` is
the deviatoric part, ``|.|`` the Euclidean norm):

- ``von_mises`` (metal; PhysGaussian ``von_mises_return_mapping``): yield
  when ``|eps^| > tau_Y / (2 mu)``, project ``eps -= dg eps^/|eps^|`` with
  ``dg = |eps^| - tau_Y / (2 mu)``; hardening
  ``tau_Y = yield_stress + (hardening 2 mu xi - softening) ep`` with ``ep``
  the accumulated ``dg``; Hencky stress. ``yield_stress = 0`` is perfectly
  plastic (only the volume change is elastic).
- ``plasticine`` (PhysGaussian ``..._with_damage``): the same return map with
  softening; a particle whose yield stress reaches 0 is damaged (no stress,
  no further return map) from the substep whose flow brings it there on
  (as PhysGaussian); fixed-corotated stress on ``F_e``.
- ``drucker_prager`` (sand; Klar et al. 2016): with
  ``alpha = sqrt(2/3) 2 sin(phi) / (3 - sin(phi))``,
  ``dg = |eps^| + (3 lam + 2 mu) / (2 mu) tr(eps) alpha``:
  ``tr(eps) > 0`` projects to the tip (``eps = 0``, cohesionless),
  ``dg <= 0`` is elastic, otherwise ``eps -= dg eps^/|eps^|``. Hardening
  ``phi(q) = friction_angle + (h1 q - h3) exp(-h2 q)`` [deg] with ``q`` the
  accumulated plastic strain (``q += dg``, or ``|eps|`` at the tip). Hencky
  stress. Tampubolon et al. (2017): with ``dp_volume_correction`` the trial
  strain is first shifted by ``log(Jp) / 3`` (the log-volume stored by
  earlier apex projections; ``Jp <- exp(tr eps)`` at the apex, 1 elsewhere),
  and ``dp_cohesion`` ``c`` moves the apex to ``eps = c``: the map acts on
  ``eps - c`` and adds ``c`` back.
- ``snow`` (Stomakhin et al. 2013): singular values clamped to
  ``[1 - theta_c, 1 + theta_s]``, ``Jp *= J_tr / J_e``; fixed-corotated
  stress with ``mu, lam`` scaled by ``h = exp(xi (1 - Jp))`` (clamped to
  [0.1, 5] as Taichi's mpm99 / mpm128 examples do, so a crushed particle
  cannot make the step unstable; the time step does not count that factor:
  at ``h = 5`` the default Courant number 0.35 is 0.78 for that particle).
- ``foam`` (PhysGaussian ``viscoplasticity_return_mapping_with_StVK``):
  ``s = 2 mu eps^``, ``y = |s| - sqrt(2/3) tau_Y``; if ``y > 0``:
  ``|s_new| = |s| - y / (1 + eta_p / (2 mu_hat dt))`` with
  ``mu_hat = mu tr(b) / 3``, ``b = diag(s_i^2)``. Hencky stress.
- ``bingham`` (Bingham plastic; ``yield_stress`` the *shear* yield stress
  ``tau_0`` and ``viscosity`` the plastic viscosity ``eta_p`` a rheometer
  gives): the same regularised flow in shear terms, yield when
  ``|s| > sqrt(2) tau_0`` and ``|s_new| = |s| - y / (1 + eta_p / (mu dt))``:
  elastic (stiffness ``mu``) below the yield stress; in steady simple shear
  each step ends at ``tau_xy = tau_0 + eta_p gamma_dot``, Bingham's law (up
  to ``(tau / mu)^2``: 3e-3 at ``tau / mu = 0.05``).
  Hencky stress (bulk modulus ``lam + 2 mu / 3``).
- ``newtonian`` (weakly compressible fluid): ``F_e = J^{1/3} I`` (no shear
  memory), Tait pressure ``p = K (J^{-7} - 1) / 7`` with
  ``K = E / (3 (1 - 2 nu))``, viscous stress from the velocity gradient
  ``C``: ``tau = -J p I + J eta (C + C^T - 2/3 tr(C) I)``.
- ``rigid``: no stress (rigid particles move with their body, solver.py).

Kelvin-Voigt damping (``SimConfig.solid_viscosity``): the solids'
``viscosity`` adds :func:`kelvin_voigt`'s dashpot stress to their own.

Singular values are floored at 0.01 inside the logarithms (PhysGaussian does
the same "to prevent NaN in extreme cases") and ``J`` at 1e-3 in ``log J``
(``safe_J``), so every branch is finite for every particle: several models
are blended with ``jnp.where`` and a NaN in an unused branch would poison
the gradient.
"""

from __future__ import annotations

import functools
import math

import jax
import jax.numpy as jnp

from physsplat_jax import platforms
from physsplat_jax.mpm import linalg as la
from physsplat_jax.mpm import transfer
from physsplat_jax.mpm.base import lame
from physsplat_jax.mpm.models import KELVIN_VOIGT_MODELS
from physsplat_jax.mpm.models import MODEL_PARAMS

SVD_MODELS = ('stvk', 'von_mises', 'plasticine', 'drucker_prager', 'snow',
              'foam', 'bingham')
# Elastic models with a closed form (polar decomposition, F F^T) that also
# have a spectral form: next to an SVD model (one blended update) they use
# its SVD instead of a second decomposition of their own.
SPECTRAL_ELASTIC = ('fixed_corotated', 'neo_hookean')
# Models whose update returns the plastic state (Jp, ep) as it came.
NO_PLASTIC_STATE = ('fixed_corotated', 'neo_hookean', 'stvk', 'newtonian',
                    'rigid')
_SIG_FLOOR = 1e-2
_J_FLOOR = 1e-3
_TAIT_GAMMA = 7.0
_SNOW_H = (0.1, 5.0)
_SQRT23 = math.sqrt(2.0 / 3.0)
_SQRT2 = math.sqrt(2.0)
_N2_MIN = 1e-30  # |e^|^2 below this is zero deviatoric strain


def safe_J(J):
  """``J`` floored at 1e-3 where a logarithm or power of it is taken.

  A particle compressed below 1/1000 of its volume has blown up anyway; the
  floor keeps the blended branches finite (run() reports the blow-up).
  """
  return jnp.maximum(J, _J_FLOOR)


def _log_sig(s):
  """Hencky strain ``log(max(s, 0.01))`` of a 3-tuple of singular values."""
  return tuple(jnp.log(jnp.maximum(x, _SIG_FLOOR)) for x in s)


def _norm3(v):
  """``sqrt(|v|^2 + tiny)``, with derivatives of every order finite at 0.

  The floor keeps the value and the first derivative finite at ``v = 0``
  (F = I), but the second derivative of the floored norm is ``1 / n`` and
  its third ``1 / n^3``, which overflow there (``jax.hessian`` of the von
  Mises family was NaN from rest). Below ``|v|^2 = 1e-30`` the norm is held
  constant instead (derivative 0, the least-norm subgradient of ``|v|`` at
  0); the value is the same bit for bit.
  """
  n2 = v[0] * v[0] + v[1] * v[1] + v[2] * v[2]
  tiny = jnp.finfo(n2.dtype).tiny
  far = n2 > _N2_MIN
  return jnp.where(far, jnp.sqrt(jnp.where(far, n2, 1.0) + tiny),
                   jnp.sqrt(jax.lax.stop_gradient(n2) + tiny))


def _dev(e):
  tr = e[0] + e[1] + e[2]
  eh = tuple(x - tr / 3.0 for x in e)
  return tr, eh, _norm3(eh)


def _hencky_k(e, mu, lam):
  tr = e[0] + e[1] + e[2]
  return tuple(2.0 * mu * x + lam * tr for x in e)


def _fcr_k(s, mu, lam):
  """Principal Kirchhoff stress of fixed corotated, ``F = U diag(s) V^T``."""
  J = s[0] * s[1] * s[2]
  return tuple(2.0 * mu * (x - 1.0) * x + lam * J * (J - 1.0) for x in s)


def _fixed_corotated(s, p):
  return s, _fcr_k(s, p['mu'], p['lam']), {'Jp': p['Jp'], 'ep': p['ep']}


def _neo_hookean(s, p):
  # tau = mu (F F^T - I) + lam log(J) I = U diag(mu (s^2 - 1) + lam log J) U^T
  log_j = jnp.log(safe_J(s[0] * s[1] * s[2]))
  k = tuple(p['mu'] * (x * x - 1.0) + p['lam'] * log_j for x in s)
  return s, k, {'Jp': p['Jp'], 'ep': p['ep']}


def _exp3(e):
  return tuple(jnp.exp(x) for x in e)


# --- per-model spectral functions fn(s, p) -> (s_e, k, aux) ----------------
# p holds (N,) arrays: mu, lam, the model's parameters, Jp, ep, dt.


def _stvk(s, p):
  e = _log_sig(s)
  return s, _hencky_k(e, p['mu'], p['lam']), {'Jp': p['Jp'], 'ep': p['ep']}


def _vm_yield(p, softening, ep):
  """Yield stress after plastic strain ``ep`` (von_mises, plasticine)."""
  return p['yield_stress'] + (p['hardening'] * 2.0 * p['mu'] * p['xi']
                              - softening) * ep


def _von_mises_core(s, p, softening, damage):
  mu = p['mu']
  e = _log_sig(s)
  tr, eh, n = _dev(e)
  ys = _vm_yield(p, softening, p['ep'])
  # von_mises: yield_stress = 0 is perfectly plastic (only the volume is
  # elastic), as PhysGaussian's map; a negative yield would flip the
  # deviator. plasticine (damage): a particle whose yield has reached 0 is
  # damaged and flows no more.
  if not damage:
    ys = jnp.maximum(ys, 0.0)
  dg = n - ys / (2.0 * mu)
  plastic = (dg > 0.0) & (ys > 0.0) if damage else dg > 0.0
  f = jnp.where(plastic, dg / jnp.where(plastic, n, 1.0), 0.0)
  e_new = tuple(x - f * y for x, y in zip(e, eh))
  s_new = tuple(jnp.where(plastic, jnp.exp(x), y) for x, y in zip(e_new, s))
  ep = p['ep'] + jnp.where(plastic, dg, 0.0)
  return s_new, e_new, ep


def _von_mises(s, p):
  s_new, e_new, ep = _von_mises_core(s, p, 0.0, False)
  return s_new, _hencky_k(e_new, p['mu'], p['lam']), {'Jp': p['Jp'],
                                                      'ep': ep}


def _plasticine(s, p):
  s_new, _, ep = _von_mises_core(s, p, p['softening'], True)
  # Stress-free from the substep whose flow softens the yield to 0 (as
  # PhysGaussian zeroes mu and lam there); a damaged particle stays so.
  sound = _vm_yield(p, p['softening'], ep) > 0.0
  k = _fcr_k(s_new, p['mu'], p['lam'])
  k = tuple(jnp.where(sound, x, 0.0) for x in k)
  return s_new, k, {'Jp': p['Jp'], 'ep': ep}


def _drucker_prager(s, p):
  mu, lam, q = p['mu'], p['lam'], p['ep']
  phi = p['friction_angle'] + (p['dp_h1'] * q - p['dp_h3']) * jnp.exp(
    -p['dp_h2'] * q)
  sin_phi = jnp.sin(jnp.deg2rad(phi))
  alpha = _SQRT23 * 2.0 * sin_phi / (3.0 - sin_phi)
  e = _log_sig(s)
  # Volume correction (Tampubolon et al. 2017): log Jp holds the log-volume
  # gained by earlier apex projections; cohesion c moves the apex to
  # eps = c (1, 1, 1).
  vc = p['dp_volume_correction'] * jnp.log(safe_J(p['Jp']))
  coh = p['dp_cohesion']
  e = tuple(x + vc / 3.0 - coh for x in e)
  tr, eh, n = _dev(e)
  dg = n + (3.0 * lam + 2.0 * mu) / (2.0 * mu) * tr * alpha
  tip = tr > 0.0
  # F = I (zero strain) is the apex of the cone, where the return map has no
  # derivative; call it elastic (the floor in ``n`` would otherwise make
  # dg > 0 there and select the cone formula, whose derivative at the apex
  # is meaningless).
  cone = (~tip) & (dg > 0.0) & (jax.lax.stop_gradient(n * n) > _N2_MIN)
  f = jnp.where(cone, dg / jnp.where(cone, n, 1.0), 0.0)
  e_new = tuple(jnp.where(tip, 0.0, x - f * y) for x, y in zip(e, eh))
  e_norm = _norm3(e)
  dq = jnp.where(tip, e_norm, jnp.where(cone, dg, 0.0))
  # The correction is spent (log Jp -> 0) once the state is elastic or on
  # the cone (both keep the corrected trace); at the apex the whole trace
  # is stored.
  on = p['dp_volume_correction'] > 0.0
  Jp = jnp.where(on, jnp.where(tip, jnp.exp(tr), 1.0), p['Jp'])
  changed = tip | cone | (on & (vc != 0.0)) | (coh != 0.0)
  e_new = tuple(x + coh for x in e_new)
  s_new = tuple(jnp.where(changed, jnp.exp(x), y)
                for x, y in zip(e_new, s))
  return s_new, _hencky_k(e_new, mu, lam), {'Jp': Jp, 'ep': q + dq}


def _snow(s, p):
  lo = 1.0 - p['theta_c']
  hi = 1.0 + p['theta_s']
  s_new = tuple(jnp.clip(x, lo, hi) for x in s)
  J_tr = s[0] * s[1] * s[2]
  J_e = s_new[0] * s_new[1] * s_new[2]
  Jp = p['Jp'] * J_tr / J_e
  h = jnp.clip(jnp.exp(p['xi'] * (1.0 - Jp)), *_SNOW_H)
  k = _fcr_k(s_new, p['mu'] * h, p['lam'] * h)
  return s_new, k, {'Jp': Jp, 'ep': p['ep']}


def _viscoplastic(s, p, eta, bingham):
  """Regularised von Mises flow on the Hencky deviator ``s = 2 mu eps^``:
  foam as PhysGaussian (``|s| <= sqrt(2/3) tau_Y``, relaxation
  ``1 + eta / (2 mu_hat dt)``); ``bingham`` in shear terms (``|s| <=
  sqrt(2) tau_Y``, ``1 + eta / (mu dt)``), so that steady simple shear
  ends each step at ``tau_xy = tau_Y + eta gamma_dot`` (to second order in
  the elastic strain ``tau / mu``)."""
  mu = p['mu']
  e = _log_sig(s)
  tr, eh, n = _dev(e)
  s_norm = 2.0 * mu * n
  y = s_norm - (_SQRT2 if bingham else _SQRT23) * p['yield_stress']
  plastic = y > 0.0
  if bingham:
    relax = 1.0 + eta / (mu * p['dt'])
  else:
    sc = tuple(jnp.maximum(x, _SIG_FLOOR) for x in s)
    mu_hat = mu * (sc[0] * sc[0] + sc[1] * sc[1] + sc[2] * sc[2]) / 3.0
    relax = 1.0 + eta / (2.0 * mu_hat * p['dt'])
  new_norm = s_norm - y / relax
  # Divided only where plastic: at F = I, s_norm ~ 1e-150 and the second
  # derivative of the unused quotient would be 0 * inf.
  f = jnp.where(plastic, new_norm / jnp.where(plastic, s_norm, 1.0), 1.0)
  e_new = tuple(f * y_ + tr / 3.0 for y_ in eh)
  s_new = tuple(jnp.where(plastic, jnp.exp(x), y_) for x, y_ in zip(e_new, s))
  ep = p['ep'] + jnp.where(plastic, (1.0 - f) * n, 0.0)
  return s_new, _hencky_k(e_new, mu, p['lam']), {'Jp': p['Jp'], 'ep': ep}


def _foam(s, p):
  return _viscoplastic(s, p, p['plastic_viscosity'], False)


def _bingham(s, p):
  return _viscoplastic(s, p, p['viscosity'], True)


_SPECTRAL = {
  'fixed_corotated': _fixed_corotated, 'neo_hookean': _neo_hookean,
  'stvk': _stvk, 'von_mises': _von_mises, 'plasticine': _plasticine,
  'drucker_prager': _drucker_prager, 'snow': _snow, 'foam': _foam,
  'bingham': _bingham,
}
# (A solid's 'viscosity' is its Kelvin-Voigt stress and its maxwell_*
# fields its Maxwell branch, both added outside the map.)
_PARAMS = {m: tuple(f for f in MODEL_PARAMS[m] if m not in KELVIN_VOIGT_MODELS
                    or not (f == 'viscosity' or f.startswith('maxwell_')))
           for m in _SPECTRAL}


@functools.lru_cache(maxsize=None)
def _spectral_map(models: tuple[str, ...]):
  """One spectral map blending the SVD models in ``models`` (static)."""

  def fn(s, p):
    out = None
    for m in models:
      r = _SPECTRAL[m](s, p)
      if out is None:
        out = r
      else:
        sel = p['sel_' + m] > 0.5
        out = jax_tree_where(sel, r, out)
    return out

  return la.make_spectral_map(fn)


def jax_tree_where(c, a, b):
  """``where(c, a, b)`` leaf by leaf."""
  return jax.tree.map(lambda x, y: jnp.where(c, x, y), a, b)


def spectral_params(svd_models, models, model_id, mat, mu, lam, Jp, ep, dt):
  """The parameters ``p`` of the spectral maps ``fn(s, p)`` of
  ``svd_models`` (a sub-tuple of ``models``): the (N,) Lame parameters
  ``mu, lam`` (``mat.lame()``), the plastic state, the substep and each
  model's own fields of ``mat``, and with more than one model a 0/1
  selector ``sel_<model>`` per model from ``model_id`` (an index into
  ``models``)."""
  p = {'mu': mu, 'lam': lam, 'Jp': Jp, 'ep': ep, 'dt': jnp.full_like(mu, dt)}
  for m in svd_models:
    for f in _PARAMS[m]:
      p[f] = getattr(mat, f)
    if len(svd_models) > 1:
      p['sel_' + m] = (model_id == models.index(m)).astype(mu.dtype)
  return p


def kelvin_voigt(J, C, eta):
  """The Kelvin-Voigt (parallel dashpot) Kirchhoff stress of a solid,
  ``J eta (C + C^T - 2/3 tr(C) I)``: ``J`` (the particle's volume ratio,
  (N,)) times the Cauchy stress of a shear viscosity ``eta`` [Pa s] at
  the velocity gradient ``C`` (MLS-MPM's affine matrix). A rigid motion
  (``C`` skew-symmetric) and a uniform velocity give none, so it damps the
  deformation, not the motion (``SimConfig.grid_v_damping_scale`` slows
  both). Nested tuples in and out."""
  trC = la.trace(C)
  visc = la.add_diag(la.add(C, la.transpose(C)), -2.0 / 3.0 * trC)
  return la.scale(visc, J * eta)


def _solids(models, model_id):
  """(N,) bool, the particles of ``KELVIN_VOIGT_MODELS`` among ``models``
  (``model_id`` indexes it); None when every model is one."""
  kv = [k for k, m in enumerate(models) if m in KELVIN_VOIGT_MODELS]
  if len(kv) == len(models):
    return None
  return functools.reduce(jnp.logical_or, [model_id == k for k in kv],
                          jnp.zeros(model_id.shape, bool))


def _safe_ratio(a, b):
  """``a / b`` where ``b > 0``, else 0 (finite derivatives either way)."""
  ok = b > 0
  return jnp.where(ok, a / jnp.where(ok, b, 1.0), 0.0)


def _maxwell(s, p):
  """The Maxwell branch's viscous return map on the singular values of its
  trial ``F_N``: the Hencky strain's deviatoric part relaxes by
  ``eta / (eta + 2 mu dt)``, its trace by ``eta / (eta + 2 K dt)`` (backward
  Euler of ``d(eps)/dt = -(dev tau + 2/9 tr(tau) I) / eta``, Physics3D's
  update); Kirchhoff stress ``2 mu eps + lam tr(eps)`` of the relaxed
  strain."""
  mu, lam, eta, dt = p['mu'], p['lam'], p['eta'], p['dt']
  e = _log_sig(s)
  tr = e[0] + e[1] + e[2]
  a_d = _safe_ratio(eta, eta + 2.0 * mu * dt)
  a_v = _safe_ratio(eta, eta + 2.0 * (lam + 2.0 * mu / 3.0) * dt)
  e_new = tuple(a_d * (x - tr / 3.0) + a_v * tr / 3.0 for x in e)
  tr_new = a_v * tr
  return (tuple(jnp.exp(x) for x in e_new),
          tuple(2.0 * mu * x + lam * tr_new for x in e_new), {})


_MAXWELL_MAP = la.make_spectral_map(_maxwell)


def maxwell_update(models, model_id, F_N, mat, dt, zero_stress=None,
                   groups=()):
  """A solid's Maxwell branch (``SimConfig.maxwell``; Fang et al. 2019,
  Physics3D): a Hencky spring (``mat.maxwell_E``, ``maxwell_nu``) in series
  with a dashpot (``maxwell_viscosity`` ``eta``), beside the model's own
  stress. ``F_N`` (nested tuples) is the branch's trial deformation
  gradient; returns ``(F_N, tau_N)`` after the return map (:func:`_maxwell`),
  ``tau_N`` 0 for particles whose model is not a solid
  (``KELVIN_VOIGT_MODELS``: the fluids, sand, rigid), whose ``F_N`` is
  reset to I (advected alone it would drift without bound), or where
  ``zero_stress`` (rigid bodies). The deviatoric
  stress relaxes with time ``eta / (2 mu_N)``, the pressure with
  ``eta / (2 K_N)``; ``eta = 0`` is no branch, ``eta -> inf`` a spring.

  With ``groups`` (:func:`model_groups`: the particles sorted by model) the
  return map runs on the solids' slices only: one SVD per solid particle
  instead of one per particle, the same results.
  """
  n = F_N[0][0].shape[0]
  runs = _solid_runs(groups)
  if not groups or runs == [(0, n)]:
    return _maxwell_rows(models, model_id, F_N, mat, dt, zero_stress)
  parts, o = [], 0
  for a, b in runs + [(n, n)]:
    rows = lambda t, a=a, b=b: jax.tree.map(lambda q: q[a:b], t)  # noqa
    if a > o:  # not a solid: F_N = I, no stress
      like = F_N[0][0][o:a]
      parts.append((la.eye(like), la.zeros(like)))
    if b > a:
      parts.append(_maxwell_rows(
        (), None, rows(F_N), rows(mat), dt,
        None if zero_stress is None else zero_stress[a:b]))
    o = b
  return jax.tree.map(lambda *q: jnp.concatenate(q), *parts)


def _solid_runs(groups):
  """Contiguous ``[a, b)`` ranges of the ``KELVIN_VOIGT_MODELS`` slices of
  ``groups`` (``(model, start, end)``)."""
  runs = []
  for m, a, b in groups:
    if m not in KELVIN_VOIGT_MODELS:
      continue
    if runs and runs[-1][1] == a:
      runs[-1] = (runs[-1][0], b)
    else:
      runs.append((a, b))
  return runs


def _maxwell_rows(models, model_id, F_N, mat, dt, zero_stress):
  """:func:`maxwell_update` on the given rows (``models`` empty: all of
  them solids)."""
  mu, lam = lame(mat.maxwell_E, mat.maxwell_nu)
  p = {'mu': mu, 'lam': lam, 'eta': mat.maxwell_viscosity,
       'dt': jnp.full_like(mu, dt)}
  F_N, tau, _ = _MAXWELL_MAP(F_N, p)
  on = _solids(models, model_id) if models else None
  if on is not None:  # not a solid: F_N = I
    F_N = jax.tree.map(lambda f, i: jnp.where(on, f, i), F_N,
                       la.eye(on.astype(F_N[0][0].dtype)))
  if zero_stress is not None:
    on = ~zero_stress if on is None else on & ~zero_stress
  if on is not None:
    tau = tuple(tuple(jnp.where(on, t, 0.0) for t in row) for row in tau)
  return F_N, tau


def constitutive_update(models, model_id, F, C, Jp, ep, mat, dt,
                        zero_stress=None, solid_viscosity=False):
  """Return mapping and Kirchhoff stress for all models present.

  Args:
    models: static tuple of canonical model names (``SimConfig.models``).
    model_id: (N,) int32 index into ``models`` (unused with one model).
    F: nested-tuple trial deformation gradients.
    C: nested-tuple affine velocity matrices [1/s] (fluid viscosity).
    Jp, ep: (N,) plastic state.
    mat: ``Materials`` (leaves (N,)).
    dt: substep [s] (python float).
    zero_stress: optional (N,) bool, particles without stress (rigid).
    solid_viscosity: add :func:`kelvin_voigt` with ``mat.viscosity`` to the
      stress of the ``KELVIN_VOIGT_MODELS`` (``SimConfig.solid_viscosity``).

  Returns:
    ``(F_e, Jp, ep, tau)``; F_e and tau nested tuples.
  """
  mu, lam = mat.lame()
  single = len(models) == 1
  Jp_in = Jp

  def pick(results):
    """Blend per-model results by model id (static list)."""
    if single:
      return results[0][1]
    out = results[0][1]
    for k, r in results[1:]:
      out = jax_tree_where(model_id == k, r, out)
    return out

  results = []
  svd_models = tuple(m for m in models if m in SVD_MODELS)
  if svd_models:
    # The elastic closed forms join the SVD models' blended update: one
    # decomposition per particle, and a shorter program (its compile time
    # grows faster than its length on a GPU).
    svd_models = tuple(m for m in models
                       if m in SVD_MODELS or m in SPECTRAL_ELASTIC)
  if svd_models:
    p = spectral_params(svd_models, models, model_id, mat, mu, lam, Jp, ep,
                        dt)
    Fe, tau, aux = _spectral_map(svd_models)(F, p)
    r = (Fe, aux['Jp'], aux['ep'], tau)
    for m in svd_models:
      # An elastic model keeps F itself, not its reconstruction U s V^T.
      results.append((models.index(m), (F,) + r[1:] if m in SPECTRAL_ELASTIC
                      else r))
  for k, m in enumerate(models):
    if m in svd_models:
      continue
    if m == 'fixed_corotated':
      R = la.polar_mat(F)
      J = la.det(F)
      t = la.matmul_t(la.scale(la.sub(F, R), 2.0 * mu), F)
      tau = la.add_diag(t, lam * J * (J - 1.0))
      results.append((k, (F, Jp, ep, tau)))
    elif m == 'neo_hookean':
      J = la.det(F)
      t = la.scale(la.matmul_t(F, F), mu)
      tau = la.add_diag(t, -mu + lam * jnp.log(safe_J(J)))
      results.append((k, (F, Jp, ep, tau)))
    elif m == 'newtonian':
      J = safe_J(la.det(F))
      Jc = jnp.cbrt(J)
      z = jnp.zeros_like(J)
      Fe = ((Jc, z, z), (z, Jc, z), (z, z, Jc))
      K = mat.E / (3.0 * (1.0 - 2.0 * mat.nu))
      pres = K / _TAIT_GAMMA * (J ** (-_TAIT_GAMMA) - 1.0)
      eta = mat.viscosity
      trC = la.trace(C)
      visc = la.add(C, la.transpose(C))
      visc = la.add_diag(visc, -2.0 / 3.0 * trC)
      tau = la.add_diag(la.scale(visc, J * eta), -J * pres)
      results.append((k, (Fe, Jp, ep, tau)))
    elif m == 'rigid':
      results.append((k, (F, Jp, ep, la.zeros(Jp))))
    else:
      raise ValueError(f'unknown model {m!r}')
  results.sort(key=lambda r: r[0])
  Fe, Jp, ep, tau = pick(results)
  if solid_viscosity and any(m in KELVIN_VOIGT_MODELS for m in models):
    eta = mat.viscosity
    on = _solids(models, model_id)
    if on is not None:
      eta = jnp.where(on, eta, 0.0)
    # The volume ratio of the whole deformation: the trial F's, whose
    # plastic flow keeps the volume except snow's, which Jp records.
    J = safe_J(la.det(F))
    if 'snow' in models:
      J = J * (Jp_in if single else jnp.where(
        model_id == models.index('snow'), Jp_in, 1.0))
    tau = la.add(tau, kelvin_voigt(J, C, eta))
  if zero_stress is not None:
    tau = tuple(tuple(jnp.where(zero_stress, 0.0, t) for t in row)
                for row in tau)
  return Fe, Jp, ep, tau


def model_groups(config) -> tuple[tuple[str, int, int], ...]:
  """``(model, start, end)`` particle slices after the frame's model sort
  (``config`` an ``mpm.SimConfig``; empty without ``config.model_counts``;
  models without particles left out)."""
  if config.model_counts is None:
    return ()
  out, a = [], 0
  for m, c in zip(config.models, config.model_counts):
    if c:
      out.append((m, a, a + c))
    a += c
  return tuple(out)


def constitutive_slices(config, merge: bool):
  """``(models, first_model_index, start, end)`` per constitutive update of
  a substep with ``config.model_counts`` (empty without).

  ``merge=False``: one slice per model with particles. ``merge=True``:
  consecutive slices whose models have a spectral form (the SVD models and
  ``SPECTRAL_ELASTIC``), with at least one SVD model among them, become
  one slice with one blended update (one SVD for them all; their
  ``model_id`` minus ``first_model_index`` indexes ``models``). On a GPU
  that program is shorter: the tabletop's MPM frame compiled for an H100
  in ~12 s instead of ~17 s, with one kernel per substep fewer
  (docs/benchmarks.md).
  """
  spectral = SVD_MODELS + SPECTRAL_ELASTIC
  groups = model_groups(config)
  runs = []  # [first model index, last model index, start, end]
  for m, a, b in groups:
    k = config.models.index(m)
    if (merge and runs and runs[-1][3] == a
        and all(q in spectral for q in config.models[runs[-1][0]:k + 1])):
      runs[-1][1], runs[-1][3] = k, b
    else:
      runs.append([k, k, a, b])
  out = []
  for k0, k1, a, b in runs:
    ms = tuple(config.models[k0:k1 + 1])
    if k1 > k0 and not any(q in SVD_MODELS for q in ms):
      # Elastic closed forms only: cheaper apart than through an SVD.
      out.extend(((m,), config.models.index(m), a1, b1)
                 for m, a1, b1 in groups if a <= a1 < b)
    else:
      out.append((ms, k0, a, b))
  return tuple(out)


def constitute_slices(slices, dt, F, C, Jpep, mat, solid_viscosity=False):
  """``constitutive.constitutive_update`` on each slice of
  ``constitutive_slices`` (nested-tuple ``F``, ``C``; the particles sorted
  by model): ``(F_e, Jpep, tau)``, ``F_e`` and ``tau`` concatenated.

  ``Jpep`` is the (2, N) plastic state ``(Jp, ep)``; only the slices of
  models that change it (not :data:`NO_PLASTIC_STATE`) are written into it
  (``lax.dynamic_update_slice``). In a loop XLA updates the carried array
  in place then, where a concatenation of all slices becomes a new array
  and a copy into the carry (one kernel per substep fewer on a GPU).
  """
  parts = []
  out = Jpep
  for models, k0, a, b in slices:
    rows = lambda t, a=a, b=b: jax.tree.map(lambda q: q[a:b], t)  # noqa
    ids = None if len(models) == 1 else mat.model_id[a:b] - k0
    Fe, Jp, ep, tau = constitutive_update(
      models, ids, rows(F), rows(C), Jpep[0, a:b], Jpep[1, a:b], rows(mat),
      dt, solid_viscosity=solid_viscosity)
    parts.append((Fe, tau))
    if not all(m in NO_PLASTIC_STATE for m in models):
      out = jax.lax.dynamic_update_slice(out, jnp.stack([Jp, ep]), (0, a))
  Fe, tau = jax.tree.map(lambda *q: jnp.concatenate(q), *parts)
  return Fe, out, tau


def constitute_all(models, dt, F, C, Jpep, mat, zero_stress=None,
                   solid_viscosity=False):
  """:func:`constitutive_update` of every model in ``models`` on every
  particle (``mat.model_id`` picks), with the plastic state as the (2, N)
  ``Jpep`` (passed through where no model changes it): ``(F_e, Jpep,
  tau)``. The form of a scene without ``model_counts``."""
  Fe, Jp, ep, tau = constitutive_update(models, mat.model_id, F, C, Jpep[0],
                                        Jpep[1], mat, dt,
                                        zero_stress=zero_stress,
                                        solid_viscosity=solid_viscosity)
  if not all(m in NO_PLASTIC_STATE for m in models):
    Jpep = jnp.stack([Jp, ep])
  return Fe, Jpep, tau


def _split_over_devices(a) -> bool:
  """Whether ``a`` varies over a manual mesh axis (inside ``shard_map``);
  the attribute's name differs across JAX versions."""
  aval = jax.typeof(a)
  mat = getattr(aval, 'manual_axis_type', None)
  varying = (getattr(mat, 'varying', None) if mat is not None
             else getattr(aval, 'vma', None))
  return bool(varying)


def make_update(config):
  """``update(FC, Jpep, body_id, mat) -> (F_e, Jpep, tau)``: the
  return-mapped state and Kirchhoff stress of a substep (the carried
  (18, N) ``FC``, F's nine rows then C's, row-major, in; nested-tuple
  matrices out; ``Jpep`` the (2, N) plastic state ``(Jp, ep)``, passed
  through where no model changes it), computed once into memory
  (``transfer.materialize``):
  XLA:CPU otherwise fuses the whole stress computation into the scatter's
  per-contribution loop and recomputes it for each of the 108
  contributions of a particle.

  With ``config.model_counts`` the particles are sorted by model and each
  model runs on its own slice only (on a GPU, the models with a spectral
  form share one: :func:`constitutive_slices`); without, every model runs
  on every particle and ``body_id >= 0`` marks the stress-free rigid ones.
  On a CUDA GPU (``config.constitutive_kernel``, default 'auto') the
  update is one Pallas kernel (``mpm.pallas_constitutive``), whose program
  compiles in a fraction of the time XLA's fusion passes take over the
  same chain; same values, same gradients. Particles split over devices
  (``shard_map``) keep the pure-JAX update.
  """
  # (Imported here: the kernel's module imports this one.)
  from physsplat_jax.mpm import pallas_constitutive  # noqa: PLC0415

  dt, models = config.dt, config.models
  visc = config.solid_viscosity
  has_bodies = config.num_bodies > 0
  groups = model_groups(config)
  single = constitutive_slices(config, merge=False)
  merged = constitutive_slices(config, merge=True)

  def with_jax(FC, Jpep, body_id, mat):
    F, C = transfer.materialize_cotangent(
      (la.rows_mat(FC, 0), la.rows_mat(FC, 9)))
    if groups:
      args = (F, C, Jpep, mat)
      if merged == single:
        return constitute_slices(single, dt, *args, solid_viscosity=visc)
      # A slice per model on the CPU (an elastic model's closed form is
      # cheaper than an SVD); elsewhere one blended slice, whose program
      # compiles faster (constitutive_slices).
      return platforms.platform_dependent(
        *args, cpu=functools.partial(constitute_slices, single, dt,
                                     solid_viscosity=visc),
        default=functools.partial(constitute_slices, merged, dt,
                                  solid_viscosity=visc))
    return constitute_all(models, dt, F, C, Jpep, mat,
                          body_id >= 0 if has_bodies else None,
                          solid_viscosity=visc)

  def with_kernel(FC, Jpep, body_id, mat, interpret):
    n = FC.shape[-1]
    # (The Maxwell branch is computed beside the kernel: not loaded there.)
    mat = mat.replace(maxwell_E=None, maxwell_nu=None, maxwell_viscosity=None)
    slices = merged if groups else ((models, 0, 0, n),)
    body = body_id if (has_bodies and not groups) else None
    Fe, Jpep, tau = pallas_constitutive.constitute(
      slices, dt, (FC, 0), (FC, 9), Jpep, mat, body, interpret=interpret,
      solid_viscosity=visc)
    return la.to_mat(Fe), Jpep, la.to_mat(tau)

  kernel = config.constitutive_kernel

  def update(FC, Jpep, body_id, mat):
    args = (FC, Jpep, body_id, mat)
    compiled = functools.partial(with_kernel, interpret=False)
    if kernel == 'jax' or _split_over_devices(FC):
      # (Particles split over devices inside shard_map: the pure-JAX
      # update; the kernel's interpreted form does not run there.)
      out = with_jax(*args)
    elif kernel == 'pallas':  # interpreted off a CUDA GPU (slow: tests)
      out = platforms.platform_dependent(
        *args, cuda=compiled,
        default=functools.partial(with_kernel, interpret=True))
    elif pallas_constitutive.available(config.dtype):  # 'auto'
      out = platforms.platform_dependent(*args, cuda=compiled, default=with_jax)
    else:  # 'auto' where this JAX cannot build the kernel
      out = with_jax(*args)
    return transfer.materialize(out)

  return update
