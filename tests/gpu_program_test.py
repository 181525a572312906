"""What the MPM substep and the renderer's binning become on a GPU, checked
without one.

Some steps of the substep are written twice and chosen by platform when
the program is lowered (``platforms.platform_dependent``, which keeps every
form while ``platforms.every_platform()`` is open): the CPU keeps the forms
XLA:CPU runs fastest (a batched product in G2P and for the rigid-body sums,
the Jacobi sweeps of the SVD as a loop); other platforms get forms XLA:GPU
fuses into fewer kernels (sums, an unrolled chain). Lowering for CUDA needs
no GPU, so these tests lower for 'cuda' and 'cpu' and check which form each
platform got, and check on the CPU that the two forms agree in value.
``experiments/gpu_kernels.py`` counts the kernels of the compiled program
(docs/benchmarks.md).
"""

import dataclasses
import os
import pathlib
import re
import subprocess
import sys
import tempfile

import jax
import jax.numpy as jnp
import numpy as np
from absl.testing import absltest

import mpm_blocks
from experiments.lib import hlo
from experiments.lib import ptxas
from physsplat_jax import mpm
from physsplat_jax import platforms
from physsplat_jax.mpm import linalg as la
from physsplat_jax.mpm import rigid
from physsplat_jax.mpm import transfer
from physsplat_jax.render import raster

_GRID = mpm.GridSpec(res=16, size=1.0, lower=(0.5, -1.0, 0.0))


def _ops(fn, args, platform):
  """Counts of StableHLO ops in ``fn`` lowered for ``platform``."""
  with platforms.every_platform():  # a program for a GPU on a CPU host
    text = jax.jit(fn).trace(*args).lower(
      lowering_platforms=(platform,)).as_text()
  ops = {op: len(re.findall(rf'stablehlo\.{op}\b', text))
         for op in ('while', 'dot_general', 'scatter', 'reduce', 'gather',
                    'concatenate')}
  ops['triton'] = text.count('__gpu$xla.gpu.triton')
  return ops


