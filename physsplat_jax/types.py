"""Shared pytree types: Gaussians, Camera, ObjectInfo, Scene.

Dimension letters used in docstrings: ``K`` Gaussians, ``N`` particles,
``B`` SH basis functions ``(d + 1)**2``, ``H W`` image, ``T`` frames.

Conventions (fixed for the whole package):
- Quaternions are ``wxyz`` (INRIA ``rot_0`` is ``w``) and stored raw; the
  activation normalises them.
- Log-scales, opacity logits and SH coefficients are stored pre-activation,
  exactly as in an INRIA 3DGS PLY: ``scale = exp(log_scale)``,
  ``opacity = sigmoid(logit)``, ``rgb_dc = 0.5 + C0 * sh[:, 0]``.
- SH coefficients are ``(K, B, 3)``: coefficient-major, channel last (the
  in-memory layout of the INRIA code; the PLY stores ``f_rest`` channel-major).
- Cameras are OpenCV/COLMAP: world-to-camera ``viewmat`` (4x4), camera axes
  +x right, +y down, +z forward; pixel centres at ``(j + 0.5, i + 0.5)``.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from physsplat_jax import struct
from physsplat_jax.errors import PhysSplatError


class DataError(PhysSplatError, ValueError):
  """Gaussians, cameras or scene arrays of the wrong shape or value; the
  message names the field."""


class UnknownObjectError(PhysSplatError, KeyError):
  """A scene object asked for by a name the scene does not have."""

  def __str__(self) -> str:  # the message, not KeyError's repr of it
    return str(self.args[0]) if self.args else ''


Array = jax.Array
ArrayLike = Any


def is_host_data(x) -> bool:
  """Whether ``x`` is host data (NumPy arrays, Python values), neither a
  JAX array nor a tracer."""
  return not isinstance(x, (jax.Array, jax.core.Tracer))


def device_array(x, dtype=None) -> Array:
  """``jnp.asarray(x, dtype)``, without compiling anything for host data.

  ``jnp.asarray`` of a NumPy array runs a small compiled program per shape
  and dtype (jax 0.10: ``jit(stage)``, or ``convert_element_type`` for a
  cast), ~14 ms each on a 2-core CPU and a persistent-cache look-up in
  every later process; preparing a scene made ~140 of them. Host data
  (NumPy arrays, lists, scalars) is converted in NumPy and transferred with
  ``jax.device_put`` (same dtype rules: float64 becomes float32 unless x64
  is on); JAX arrays and tracers go through ``jnp.asarray``.
  """
  if not is_host_data(x):
    return jnp.asarray(x, dtype)
  return jax.device_put(np.asarray(x, None if dtype is None
                                   else jnp.dtype(dtype)))


def in_host_memory(x) -> bool:
  """Whether ``x`` is concrete and in host memory (NumPy data, or a JAX
  array on CPU devices), so that NumPy reads it without a transfer."""
  if isinstance(x, jax.core.Tracer):
    return False
  if isinstance(x, jax.Array):
    return all(d.platform == 'cpu' for d in x.devices())
  return True


def sh_degree_from_bases(num_bases: int) -> int:
  """SH degree ``d`` from the number of basis functions ``(d + 1)**2``."""
  d = int(round(np.sqrt(num_bases))) - 1
  if (d + 1) ** 2 != num_bases or not 0 <= d <= 3:
    raise DataError(
      f'SH coefficient count {num_bases} is not (d+1)^2 for a degree d in '
      '0..3 (expected 1, 4, 9 or 16 per channel).'
    )
  return d


def nonfinite_rows(a) -> np.ndarray:
  """Indices of the rows of a concrete (K, ...) array holding a non-finite
  value (the test runs where the array lives; K booleans come back).
  Empty for K = 0 (the callers say what an empty set means to them)."""
  if np.shape(a)[0] == 0:
    return np.zeros(0, np.int64)
  if in_host_memory(a):
    x = np.asarray(a)
    return np.flatnonzero(~np.isfinite(x.reshape(len(x), -1)).all(axis=1))
  ok = jnp.isfinite(a).reshape(a.shape[0], -1).all(axis=1)
  return np.flatnonzero(~np.asarray(ok))


def rows_text(rows) -> str:
  """The first few of some row indices, for a message: '0, 1, 2, 3, 4, ...'."""
  shown = ', '.join(str(int(r)) for r in rows[:5])
  return shown + (', ...' if len(rows) > 5 else '')


def check_gaussians(g: Gaussians, where: str = 'gaussians', *,
                    finite: bool = True, sh: bool = True) -> int:
  """Checks a :class:`Gaussians` set and returns its size K.

  Shapes (static, so safe under ``jit``): ``means`` (K, 3), ``log_scales``
  (K, 3), ``quats`` (K, 4), ``opacity_logits`` (K,), ``sh`` (K, B, 3) with
  B = 1, 4, 9 or 16 (unless ``sh=False``), ``normals`` (K, 3) or None, all
  floating point. With ``finite``, concrete arrays (not tracers) must also
  be finite: a NaN scale or opacity would otherwise drop the Gaussian from
  every image without a word, a NaN colour turn pixels NaN.

  Raises:
    DataError: naming ``where``, the field, the shape or the bad rows.
  """
  if not isinstance(g, Gaussians):
    raise DataError(f'{where}: expected a physsplat_jax.types.Gaussians, got '
                    f'{type(g).__name__}')
  means = g.means
  if np.ndim(means) != 2 or np.shape(means)[1] != 3:
    raise DataError(f'{where}: Gaussians.means has shape {np.shape(means)}, '
                    'expected (K, 3)')
  K = np.shape(means)[0]
  fields = [('means', (K, 3)), ('log_scales', (K, 3)), ('quats', (K, 4)),
            ('opacity_logits', (K,))]
  if sh:
    fields.append(('sh', (K, None, 3)))
  if g.normals is not None:
    fields.append(('normals', (K, 3)))
  for name, shape in fields:
    a = getattr(g, name)
    got = np.shape(a)
    if len(got) != len(shape) or any(e is not None and e != d
                                     for e, d in zip(shape, got)):
      want = '(' + ', '.join('B' if e is None else str(e) for e in shape) + \
        (',)' if len(shape) == 1 else ')')
      raise DataError(f'{where}: Gaussians.{name} has shape {got}, expected '
                      f'{want} for its {K} Gaussians')
    if not jnp.issubdtype(jnp.result_type(a), jnp.floating):
      raise DataError(f'{where}: Gaussians.{name} has dtype '
                      f'{jnp.result_type(a)}; use float32 (or float64)')
  if sh:
    try:
      sh_degree_from_bases(np.shape(g.sh)[1])
    except DataError as e:
      raise DataError(f'{where}: Gaussians.sh: {e}') from None
  if finite:
    for name, _ in fields:
      a = getattr(g, name)
      if name == 'normals' or isinstance(a, jax.core.Tracer):
        continue
      rows = nonfinite_rows(a)
      if rows.size:
        raise DataError(
          f'{where}: {rows.size} of {K} Gaussians have non-finite {name} '
          f'(rows {rows_text(rows)}); drop them (Gaussians.subset) or fix '
          'the scene file')
  return K


class Gaussians(struct.PyTreeNode):
  """A set of 3D Gaussians with their pre-activation parameters.

  Attributes:
    means: (K, 3) centres [scene units].
    log_scales: (K, 3) log of the standard deviations along the local axes.
    quats: (K, 4) rotations as raw (not necessarily unit) quaternions, wxyz.
    opacity_logits: (K,) opacity before the sigmoid.
    sh: (K, B, 3) spherical-harmonics colour coefficients, B = (d + 1)**2.
    normals: (K, 3) or None; carried only so INRIA files round-trip exactly.
    extras: dict name -> (K,) array of other per-Gaussian PLY properties
      (e.g. ``object_id``); carried through subsets and written back.
  """

  means: Array
  log_scales: Array
  quats: Array
  opacity_logits: Array
  sh: Array
  normals: Array | None = None
  extras: dict[str, Array] = struct.field(default_factory=dict)

  @property
  def num(self) -> int:
    return self.means.shape[0]

  def __len__(self) -> int:
    return self.means.shape[0]

  @property
  def sh_degree(self) -> int:
    return sh_degree_from_bases(self.sh.shape[-2])

  # Activations --------------------------------------------------------------
  @property
  def scales(self) -> Array:
    """(K, 3) standard deviations along the local axes."""
    return jnp.exp(self.log_scales)

  @property
  def opacities(self) -> Array:
    """(K,) opacities in (0, 1)."""
    return jax.nn.sigmoid(self.opacity_logits)

  @property
  def unit_quats(self) -> Array:
    """(K, 4) normalised wxyz quaternions."""
    from physsplat_jax import gaussians as _g

    return _g.normalize_quat(self.quats)

  @property
  def rotations(self) -> Array:
    """(K, 3, 3) rotation matrices (columns are the local axes)."""
    from physsplat_jax import gaussians as _g

    return _g.quat_to_rotmat_jit(self.quats)

  @property
  def covariances(self) -> Array:
    """(K, 3, 3) covariances ``R S S^T R^T``."""
    from physsplat_jax import gaussians as _g

    return _g.covariance_jit(self.log_scales, self.quats)

  @property
  def rgb_dc(self) -> Array:
    """(K, 3) view-independent colour ``0.5 + C0 * sh_dc`` (not clamped)."""
    from physsplat_jax import gaussians as _g

    return _g.sh_dc_to_rgb(self.sh[:, 0, :])

  # Selection ----------------------------------------------------------------
  def subset(self, index) -> Gaussians:
    """Rows selected by a boolean mask or an integer index array (host side).

    Not for use under ``jit`` with a boolean mask (the size is data-dependent);
    there, use masks or fixed capacities instead.
    """
    idx = np.asarray(index)
    if idx.dtype == bool:
      if idx.shape != (self.num,):
        raise DataError(
          f'subset mask has shape {idx.shape}, expected ({self.num},)'
        )
      idx = np.nonzero(idx)[0]
    def take(a):
      if a is None or isinstance(a, jax.core.Tracer):
        return None if a is None else a[idx]
      # Concrete arrays are indexed in NumPy: an eager JAX gather compiles
      # once per shape (~30 ms each, 2 s of a scene's preparation).
      return device_array(np.asarray(a)[idx])

    return self.replace(
      means=take(self.means),
      log_scales=take(self.log_scales),
      quats=take(self.quats),
      opacity_logits=take(self.opacity_logits),
      sh=take(self.sh),
      normals=take(self.normals),
      extras={k: take(v) for k, v in self.extras.items()},
    )

  def with_sh_degree(self, degree: int) -> Gaussians:
    """Truncates or zero-pads the SH coefficients to ``degree``."""
    nb = (degree + 1) ** 2
    sh = self.sh
    if sh.shape[1] >= nb:
      sh = sh[:, :nb]
    else:
      pad = jnp.zeros((sh.shape[0], nb - sh.shape[1], 3), sh.dtype)
      sh = jnp.concatenate([sh, pad], axis=1)
    return self.replace(sh=sh)

  def astype(self, dtype) -> Gaussians:
    """Casts every floating array to ``dtype``."""
    cast = lambda a: (
      a
      if a is None or not jnp.issubdtype(a.dtype, jnp.floating)
      else a.astype(dtype)
    )
    return jax.tree.map(cast, self)


def concatenate_gaussians(parts: list[Gaussians]) -> Gaussians:
  """Concatenates Gaussian sets (same SH degree) along the first axis."""
  if not parts:
    raise DataError('concatenate_gaussians needs at least one set')
  deg = max(p.sh_degree for p in parts)
  parts = [p.with_sh_degree(deg) for p in parts]
  def cat(xs):
    if all(in_host_memory(x) for x in xs):
      # Joined in NumPy: no eager program to compile.
      return device_array(np.concatenate([np.asarray(x) for x in xs]))
    return jnp.concatenate(xs, axis=0)  # traced, or on an accelerator

  have_normals = all(p.normals is not None for p in parts)
  keys = set(parts[0].extras)
  for p in parts[1:]:
    keys &= set(p.extras)
  return Gaussians(
    means=cat([p.means for p in parts]),
    log_scales=cat([p.log_scales for p in parts]),
    quats=cat([p.quats for p in parts]),
    opacity_logits=cat([p.opacity_logits for p in parts]),
    sh=cat([p.sh for p in parts]),
    normals=cat([p.normals for p in parts]) if have_normals else None,
    extras={k: cat([p.extras[k] for p in parts]) for k in sorted(keys)},
  )


class Camera(struct.PyTreeNode):
  """A pinhole camera, OpenCV convention.

  Attributes:
    viewmat: (4, 4) world-to-camera transform (+x right, +y down, +z forward).
    fx, fy: focal lengths [pixels].
    cx, cy: principal point [pixels]; pixel (i, j) has its centre at
      ``(j + 0.5, i + 0.5)``, so an image-centred camera has ``cx = W / 2``.
    width, height: image size [pixels] (static: they set array shapes).
    near, far: clipping depths [scene units], scalar arrays (traced, so
      cameras that differ only in their depth range share compiled code).
    name: a label, e.g. the image file name (static; the package's jitted
      renderers drop it with :meth:`unlabelled`, so it never recompiles
      them).
  """

  viewmat: Array
  fx: Array
  fy: Array
  cx: Array
  cy: Array
  width: int = struct.field(pytree_node=False)
  height: int = struct.field(pytree_node=False)
  near: Array = 0.01
  far: Array = 1e10
  name: str = struct.field(pytree_node=False, default='')

  def unlabelled(self) -> Camera:
    """The camera without its name, near/far as arrays of ``fx``'s dtype:
    what a jitted function should receive, so that cameras differing only
    in label or depth range hit the same compiled code."""
    f = lambda v: jnp.asarray(v, jnp.result_type(self.fx))  # noqa: E731
    return self.replace(near=f(self.near), far=f(self.far), name='')

  @property
  def K(self) -> Array:
    """(3, 3) intrinsic matrix."""
    z = jnp.zeros_like(self.fx)
    o = jnp.ones_like(self.fx)
    return jnp.stack(
      [
        jnp.stack([self.fx, z, self.cx]),
        jnp.stack([z, self.fy, self.cy]),
        jnp.stack([z, z, o]),
      ]
    )

  @property
  def camtoworld(self) -> Array:
    """(4, 4) camera-to-world transform."""
    R = self.viewmat[:3, :3]
    t = self.viewmat[:3, 3]
    out = jnp.eye(4, dtype=self.viewmat.dtype)
    out = out.at[:3, :3].set(R.T)
    return out.at[:3, 3].set(-R.T @ t)

  @property
  def position(self) -> Array:
    """(3,) camera centre in world coordinates."""
    R = self.viewmat[:3, :3]
    return -R.T @ self.viewmat[:3, 3]

  def project(self, points: Array) -> tuple[Array, Array]:
    """Projects world points to pixels.

    Args:
      points: (..., 3) world coordinates.

    Returns:
      (uv, depth): (..., 2) pixel coordinates (continuous; pixel (i, j) covers
      ``[j, j+1) x [i, i+1)``) and (...,) camera-space depth.
    """
    pc = points @ self.viewmat[:3, :3].T + self.viewmat[:3, 3]
    z = pc[..., 2]
    u = self.fx * pc[..., 0] / z + self.cx
    v = self.fy * pc[..., 1] / z + self.cy
    return jnp.stack([u, v], axis=-1), z

  def resized(self, width: int, height: int) -> Camera:
    """The same camera at another resolution (intrinsics scaled)."""
    if int(width) < 1 or int(height) < 1:
      raise DataError(f'Camera.resized: image size {width}x{height}; width '
                      'and height must be >= 1')
    sx = width / self.width
    sy = height / self.height
    return self.replace(
      fx=self.fx * sx,
      fy=self.fy * sy,
      cx=self.cx * sx,
      cy=self.cy * sy,
      width=int(width),
      height=int(height),
    )


def check_camera(camera: Camera) -> None:
  """:func:`make_camera`'s checks on a camera built otherwise (e.g. by
  ``Camera.replace``), on its concrete values; raises :class:`DataError`."""
  if not isinstance(camera, Camera):
    hint = ('; pick one, e.g. scene.cameras[0]'
            if isinstance(camera, (list, tuple)) else
            '; build one with make_camera or look_at')
    raise DataError(f'camera is a {type(camera).__name__}, not a '
                    f'physsplat_jax.Camera{hint}')
  _check_camera_values(camera.viewmat, camera.fx, camera.fy, camera.width,
                       camera.height, camera.near, camera.far, camera.name,
                       cx=camera.cx, cy=camera.cy)


def _check_camera_values(viewmat, fx, fy, width, height, near, far,
                         name='', cx=0.0, cy=0.0) -> None:
  """:func:`make_camera`'s checks, on the values that are concrete."""
  what = f'camera {name!r}' if name else 'camera'
  if int(width) < 1 or int(height) < 1 or int(width) != width or \
      int(height) != height:
    raise DataError(f'{what}: image size {width}x{height}; width and height '
                    'must be whole numbers >= 1')
  if np.shape(viewmat) != (4, 4):
    raise DataError(f'{what}: viewmat has shape {np.shape(viewmat)}, expected '
                    '(4, 4) (world-to-camera, OpenCV axes)')
  concrete = lambda v: not isinstance(v, jax.core.Tracer)  # noqa: E731
  for label, v in (('fx', fx), ('fy', fy)):
    if concrete(v) and not (np.isfinite(v) and float(v) > 0):
      raise DataError(f'{what}: focal length {label}={float(v)!r} must be a '
                      'positive number of pixels')
  for label, v in (('cx', cx), ('cy', cy)):
    if concrete(v) and not np.all(np.isfinite(v)):
      raise DataError(f'{what}: principal point {label}={v!r} must be a '
                      'finite number of pixels (default: the image centre)')
  if concrete(near) and concrete(far) and not (
      np.isfinite(near) and 0 < float(near) < float(far)):
    raise DataError(f'{what}: near={float(near)!r}, far={float(far)!r}; '
                    'need 0 < near < far')
  if concrete(viewmat):
    vm = np.asarray(viewmat, np.float64)
    R = vm[:3, :3]
    if not np.all(np.isfinite(vm)):
      raise DataError(f'{what}: viewmat has non-finite entries')
    err = float(np.max(np.abs(R @ R.T - np.eye(3))))
    if err > 1e-3 or np.linalg.det(R) < 0 or np.any(vm[3] != (0, 0, 0, 1)):
      raise DataError(
        f'{what}: viewmat is not a rigid transform (its 3x3 block must be a '
        f'rotation: |R R^T - I| = {err:.3g}, det {np.linalg.det(R):.3g}; '
        f'last row {vm[3].tolist()}, expected [0, 0, 0, 1]); build it with '
        'cameras.look_at or from a camera-to-world pose')


