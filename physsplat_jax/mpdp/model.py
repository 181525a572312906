"""MPDP point network: per-point multiplicative material fields.

PhysSplat's Material Property Distribution Prediction (MPDP) turns the
MLLM's *mean* properties of an object (E, nu, rho, constitutive model) into a
per-point distribution: a network predicts a field ``m(x)`` normalised by its
mean, and the per-point value is ``mean * m(x)`` (PhysSplat, ICCV 2025,
Sec. 3.3). This module is that network, written as a small PointNet/DGCNN
(Qi et al. 2017; Wang et al. 2019) in Flax linen:

  h_i   = MLP(p_i)                                  shared per-point MLP
  e_i   = max_{j in kNN(i)} MLP([h_i, h_j - h_i, p_j - p_i])   EdgeConv
  g     = max_{i valid} Dense([h_i, e_i])           global feature
  c     = MLP(means)                                condition on the MLLM means
  raw_i = MLP([h_i, e_i, g, c, p_i])  (3 channels: E, nu, rho)
  l_i   = r * tanh(raw_i / r)                  bounded logits, r per channel
  m_i   = exp(l_i) / mean_{j valid} exp(l_j)         mean exactly 1

``p`` are the object's points centred on their (masked) mean and scaled so the
farthest valid point is at radius 1, so the field is invariant to
translation and scale. The kNN is static-shaped and exact, padded points are
never chosen (:mod:`physsplat_jax.mpdp.knn`: brute force on small objects,
sorted cell lists with O(N k) memory on large ones; the same neighbours
either way), and above ``network.EDGE_CHUNK`` points the EdgeConv runs in
chunks, so memory grows linearly with N. The network itself
(:class:`PointNet`) is in :mod:`physsplat_jax.mpdp.network`, imported when
it is first traced (Flax is not imported with the package).
The last layer is zero-initialised, so an untrained network gives the
mean-only baseline ``m = 1`` exactly.

Normalisation: ``m_i = N_valid * w_i / sum_valid w``, ``w = exp(l - max l)``;
the mean over valid points is 1 up to float rounding (|mean - 1| <= ~1e-7 in
f32). With per-point ``weights`` a (volumes, as the pipeline passes) it is
``m_i = w_i sum a / sum a w``: the volume-weighted mean is 1, so an object's
mass and mean stiffness are the MLLM's however its driving particles are
spaced (a plain mean over PGAS's denser-where-soft particles was off by up
to 4.5 % in E). Padded points get ``m = 1`` and never affect valid outputs.

Poisson's ratio: ``nu_i = clip(nu_mean * m_nu_i, 0, NU_MAX)`` with
``NU_MAX = 0.49`` in :func:`material_from_field` (clipping keeps nu in
[0, 0.5) whatever the mean; the nu field's logit range is small, log 1.5, so
clipping only bites for means near 0.5).

The physics only ever sees a params pytree: ``predict(params, points,
means, mask)``.
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np

from physsplat_jax.errors import PhysSplatError
from physsplat_jax.mpdp import knn as knn_lib
from physsplat_jax.mpm.models import CANONICAL_MODELS
from physsplat_jax.types import device_array
from physsplat_jax.values import is_int, is_real  # noqa: F401 (public)
from physsplat_jax.mpdp.knn import knn_indices as knn_indices  # noqa: F401


class MPDPError(PhysSplatError, ValueError):
  """Bad input to the MPDP network or its weights (configs, shapes, model
  names, files); the message names it and the fix."""


# Canonical constitutive-model names: the solver's (their order fixes the
# one-hot encoding of the shipped weights).
MODEL_NAMES = CANONICAL_MODELS
NUM_MODELS = len(MODEL_NAMES)
# log10 E, nu, log10 rho, model one-hot, rigid flag.
MEANS_DIM = 3 + NUM_MODELS + 1
NU_MAX = 0.49
# Channel order of the field.
FIELD_CHANNELS = ('E', 'nu', 'rho')


# Kinds of :func:`check_values`: name -> (test, what to give instead).
VALUE_KINDS = {
  'int': (is_int, 'an integer'),
  'int>=0': (lambda v: is_int(v) and v >= 0, 'an integer >= 0'),
  'int>=1': (lambda v: is_int(v) and v >= 1, 'an integer >= 1'),
  '>0': (lambda v: is_real(v) and v > 0, 'a finite number > 0'),
  '>=0': (lambda v: is_real(v) and v >= 0, 'a finite number >= 0'),
}


def check_values(owner: str, values, error: type | None = None) -> None:
  """Checks config values before any work.

  Args:
    owner: how the user names their section, e.g. ``'config.train'``.
    values: ``(name, value, kind)`` triples; ``kind`` is a key of
      :data:`VALUE_KINDS` or a ``(test, what to give)`` pair.
    error: the exception class raised (default :class:`MPDPError`).

  Raises:
    error: ``'<owner>.<name> = <value>; give <what>.'`` for the first value
      that is not of its kind.
  """
  for name, value, kind in values:
    test, want = VALUE_KINDS[kind] if isinstance(kind, str) else kind
    if not test(value):
      raise (error or MPDPError)(f'{owner}.{name} = {value!r}; give {want}.')


@dataclasses.dataclass(frozen=True)
class ModelConfig:
  """Static (hashable) architecture of the MPDP network.

  Attributes:
    features: widths of the shared per-point MLP.
    edge_features: width of the EdgeConv MLP; 0 disables EdgeConv.
    k_neighbors: kNN size of the EdgeConv (static), >= 1 (``edge_features
      = 0``, not ``k_neighbors = 0``, turns EdgeConv off).
    global_features: width of the max-pooled global feature.
    cond_features: width of the embedding of the mean properties.
    head_features: widths of the per-point output MLP.
    log_range: per-channel bound r of the logits (E, nu, rho): the field's
      max/min ratio is at most exp(2 r); three finite numbers > 0.

  Every width is an integer >= 1 (``edge_features`` >= 0); a bad field
  raises :class:`MPDPError` naming it when the config is made.
  """

  features: tuple[int, ...] = (64, 64)
  edge_features: int = 64
  k_neighbors: int = 8
  global_features: int = 128
  cond_features: int = 32
  head_features: tuple[int, ...] = (64, 64)
  log_range: tuple[float, float, float] = (3.0, 0.405, 0.693)

  def __post_init__(self):
    for k, size, what in (
        ('features', None, 'a list of layer widths (integers >= 1)'),
        ('head_features', None, 'a list of layer widths (integers >= 1)'),
        ('log_range', 3, 'three finite numbers > 0 (E, nu, rho)')):
      v = getattr(self, k)
      if not isinstance(v, (tuple, list)) or (size and len(v) != size):
        raise MPDPError(f'ModelConfig.{k} = {v!r}; give {what}.')
      object.__setattr__(self, k, tuple(v))
    if not (is_int(self.k_neighbors) and self.k_neighbors >= 1):
      raise MPDPError(
        f'ModelConfig.k_neighbors = {self.k_neighbors!r}; give an integer '
        '>= 1 (to turn EdgeConv off, set edge_features = 0).')
    check_values('ModelConfig', [
      *((f'features[{i}]', f, 'int>=1') for i, f in enumerate(
        self.features)),
      ('edge_features', self.edge_features, 'int>=0'),
      ('global_features', self.global_features, 'int>=1'),
      ('cond_features', self.cond_features, 'int>=1'),
      *((f'head_features[{i}]', f, 'int>=1') for i, f in enumerate(
        self.head_features)),
      *((f'log_range[{i}]', r, '>0') for i, r in enumerate(
        self.log_range))])

  @classmethod
  def from_dict(cls, d) -> 'ModelConfig':
    """Builds a config from a dict / ConfigDict (lists become tuples; a
    value of the wrong type raises :class:`MPDPError` naming the field)."""
    d = dict(d)
    unknown = set(d) - {f.name for f in dataclasses.fields(cls)}
    if unknown:
      raise MPDPError(
        f'Unknown MPDP model config fields {sorted(unknown)}; valid fields '
        f'are {[f.name for f in dataclasses.fields(cls)]}.'
      )
    return cls(**d)

  def to_dict(self) -> dict:
    return {k: list(v) if isinstance(v, tuple) else v
            for k, v in dataclasses.asdict(self).items()}


def encode_means(E, nu, rho, model='fixed_corotated', rigid=None):
  """Encodes an object's mean properties as the network's condition vector
  (host side, NumPy: concrete values, not traced ones; under ``jit`` pass
  the encoded vector in).

  Args:
    E: mean Young's modulus [Pa], > 0 (scalar or array).
    nu: mean Poisson's ratio in [0, 0.5).
    rho: mean density [kg/m^3], > 0.
    model: constitutive-model name (one of ``MODEL_NAMES``) or an int index,
      or a sequence of them matching the shape of ``E``.
    rigid: rigid flag; defaults to ``model == 'rigid'``.

  Returns:
    (..., MEANS_DIM) float32: [(log10 E - 6) / 2, (nu - 0.25) / 0.25,
    (log10 rho - 3) / 0.5, one-hot(model), rigid].

  Raises:
    ValueError: on non-positive/non-finite E or rho, nu outside [0, 0.5), or
      an unknown model name.
  """
  E = np.asarray(E, np.float64)
  nu = np.asarray(nu, np.float64)
  rho = np.asarray(rho, np.float64)
  if not np.all(np.isfinite(E)) or np.any(E <= 0):
    raise MPDPError(f'MPDP means: E must be finite and > 0 Pa, got {E}.')
  if not np.all(np.isfinite(rho)) or np.any(rho <= 0):
    raise MPDPError(
      f'MPDP means: rho must be finite and > 0 kg/m^3, got {rho}.')
  if not np.all(np.isfinite(nu)) or np.any(nu < 0) or np.any(nu >= 0.5):
    raise MPDPError(
      f'MPDP means: nu must be in [0, 0.5), got {nu}; clamp it (e.g. 0.49) '
      'for nearly incompressible materials.')
  shape = np.broadcast_shapes(E.shape, nu.shape, rho.shape)
  models = np.asarray(model, dtype=object).reshape(-1)
  ids = []
  for m in models:
    if isinstance(m, (int, np.integer)):
      if not 0 <= int(m) < NUM_MODELS:
        raise MPDPError(
          f'MPDP means: model index {m} not in 0..{NUM_MODELS - 1}.')
      ids.append(int(m))
    elif m in MODEL_NAMES:
      ids.append(MODEL_NAMES.index(m))
    else:
      raise MPDPError(
        f'MPDP means: unknown constitutive model {m!r}; use one of '
        f'{MODEL_NAMES}.')
  ids = np.broadcast_to(np.asarray(ids).reshape(
    np.asarray(model, dtype=object).shape), shape)
  if rigid is None:
    rigid = ids == MODEL_NAMES.index('rigid')
  rigid = np.broadcast_to(np.asarray(rigid, np.float64), shape)
  onehot = np.eye(NUM_MODELS)[ids]
  out = np.concatenate([
    ((np.log10(E) - 6.0) / 2.0)[..., None] * np.ones(shape + (1,)),
    ((nu - 0.25) / 0.25)[..., None] * np.ones(shape + (1,)),
    ((np.log10(rho) - 3.0) / 0.5)[..., None] * np.ones(shape + (1,)),
    onehot, rigid[..., None],
  ], axis=-1)
  return device_array(out, jnp.float32)


def normalize_points(points, mask):
  """Centres points on their masked mean and scales the farthest to radius 1.

  Args:
    points: (N, 3) positions [any length unit].
    mask: (N,) bool, True for valid points.

  Returns:
    (N, 3) normalised points (padded rows are zeroed).
  """
  w = mask.astype(points.dtype)
  n = jnp.maximum(jnp.sum(w), 1.0)
  centre = jnp.sum(points * w[:, None], axis=0) / n
  p = (points - centre) * w[:, None]
  r = jnp.sqrt(jnp.max(jnp.sum(p * p, axis=-1)))
  # A single point (r = 0) stays at the origin instead of dividing by zero.
  r = jnp.where(r > 0, r, 1.0)
  return p / r


def normalize_field(logits, mask, weights=None):
  """Turns logits into a positive field with masked mean exactly 1.

  Args:
    logits: (N, C) logits.
    mask: (N,) bool validity.
    weights: optional (N,) weights >= 0 of the mean (e.g. the points'
      volumes, so that an object's volume-weighted mean property, and its
      mass, is the given mean however its points are spaced); default 1.

  Returns:
    (N, C) field; the (weighted) mean over valid rows is 1 per channel,
    padded rows are 1.
  """
  m = mask[:, None]
  lmax = jnp.max(jnp.where(m, logits, -jnp.inf), axis=0)
  lmax = jax.lax.stop_gradient(jnp.where(jnp.isfinite(lmax), lmax, 0.0))
  w = jnp.where(m, jnp.exp(jnp.where(m, logits, 0.0) - lmax), 0.0)
  n = jnp.maximum(jnp.sum(mask.astype(logits.dtype)), 1.0)
  field = w * (n / jnp.sum(w, axis=0))
  if weights is not None:
    a = jnp.where(mask, weights.astype(logits.dtype), 0.0)[:, None]
    # Scaled to a largest weight of 1 (the field does not depend on the
    # scale): volumes of 1e-25 m^3 underflowed the sums in float32.
    top = jax.lax.stop_gradient(jnp.max(a))
    a = a / jnp.where(top > 0, top, 1.0)
    den = jnp.sum(a * w, axis=0)
    # (an object whose weights are all 0 keeps the plain field, no 0 / 0)
    ok = den > 0
    field = jnp.where(ok, w * (jnp.sum(a) / jnp.where(ok, den, 1.0)), field)
  return jnp.where(m, field, 1.0)


def _check_inputs(points, means, mask):
  if points.ndim not in (2, 3) or points.shape[-1] != 3:
    raise MPDPError(
      f'MPDP predict: points must have shape (N, 3) or (B, N, 3), got '
      f'{points.shape}.')
  if means.shape[-1] != MEANS_DIM or means.ndim != points.ndim - 1:
    raise MPDPError(
      f'MPDP predict: means must have shape ({MEANS_DIM},) (or (B, '
      f'{MEANS_DIM}) for batched points); got {means.shape}. Build it with '
      'physsplat_jax.mpdp.encode_means(E, nu, rho, model).')
  if mask is not None and mask.shape != points.shape[:-1]:
    raise MPDPError(
      f'MPDP predict: mask shape {mask.shape} must equal points.shape[:-1] '
      f'= {points.shape[:-1]}.')


def make_predict(config: ModelConfig = ModelConfig(),
                 knn_method: str = 'auto'):
  """Returns ``predict_fn(params, points, means, mask=None, weights=None)
  -> (N, 3)``.

  ``predict_fn`` normalises the points, runs :class:`PointNet` and returns
  the field (E, nu, rho multipliers) with masked mean exactly 1, weighted
  by ``weights`` if given (:func:`normalize_field`; the pipeline passes the
  driving particles' volumes). Leading batch dimension is supported:
  points (B, N, 3), means (B, MEANS_DIM), mask and weights (B, N).

  Args:
    config: the architecture.
    knn_method: EdgeConv neighbour search, 'auto' (brute force up to
      ``knn.BRUTE_MAX_POINTS`` points, else the cell grid), 'grid' or
      'brute'; the same weights give the same field with any of them.
  """
  if knn_method not in knn_lib.METHODS:
    raise MPDPError(f'make_predict: knn_method={knn_method!r}; use one of '
                    f'{knn_lib.METHODS}')

  def single(params, points, means, mask, weights):
    # Flax is imported when the network is first traced, not with the
    # package (a run whose MPDP program is stored never traces it).
    from physsplat_jax.mpdp import network  # noqa: PLC0415

    net = network.PointNet(config, knn_method=knn_method)
    p = normalize_points(points, mask)
    # Neighbours from the given points on an integer lattice: exact
    # distances, so float rounding (of the normalisation, of a backend's
    # arithmetic) cannot swap two equidistant neighbours, and one field
    # comes out on every backend and JAX version (docs/mpdp.md).
    logits = net.apply({'params': params}, p, means.astype(p.dtype), mask,
                       knn_lib.lattice_coordinates(points, mask))
    return normalize_field(logits, mask, weights)

  def predict_fn(params, points, means, mask=None, weights=None):
    points = jnp.asarray(points)
    means = jnp.asarray(means)
    _check_inputs(points, means, mask)
    if mask is None:
      mask = jnp.ones(points.shape[:-1], bool)
    mask = jnp.asarray(mask, bool)
    if weights is not None:
      weights = jnp.asarray(weights)
      if weights.shape != mask.shape:
        raise MPDPError(
          f'MPDP predict: weights shape {weights.shape} must equal '
          f'points.shape[:-1] = {mask.shape}.')
    if points.ndim == 3:
      return jax.vmap(single, (None, 0, 0, 0, 0 if weights is not None
                               else None))(params, points, means, mask,
                                           weights)
    return single(params, points, means, mask, weights)

  return predict_fn


def init_params(key, config: ModelConfig = ModelConfig(),
                num_points: int = 16):
  """Initial params pytree (the field is exactly 1 until trained)."""
  return _init_fn(config, num_points)(key)


@functools.lru_cache(maxsize=32)
def _init_fn(config: ModelConfig, num_points: int):
  """Flax's init of the network, jitted once per config in a process.

  Jitted: linen's eager init of this network takes seconds on a CPU. Kept:
  a new ``jax.jit`` of a new module's ``init`` on every call traced and
  compiled the network's forward pass again (0.9-1.8 s on the 2-core VM).
  """
  from physsplat_jax.mpdp import network  # noqa: PLC0415

  def init(key):
    p = jnp.zeros((num_points, 3))
    m = jnp.zeros((MEANS_DIM,))
    mask = jnp.ones((num_points,), bool)
    return network.PointNet(config).init(key, p, m, mask)['params']

  return jax.jit(init)


def param_shapes(config: ModelConfig = ModelConfig()) -> dict:
  """Shapes of the params of :class:`PointNet` for ``config``, without Flax.

  What :func:`init_params` gives (the tests compare the two), for checking
  weight files against their config without tracing the network:
  ``{'Dense_i': {'kernel': (in, out), 'bias': (out,)}}`` in layer order.
  """
  layers = []

  def mlp(width, features):
    for f in features:
      layers.append((width, f))
      width = f
    return width

  local = h = mlp(3, config.features)
  if config.edge_features > 0 and config.k_neighbors > 0:
    e = config.edge_features
    layers += [(2 * h + 3, e), (e, e)]
    local += e
  layers.append((local, config.global_features))
  c = mlp(MEANS_DIM, (config.cond_features, config.cond_features))
  z = mlp(local + config.global_features + c + 3, config.head_features)
  layers.append((z, 3))
  return {f'Dense_{i}': {'kernel': (a, b), 'bias': (b,)}
          for i, (a, b) in enumerate(layers)}


predict = make_predict(ModelConfig())
predict.__doc__ = (
  """Per-point multiplicative field of the default architecture.

  Args:
    params: params pytree (e.g. :func:`load_pretrained`).
    points: (N, 3) object points (any frame/scale; normalised inside), or
      (B, N, 3).
    means: (MEANS_DIM,) from :func:`encode_means`, or (B, MEANS_DIM).
    mask: optional (N,) / (B, N) bool validity for padded points.
    weights: optional (N,) / (B, N) weights >= 0 of the mean (volumes).

  Returns:
    (N, 3) multipliers for (E, nu, rho); masked (weighted) mean exactly 1,
    padded rows 1.
  """)


def material_from_field(field, E, nu, rho):
  """Per-point E, nu, rho = mean * field, with nu clipped to [0, NU_MAX].

  Args:
    field: (N, 3) multipliers from :func:`predict`.
    E, nu, rho: scalar means [Pa, -, kg/m^3] (may be traced).

  Returns:
    (E, nu, rho), each (N,).
  """
  return (E * field[:, 0], jnp.clip(nu * field[:, 1], 0.0, NU_MAX),
          rho * field[:, 2])