class FormsAgreeTest(absltest.TestCase):
  """Both forms of each platform-dependent step give the same values."""

  def test_g2p_sum_equals_product(self):
    """On a random (non-affine) field; mpm_solver_test checks both forms
    reproduce an affine field exactly."""
    with jax.enable_x64(True):
      rng = np.random.default_rng(2)
      x = np.asarray(_GRID.lower) + 0.2 + 0.6 * rng.random((40, 3))
      st = transfer.Stencil(_GRID, tuple(jnp.asarray(x.T)))
      gv = tuple(jnp.asarray(rng.normal(size=(16,) * 3)) for _ in range(3))
      d, s = (transfer.g2p(_GRID, st, gv, form=f) for f in ('dot', 'sum'))
      for p, q in zip(jax.tree.leaves(d), jax.tree.leaves(s)):
        np.testing.assert_allclose(p, q, rtol=1e-12, atol=1e-12)

  def test_channels_select_equals_stack(self):
    """P2G's per-particle channel blocks and the stencil's base indices:
    the selects (GPU) give exactly the stacked arrays (CPU), scalars
    (Python zeros) and integers included."""
    rng = np.random.default_rng(4)
    cols = [jnp.asarray(rng.normal(size=7)), 0.0,
            jnp.asarray(rng.normal(size=7)), 2.5]
    stack, select = (transfer._channels(cols, f) for f in ('stack', 'select'))
    self.assertEqual(select.shape, (7, 4))
    np.testing.assert_array_equal(stack, select)
    ints = [jnp.asarray(rng.integers(0, 9, size=5), jnp.int32)
            for _ in range(3)]
    np.testing.assert_array_equal(transfer._channels(ints, 'select'),
                                  np.stack(ints, axis=-1))
    self.assertEqual(transfer._channels(ints, 'select').dtype, jnp.int32)

  def test_block_weights_select_equals_stack(self):
    """The stencil's weights as one (N, 3, 3) array of selects (GPU) and
    as three stacks (CPU): the same bits; a partition of unity."""
    rng = np.random.default_rng(5)
    f = tuple(jnp.asarray(0.5 + rng.random(50), jnp.float32)
              for _ in range(3))
    stack, select = (transfer.block_weights(f, form)
                     for form in ('stack', 'select'))
    self.assertEqual(select.shape, (50, 3, 3, 3))
    np.testing.assert_array_equal(stack, select)
    np.testing.assert_allclose(jnp.sum(select, (1, 2, 3)), 1.0, rtol=1e-6)
    # and the same derivatives (the GPU form is differentiated there)
    grads = [jax.grad(lambda f, form=form: jnp.sum(
      transfer.block_weights(f, form) ** 2))(f) for form in ('stack', 'select')]
    for p, q in zip(*grads):
      np.testing.assert_allclose(p, q, rtol=1e-6, atol=1e-7)
    cols = [jnp.asarray(rng.normal(size=6)) for _ in range(3)]
    gs = [jax.grad(lambda c, form=form: jnp.sum(
      transfer._channels(c, form) * jnp.arange(3.0)))(cols)
      for form in ('stack', 'select')]
    for p, q in zip(*gs):
      np.testing.assert_array_equal(p, q)

  def test_channel_forms_reject_an_unknown_form(self):
    with self.assertRaisesRegex(ValueError, "'auto', 'stack' or 'select'"):
      transfer._channels([jnp.zeros(3)], form='concat')
    with self.assertRaisesRegex(ValueError, "'auto', 'stack' or 'select'"):
      transfer.block_weights((jnp.zeros(3),) * 3, form='concat')

  def test_g2p_rejects_an_unknown_form(self):
    st = transfer.Stencil(_GRID, tuple(jnp.full((3, 2), 0.5)))
    gv = tuple(jnp.zeros((16,) * 3) for _ in range(3))
    with self.assertRaisesRegex(ValueError, "'auto', 'dot' or 'sum'"):
      transfer.g2p(_GRID, st, gv, form='einsum')

  def test_g2p_window_rows_equal_block(self):
    """G2P's window read as nine rows (CPU) and as one block (GPU), with
    particles at the grid's first and last base nodes."""
    rng = np.random.default_rng(3)
    G = _GRID.res
    g4 = jnp.asarray(rng.normal(size=(G, G, G, 3)))
    base = rng.integers(0, G - 2, size=(60, 3))
    base[:4] = [[0, 0, 0], [G - 3] * 3, [0, G - 3, 5], [G - 3, 0, G - 3]]
    lin = (base[:, 0] * G + base[:, 1]) * G + base[:, 2]
    base, lin = jnp.asarray(base, jnp.int32), jnp.asarray(lin, jnp.int32)
    rows = transfer._window_rows(g4, base, lin)
    block = transfer._window_block(g4, base, lin)
    np.testing.assert_array_equal(rows, block)
    # And the block is the window (offsets in OFFSETS order).
    b = np.asarray(base)
    for n in (0, 1, 7):
      for k, (i, j, l) in enumerate(transfer.OFFSETS):
        np.testing.assert_array_equal(
          block[n, k], g4[b[n, 0] + i, b[n, 1] + j, b[n, 2] + l])

  def test_rigid_per_particle_product_equals_gather(self):
    """The per-body values reach the particles by a one-hot product (CPU)
    or gathers (GPU): the same values, bit for bit (float32 and 64), with
    empty segments and negative, tiny and huge values."""
    rng = np.random.default_rng(4)
    seg = jnp.asarray(rng.choice([0, 2, 3], 57), jnp.int32)  # 1 empty
    for dtype in (jnp.float32, jnp.float64):
      with jax.enable_x64(dtype == jnp.float64):
        cols = [jnp.asarray(rng.normal(size=4) * s, dtype)
                for s in (1.0, 1e-30, 1e30, -3.0)]
        got = {f: jax.jit(rigid._per_particle(seg, 4, dtype, f))(cols)
               for f in ('product', 'gather', 'auto')}
        for p, q, r, col in zip(got['product'], got['gather'], got['auto'],
                                cols):
          np.testing.assert_array_equal(p, q)
          np.testing.assert_array_equal(r, q)
          np.testing.assert_array_equal(q, np.asarray(col)[np.asarray(seg)])

  def test_sub_tile_ranges_unrolled_equals_loop(self):
    """The renderer's sub-tile ranges: both binary searches give numpy's
    ranges on sorted ids with empty sub-tiles and unused slots (id
    ``num_sub``)."""
    rng = np.random.default_rng(5)
    num_sub = 37
    ids = np.sort(np.concatenate([rng.choice([0, 3, 4, 9, 20, 36], 50),
                                  np.full(13, num_sub)])).astype(np.int32)
    want = np.searchsorted(ids, np.arange(num_sub + 1), side='left')
    for method in ('scan', 'scan_unrolled', None):
      got = raster._sub_tile_ranges(jnp.asarray(ids), num_sub, method)
      np.testing.assert_array_equal(got, want)

  def test_jacobi_unrolled_equals_loop(self):
    with jax.enable_x64(True):
      rng = np.random.default_rng(0)
      A = rng.normal(size=(50, 3, 3))
      S = la.to_mat(jnp.asarray(np.transpose(A + A.transpose(0, 2, 1),
                                             (1, 2, 0))))
      (d0, V0), (d1, V1) = (la._jacobi_eigh(S, 6, unroll=u)
                            for u in (False, True))
      np.testing.assert_allclose(np.stack(d0), np.stack(d1), atol=1e-13)
      np.testing.assert_allclose(np.asarray(V0), np.asarray(V1), atol=1e-13)
      # And they are the eigen-decomposition (sorted eigenvalues agree).
      ref = np.linalg.eigvalsh(A + A.transpose(0, 2, 1))
      np.testing.assert_allclose(np.sort(np.stack(d1, -1), -1), ref,
                                 atol=1e-12)

  def test_rigid_segment_sums_product_equals_reduction(self):
    with jax.enable_x64(True):
      rng = np.random.default_rng(1)
      seg = jnp.asarray(rng.integers(0, 4, 200))
      cols = [jnp.asarray(rng.normal(size=200)) for _ in range(5)]
      want = [np.bincount(np.asarray(seg), np.asarray(c), 4) for c in cols]
      for form in ('product', 'reduction'):
        got = rigid._segment_sums(seg, 4, jnp.float64, form=form)(cols)
        np.testing.assert_allclose(np.stack(got), np.stack(want),
                                   rtol=1e-12, err_msg=form)

  def test_rigid_sums_without_the_dump_segment(self):
    """The solver's rigid slice has no particle in the last (dump)
    segment (``last_empty``): its sums are zeros, the others the full
    forms' sums, for one body (a column sum, or a product with ones) and
    for several."""
    with jax.enable_x64(True):
      rng = np.random.default_rng(2)
      cols = [jnp.asarray(rng.normal(size=90)) for _ in range(4)]
      for bodies in (1, 3):
        seg = jnp.asarray(rng.integers(0, bodies, 90), jnp.int32)
        want = [np.bincount(np.asarray(seg), np.asarray(c), bodies + 1)
                for c in cols]
        for form in ('product', 'reduction', 'auto'):
          got = jax.jit(rigid._segment_sums(
            seg, bodies + 1, jnp.float64, form=form, last_empty=True))(cols)
          np.testing.assert_allclose(np.stack(got), np.stack(want),
                                     rtol=1e-12, atol=1e-12,
                                     err_msg=f'{bodies} {form}')
          self.assertTrue(np.all(np.stack(got)[:, -1] == 0.0))


  def test_rigid_contacts_sequential_equals_merged(self):
    """Bodies pushed into a floor and two walls orthogonal to it and to
    each other: measuring the planes one after another (CPU) and all at
    once (GPU) gives the same motion (mpm_bc_test checks coincident planes
    under a flat face, where they agree too)."""
    with jax.enable_x64(True):
      x, v, body, mass, planes = _bodies_in_a_corner()
      F = tuple(tuple(jnp.full((len(x),), float(i == j)) for j in range(3))
                for i in range(3))
      out = {}
      for form in ('sequential', 'merged'):
        _, xn, vn, _, _ = rigid.project(
          3, (False, False, False), 0.05, 1e-3, body, mass,
          tuple(x[:, d] for d in range(3)), tuple(v[:, d] for d in range(3)),
          F, planes=planes, contact_form=form)
        out[form] = np.stack(xn + vn)
      np.testing.assert_allclose(out['merged'], out['sequential'],
                                 atol=1e-13)
      # They did move out of the planes.
      self.assertGreater(np.abs(out['merged'][:3] - x.T).max(), 0.005)