def make_camera(
  viewmat,
  fx,
  fy,
  width: int,
  height: int,
  cx=None,
  cy=None,
  near: float = 0.01,
  far: float = 1e10,
  name: str = '',
  dtype=jnp.float32,
) -> Camera:
  """Builds a :class:`Camera`; the principal point defaults to the centre.

  Raises:
    DataError: a size below 1 pixel, a focal length that is not positive, a
      non-finite principal point, a ``viewmat`` that is not a finite 4x4
      rigid transform, or
      ``0 < near < far`` broken (values given as tracers are not checked).
  """
  cx = width / 2.0 if cx is None else cx
  cy = height / 2.0 if cy is None else cy
  _check_camera_values(viewmat, fx, fy, width, height, near, far, name,
                       cx=cx, cy=cy)
  f = lambda v: device_array(v, dtype)
  return Camera(
    viewmat=f(viewmat),
    fx=f(fx),
    fy=f(fy),
    cx=f(cx),
    cy=f(cy),
    width=int(width),
    height=int(height),
    near=f(near),
    far=f(far),
    name=str(name),
  )


@dataclasses.dataclass(frozen=True)
class ObjectInfo:
  """Static description of one object of a scene.

  Attributes:
    name: a human-readable name, e.g. ``'jelly cube'`` (used by offline
      perception to pick a library material).
    material: a material-library key chosen by the scene's author, or None.
    fixed: True for objects that do not move (tables, pots, ground).
    tags: free-form labels.
  """

  name: str
  material: str | None = None
  fixed: bool = False
  tags: tuple[str, ...] = ()


