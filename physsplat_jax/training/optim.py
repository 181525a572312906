"""A host-side optimiser for :func:`.simtrain.fit_material`.

:func:`lbfgs` runs SciPy's L-BFGS-B on the host around one compiled value
and gradient, for fits of a few parameters through a whole rollout, where
compiling the program is what costs.
"""

from __future__ import annotations

from typing import Callable

import jax.numpy as jnp
import numpy as np
from jax import flatten_util
import scipy


def lbfgs(value_and_grad: Callable, theta, num_steps: int,
          record: Callable, diverged: Callable):
  """SciPy's L-BFGS-B on the host around one compiled ``value_and_grad``.

  (optax.lbfgs's step holds the rollout and its gradient three times, in
  its stored value's cond and its zoom search's two branches: on a 2-core
  CPU the test fit's step compiled in 38 s, this one program in 11 s.)
  Runs ``num_steps`` iterations unless the line search can lower the loss
  no further; ``record(step, loss before it, theta after it)``. Returns
  (theta, the final loss).
  """
  x0, unravel = flatten_util.ravel_pytree(theta)
  now = {'step': 0, 'loss': None}

  def fun(x):
    loss, g = value_and_grad(unravel(jnp.asarray(x, x0.dtype)))
    loss = float(loss)
    g = np.asarray(flatten_util.ravel_pytree(g)[0], np.float64)
    if not (np.isfinite(loss) and np.all(np.isfinite(g))):
      raise diverged(now['step'])
    if now['loss'] is None:  # (the first call is at x0)
      now['loss'] = loss
    return loss, g

  def callback(intermediate_result):
    record(now['step'], now['loss'],
           unravel(jnp.asarray(intermediate_result.x, x0.dtype)))
    now['step'] += 1
    now['loss'] = float(intermediate_result.fun)

  res = scipy.optimize.minimize(
    fun, np.asarray(x0, np.float64), jac=True, method='L-BFGS-B',
    callback=callback,
    options={'maxiter': num_steps, 'ftol': 0.0, 'gtol': 0.0})
  return unravel(jnp.asarray(res.x, x0.dtype)), float(res.fun)