def _bodies_in_a_corner():
  """Three rigid bodies of random particles: one 0.01-0.02 m into a sticky
  floor at z = 0.3 and a wall at x = 0.3, one into the floor only, one into
  a wall at y = 0.25 only; falling and sliding."""
  rng = np.random.default_rng(2)
  x = np.concatenate([rng.uniform(0, 0.1, (20, 3)) + c for c in
                      ([0.28, 0.5, 0.29], [0.5, 0.5, 0.28], [0.5, 0.23, 0.6])])
  body = jnp.asarray(np.repeat(np.arange(3), 20))
  v = jnp.asarray(rng.normal(size=x.shape) * 0.1 + [0.1, 0.0, -0.5])
  mass = jnp.asarray(rng.uniform(0.5, 1.5, len(x)))
  on = jnp.asarray(True)
  planes = [((0.0, 0.0, 0.3), (0.0, 0.0, 1.0), np.inf, 'sticky', on, 0.0),
            ((0.3, 0.0, 0.0), (1.0, 0.0, 0.0), 0.5, 'separate', on, 0.0),
            ((0.0, 0.25, 0.0), (0.0, 1.0, 0.0), 0.2, 'separate', on, 0.0)]
  return jnp.asarray(x), v, body, mass, planes


class PlatformFormsTest(absltest.TestCase):
  """Which form each platform's program gets."""

  def test_rigid_contacts_are_one_sum_on_cuda(self):
    """Three planes: on CUDA the contact sets are one per-body sum (2 in
    all, with the one of the body's mass, momenta and inertia) and the
    per-body values reach the particles by gathers; on the CPU one product
    per plane (4 sums) and 4 one-hot products for the per-body values
    (``rigid._per_particle``)."""
    x, v, body, mass, planes = _bodies_in_a_corner()
    F = tuple(tuple(jnp.ones(len(x)) for _ in range(3)) for _ in range(3))

    def project(x, v):
      return rigid.project(3, (False, False, False), 0.05, 1e-3, body, mass,
                           tuple(x[:, d] for d in range(3)),
                           tuple(v[:, d] for d in range(3)), F,
                           planes=planes)[1]

    cpu, cuda = (_ops(project, (x, v), p) for p in ('cpu', 'cuda'))
    self.assertEqual(cpu['dot_general'], 8)
    self.assertEqual(cuda['dot_general'], 0)
    self.assertEqual(cuda['reduce'], 2)
    self.assertGreaterEqual(cuda['gather'], 1)

  def test_g2p_is_a_product_on_cpu_a_sum_on_cuda(self):
    x = jnp.full((3, 8), 0.3)
    gv = tuple(jnp.zeros((16,) * 3) for _ in range(3))

    def g2p(x, gv):
      return transfer.g2p(_GRID, transfer.Stencil(_GRID, tuple(x)), gv)

    cpu, cuda = (_ops(g2p, (x, gv), p) for p in ('cpu', 'cuda'))
    self.assertGreaterEqual(cpu['dot_general'], 1)
    self.assertEqual(cuda['dot_general'], 0)
    self.assertGreaterEqual(cuda['reduce'], 1)

  def test_p2g_operands_are_not_concatenated_on_cuda(self):
    """P2G and G2P (the stencil's weights, the per-particle channels, the
    base indices): concatenations on the CPU, none on CUDA, where each was
    a kernel of its own at the paper's sizes (docs/benchmarks.md)."""
    x = jnp.full((3, 8), 0.3)
    v = tuple(jnp.zeros(8) for _ in range(3))
    A = tuple(tuple(jnp.zeros(8) for _ in range(3)) for _ in range(3))
    gv = tuple(jnp.zeros((16,) * 3) for _ in range(3))

    def transfers(x, v, A, gv):
      st = transfer.Stencil(_GRID, tuple(x))
      grid = transfer.p2g(_GRID, st, v, jnp.ones(8), A, jnp.ones(8))
      return grid, transfer.g2p(_GRID, st, gv)

    args = (x, v, A, gv)
    cpu, cuda = (_ops(transfers, args, p) for p in ('cpu', 'cuda'))
    self.assertGreaterEqual(cpu['concatenate'], 4)
    # G2P's grid velocity (G, G, G, 3) is the one left: a grid-sized
    # array, materialised before its gather on every platform.
    self.assertEqual(cuda['concatenate'], 1)

  def test_render_ranges_have_no_loop_on_cuda(self):
    ids = jnp.zeros((64,), jnp.int32)
    fn = lambda a: raster._sub_tile_ranges(a, 16)  # noqa: E731
    cpu, cuda = (_ops(fn, (ids,), p) for p in ('cpu', 'cuda'))
    self.assertEqual(cpu['while'], 1)
    self.assertEqual(cuda['while'], 0)

  def test_multi_material_frame_has_no_loop_or_product_on_cuda(self):
    """A frame of two SVD models, a fixed-corotated block and a rigid body
    on a plane: on CUDA the only loop is the scan over substeps (no Jacobi
    loops) and nothing is a matrix product (G2P, rigid sums); on the CPU
    the Jacobi loops and the products are there."""
    s, mat, forces, cfg = mpm_blocks.four_blocks()
    frame = mpm.make_frame(cfg)
    cpu, cuda = (_ops(frame, (s, mat, forces), p) for p in ('cpu', 'cuda'))
    self.assertEqual(cuda['while'], 1)
    self.assertEqual(cuda['dot_general'], 0)
    # The stress update is one Pallas (Triton) kernel on CUDA only
    # (SimConfig.constitutive_kernel='auto'; 'jax' keeps XLA's fusion).
    self.assertEqual(cuda['triton'], 1)
    self.assertEqual(cpu['triton'], 0)
    jax_cuda = _ops(mpm.make_frame(dataclasses.replace(
      cfg, constitutive_kernel='jax')), (s, mat, forces), 'cuda')
    self.assertEqual(jax_cuda['triton'], 0)
    # The scan and Drucker-Prager's Jacobi loop (neo-Hookean has no SVD;
    # the stress is computed in the substep only, not again before the
    # scan), and the products.
    self.assertEqual(cpu['while'], 2)
    self.assertGreaterEqual(cpu['dot_general'], 2)