class Scene(struct.PyTreeNode):
  """A 3DGS scene split into objects, with cameras.

  Attributes:
    gaussians: the Gaussians, K of them.
    object_ids: (K,) int32 object index per Gaussian into ``objects``;
      -1 means background (not simulated).
    objects: static tuple of :class:`ObjectInfo`.
    cameras: tuple of :class:`Camera` (may be empty).
    up_axis: static, the world's up: one of 'x', 'y', 'z', '-x', '-y',
      '-z', or a direction 'x,y,z' (see :func:`up_vector`).
    meters_per_unit: static, metres per scene unit (physics runs in metres).
    name: static label.
  """

  gaussians: Gaussians
  object_ids: Array
  objects: tuple[ObjectInfo, ...] = struct.field(pytree_node=False, default=())
  cameras: tuple[Camera, ...] = ()
  up_axis: str = struct.field(pytree_node=False, default='z')
  meters_per_unit: float = struct.field(pytree_node=False, default=1.0)
  name: str = struct.field(pytree_node=False, default='')

  @property
  def num_objects(self) -> int:
    return len(self.objects)

  @property
  def object_names(self) -> tuple[str, ...]:
    return tuple(o.name for o in self.objects)

  @property
  def up_vector(self) -> np.ndarray:
    """(3,) unit world-up vector."""
    return up_vector(self.up_axis)

  def object_mask(self, index_or_name) -> Array:
    """(K,) bool mask of one object, by index or name."""
    if isinstance(index_or_name, str):
      names = self.object_names
      if index_or_name not in names:
        raise UnknownObjectError(
          f'scene {self.name!r} has no object {index_or_name!r}; objects: '
          f'{list(names)}'
        )
      index_or_name = names.index(index_or_name)
    return self.object_ids == index_or_name


def up_vector(axis: str) -> np.ndarray:
  """Unit vector for an up label: a signed axis such as ``'z'`` or ``'-y'``,
  or a general direction written ``'x,y,z'`` (e.g. ``'0.1,-0.99,0.05'``,
  normalised here)."""
  table = {'x': 0, 'y': 1, 'z': 2}
  a = axis.strip().lower()
  if ',' in a:
    try:
      v = np.array([float(c) for c in a.split(',')], np.float64)
    except ValueError:
      v = np.zeros(0)
    if v.shape != (3,) or not np.all(np.isfinite(v)) or not v.any():
      raise DataError(
        f"up axis {axis!r} is not a direction: write three finite numbers "
        "'x,y,z', not all zero, or one of 'x', 'y', 'z', '-x', '-y', '-z'")
    return v / np.linalg.norm(v)
  sign = -1.0 if a.startswith('-') else 1.0
  a = a.lstrip('+-')
  if a not in table:
    raise DataError(
      f"up axis {axis!r} is not one of 'x', 'y', 'z', '-x', '-y', '-z' "
      "(or a direction 'x,y,z')"
    )
  v = np.zeros(3)
  v[table[a]] = sign
  return v