_HLO = """HloModule m

%fused (p0: f32[4]) -> f32[4] {
  %p0 = f32[4]{0} parameter(0)
  ROOT %s = f32[4]{0} sine(%p0)
}

%inner (a: (s32[], f32[4])) -> (s32[], f32[4]) {
  %a = (s32[], f32[4]{0}) parameter(0)
  %i = s32[] get-tuple-element(%a), index=0
  %x = f32[4]{0} get-tuple-element(%a), index=1
  %f = f32[4]{0} fusion(%x), kind=kLoop, calls=%fused
  ROOT %t = (s32[], f32[4]{0}) tuple(%i, %f)
}

%body (b: (s32[], f32[4])) -> (s32[], f32[4]) {
  %b = (s32[], f32[4]{0}) parameter(0)
  %w = (s32[], f32[4]{0}) while(%b), condition=%cond, body=%inner, backend_config={"known_trip_count":{"n":"3"}}
  %y = f32[4]{0} get-tuple-element(%w), index=1
  %c = f32[4]{0} copy(%y)
  %r = f32[4]{0} fusion(%c), kind=kInput, calls=%fused
  %i = s32[] get-tuple-element(%w), index=0
  ROOT %t = (s32[], f32[4]{0}) tuple(%i, %r)
}

ENTRY %main (e: f32[4]) -> f32[4] {
  %e = f32[4]{0} parameter(0)
  %z = s32[] constant(0)
  %t = (s32[], f32[4]{0}) tuple(%z, %e)
  %w = (s32[], f32[4]{0}) while(%t), condition=%cond, body=%body, backend_config={"known_trip_count":{"n":"5"}}
  ROOT %o = f32[4]{0} get-tuple-element(%w), index=1
}
"""


class XlaCpuTuningTest(absltest.TestCase):
  """platforms.tune_xla_cpu: the package's XLA:CPU flag, added only where
  it can take effect and nobody chose otherwise."""

  def test_added_once_and_only_where_it_can_apply(self):
    from jax._src import xla_bridge  # noqa: PLC0415
    flag = '--xla_cpu_experimental_ynn_fusion_type=dot,individual_dot'
    with absltest.mock.patch.dict(xla_bridge._backends, clear=True), \
        absltest.mock.patch('jaxlib.__version__', '0.10.2'):
      env = {'XLA_FLAGS': '--xla_foo=1'}
      self.assertTrue(platforms.tune_xla_cpu(env))
      self.assertEqual(env['XLA_FLAGS'], f'--xla_foo=1 {flag}')
      self.assertFalse(platforms.tune_xla_cpu(env))  # there already
      self.assertEqual(env['XLA_FLAGS'], f'--xla_foo=1 {flag}')
      mine = {'XLA_FLAGS': '--xla_cpu_experimental_ynn_fusion_type=reduce'}
      self.assertFalse(platforms.tune_xla_cpu(mine))  # the user's stands
      self.assertEqual(mine['XLA_FLAGS'],
                       '--xla_cpu_experimental_ynn_fusion_type=reduce')
      for off in ('0', 'off', 'False'):
        env = {platforms.OPT_OUT: off}
        self.assertFalse(platforms.tune_xla_cpu(env))
        self.assertNotIn('XLA_FLAGS', env)
      with absltest.mock.patch('jaxlib.__version__', '0.99.0'):
        env = {}
        self.assertFalse(platforms.tune_xla_cpu(env))  # flag not known
        self.assertEqual(env, {})
    # In a fresh process, importing the package is enough: the reduction
    # compiles without YNNPACK (its fusion kind named in the program).
    code = ('import physsplat_jax, jax, jax.numpy as jnp, jaxlib, os\n'
            'y = jnp.ones((6000, 27, 4))\n'
            't = jax.jit(lambda y: (y * y).sum(1)).lower(y).compile()\n'
            'print(jaxlib.__version__, t.as_text().count("__ynn_fusion"))\n')
    env = {k: v for k, v in os.environ.items()
           if k not in ('XLA_FLAGS', platforms.OPT_OUT)}
    out = subprocess.run([sys.executable, '-c', code], capture_output=True,
                         text=True, timeout=120, check=True,
                         env=dict(env, JAX_PLATFORMS='cpu')).stdout.split()
    if out[0] in platforms._CPU_FLAG_JAXLIB:  # noqa: SLF001
      self.assertEqual(out[1], '0')
    # This process's backends have started: too late to apply.
    jax.devices()
    env = {}
    self.assertFalse(platforms.tune_xla_cpu(env))
    self.assertEqual(env, {})


_NO_TRITON = r"""
import sys
sys.modules['jax.experimental.pallas.triton'] = None  # as if removed
sys.path.insert(0, 'tests')
import jax, numpy as np
import mpm_blocks
from physsplat_jax import cameras, mpm, platforms, test_util
from physsplat_jax.mpm import pallas_constitutive
from physsplat_jax.render import raster
from physsplat_jax.types import make_camera
assert platforms.pallas_triton() is None
assert not pallas_constitutive.available('float32')
s, mat, forces, cfg = mpm_blocks.four_blocks(np.array([0.3, -0.2, -1.0]))
try:
  cfg.replace(constitutive_kernel='pallas')
except mpm.MPMInputError as e:
  print('SIM-ERROR', e)
final, _, _ = jax.jit(lambda s: mpm.rollout(s, mat, forces, cfg, 2))(s)
np.save(sys.argv[1], np.asarray(final.x))
g = test_util.random_gaussians(jax.random.PRNGKey(3), 200)
cam = make_camera(cameras.look_at(np.array([0.0, -3.5, 1.0]), np.zeros(3)),
                  60.0, 60.0, 48, 32)
print('AUTO', raster.RenderConfig().resolved_backend())
a = raster.render(g, cam, config=raster.RenderConfig(backend='jax')).image
b = raster.render(g, cam, config=raster.RenderConfig(
  backend='pallas', interpret=True)).image
print('INTERPRET', float(np.abs(np.asarray(a) - np.asarray(b)).max()))
try:
  raster.render(g, cam, config=raster.RenderConfig(backend='pallas'))
except raster.RenderConfigError as e:
  print('RENDER-ERROR', e)
"""


class NoTritonTest(absltest.TestCase):
  """A JAX without Pallas's Triton backend (deprecated in JAX 0.12):
  the package imports, 'auto' runs the pure-JAX forms with the same
  values, and asking for the kernels by name says what to change."""

  def test_the_package_runs_without_pallas_triton(self):
    with tempfile.TemporaryDirectory() as tmp:
      path = os.path.join(tmp, 'x.npy')
      root = pathlib.Path(__file__).parent.parent
      out = subprocess.run(
        [sys.executable, '-c', _NO_TRITON, path], capture_output=True,
        text=True, timeout=300, cwd=root,
        env=dict(os.environ, JAX_PLATFORMS='cpu'))
      self.assertEqual(out.returncode, 0, out.stderr[-3000:])
      x = np.load(path)
    lines = dict(line.split(' ', 1) for line in out.stdout.splitlines())
    for key in ('SIM-ERROR', 'RENDER-ERROR'):
      self.assertIn('no Pallas Triton backend', lines[key])
    self.assertIn("constitutive_kernel='auto' or 'jax'", lines['SIM-ERROR'])
    self.assertIn("backend='auto' or 'jax'", lines['RENDER-ERROR'])
    self.assertEqual(lines['AUTO'], 'jax')
    self.assertLess(float(lines['INTERPRET']), 1e-4)
    # This process has the backend: the same frames, to the bit.
    s, mat, forces, cfg = mpm_blocks.four_blocks(np.array([0.3, -0.2, -1.0]))
    final, _, _ = jax.jit(lambda s: mpm.rollout(s, mat, forces, cfg, 2))(s)
    np.testing.assert_array_equal(x, np.asarray(final.x))
    self.assertFalse(np.allclose(x, np.asarray(s.x)))  # it moved


class TraceTimeChoiceTest(absltest.TestCase):
  """``platforms.platform_dependent`` traces the CPU's form alone where only
  the CPU can run the program, every form inside ``every_platform``."""

  def test_cpu_form_alone_then_every_form(self):
    if not platforms.traced_for_cpu_only():
      self.skipTest('a GPU in this process: every form is traced anyway')

    def f(x):
      return platforms.platform_dependent(
        x, cpu=lambda y: y * 3.0, default=lambda y: y * 5.0)

    x = jnp.ones(4)
    jitted = jax.jit(f)
    self.assertTrue(platforms.traced_for_cpu_only())
    prims = {e.primitive.name for e in jax.make_jaxpr(f)(x).eqns}
    self.assertNotIn('platform_index', prims)
    self.assertNotIn('cond', prims)
    np.testing.assert_array_equal(jitted(x), 3.0 * np.ones(4))
    with platforms.every_platform():
      self.assertFalse(platforms.traced_for_cpu_only())
      prims = {e.primitive.name for e in jax.make_jaxpr(f)(x).eqns}
      self.assertIn('platform_index', prims)
      # The jitted function traced before is traced again (a cached
      # CPU-only trace would give CUDA the CPU's form): 5 for CUDA.
      cuda = jitted.trace(x).lower(lowering_platforms=('cuda',)).as_text()
      self.assertRegex(cuda, r'5\.0+e\+00')
      self.assertNotRegex(cuda, r'3\.0+e\+00')
      np.testing.assert_array_equal(jitted(x), 3.0 * np.ones(4))
    self.assertTrue(platforms.traced_for_cpu_only())
    with self.assertRaisesRegex(ValueError, 'no branch for the CPU'):
      platforms.platform_dependent(x, cuda=lambda y: y)


class KernelCountTest(absltest.TestCase):
  """experiments/lib/hlo.py, which experiments/gpu_kernels.py uses."""

  def test_counts_a_known_program(self):
    got = hlo.substep_kernels(_HLO, 5)
    # The nested loop: 3 x 1 fusion; then a copy and an input fusion.
    self.assertEqual(got['by_kind'], {'copy': 1, 'fusion:kInput': 1,
                                      'loop': 3})
    self.assertEqual(got['kernels'], 5)
    with self.assertRaisesRegex(ValueError, 'trip count 7'):
      hlo.substep_kernels(_HLO, 7)

  def test_counts_a_compiled_scan(self):
    def f(x):
      def body(c, _):
        c = jnp.sin(c) * 2 + c[::-1]
        c = jax.lax.fori_loop(0, 3, lambda i, y: jnp.cos(y) + y[::-1], c)
        return c, None
      return jax.lax.scan(body, x, None, length=5)[0]

    got = hlo.substep_kernels(
      jax.jit(f).lower(jnp.ones(100)).compile().as_text(), 5)
    self.assertEqual(got['kernels'], sum(got['by_kind'].values()))
    self.assertGreater(got['by_kind']['loop'], 0)
    self.assertEqual(got['by_kind']['loop'] % 3, 0)


class PtxasReportTest(absltest.TestCase):
  """experiments/lib/ptxas.py: occupancy from ptxas' registers and the
  launches XLA dumps (ptxas itself runs only where a CUDA jaxlib is)."""

  def test_h100_limits_and_occupancy(self):
    spec = (pathlib.Path(__file__).parent.parent / 'experiments' / 'configs'
            / 'gpu_specs' / 'h100_sxm.txtpb').read_text()
    limits = ptxas.spec_limits(spec)
    self.assertEqual(limits['arch'], 'sm_90a')
    self.assertEqual(limits['registers'], 65536)
    # (registers, threads, shared bytes) -> resident warps per SM.
    cases = {(227, 128, 512): 8,  # registers bound: 2 blocks of 4 warps
             (255, 128, 512): 8,
             (113, 256, 512): 16,
             (32, 64, 8): 64,  # threads bound: 2048 per SM
             (64, 32, 0): 32,  # blocks bound: 32 per SM
             (32, 256, 120_000): 8}  # shared memory bound: 1 block
    for (regs, threads, shared), warps in cases.items():
      with self.subTest(regs=regs, threads=threads, shared=shared):
        self.assertEqual(
          ptxas.occupancy(regs, threads, shared, limits), warps)

  def test_reads_launches_from_a_thunk_dump(self):
    line = ('002: kCustomKernel [prev=001 (1) | next=003 (1)] splat_forward '
            'grid: [16384, 1, 1] threads: [64, 1, 1]  shared_memory: 8 '
            'bytes\n')
    with tempfile.TemporaryDirectory() as d:
      pathlib.Path(d, 'm.thunk_sequence.txt').write_text(line)
      self.assertEqual(ptxas._launches(d), {'splat_forward': (64, 8)})


if __name__ == '__main__':
  absltest.main()
