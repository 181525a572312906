"""Tests of MLLM-P3 perception against a scripted chat-completions server."""

import base64
import io
import json
import os
import tempfile
import time
from unittest import mock

import imageio.v3 as iio
import jax
import jax.numpy as jnp
import numpy as np
from absl.testing import absltest
from absl.testing import parameterized

from physsplat_jax import perception
from physsplat_jax.io import mllm
from physsplat_jax.perception import p3
from physsplat_jax.perception import parsing
from physsplat_jax.perception import prompts
from physsplat_jax.types import Gaussians
from physsplat_jax.types import ObjectInfo
from physsplat_jax.types import Scene
from mllm_test_server import Reply
from mllm_test_server import ScriptedChatServer
from mllm_test_server import user_text

_TIMEOUT_S = 0.3
_VIEW = np.full((8, 8, 3), 0.5, np.float32)  # stands in for a render
_LIB = perception.default_library()


def _blob(key, center, color, n=40):
  k1, k2 = jax.random.split(key)
  means = jnp.asarray(center) + 0.1 * jax.random.normal(k1, (n, 3))
  sh = jnp.broadcast_to((jnp.asarray(color) - 0.5) / 0.28209479, (n, 1, 3))
  return Gaussians(
    means=means, log_scales=jnp.full((n, 3), -3.0),
    quats=jnp.tile(jnp.asarray([[1.0, 0, 0, 0]]), (n, 1)),
    opacity_logits=jnp.full((n,), 3.0), sh=sh,
  ), n


def _scene(names=('metal can', 'rubber ball'), materials=None):
  materials = materials or (None,) * len(names)
  parts, ids = [], []
  for i, _ in enumerate(names):
    g, n = _blob(jax.random.PRNGKey(i), (i * 1.0, 0.0, 0.0),
                 (0.8, 0.2 + 0.3 * i, 0.2))
    parts.append(g)
    ids.append(np.full(n, i, np.int32))
  from physsplat_jax.types import concatenate_gaussians
  return Scene(
    gaussians=concatenate_gaussians(parts),
    object_ids=jnp.asarray(np.concatenate(ids)),
    objects=tuple(ObjectInfo(n, m) for n, m in zip(names, materials)),
  )


def _answers(material='aluminum', props=None, rigid=True, scores=None,
             caption='A shiny silver drink can made of thin aluminium.'):
  """A script that answers each task well (per-task overrides)."""
  props = props if props is not None else {
    'density_kg_m3': 2700.0, 'youngs_modulus_pa': 6.9e10,
    'poisson_ratio': 0.33}
  cands = {'candidates': [{'material': material, 'reason': 'looks like it'},
                          {'material': 'steel', 'reason': 'metal'},
                          {'material': 'hard plastic', 'reason': 'maybe'}],
           'rigid': rigid}
  scores = scores if scores is not None else {
    'scores': {material: 0.9, 'steel': 0.4, 'hard plastic': 0.1}}
  return {
    'caption': caption,
    'candidates': json.dumps(cands),
    'score': json.dumps(scores),
    'properties': json.dumps(props) if isinstance(props, dict) else props,
  }


def _script(answers, special=None):
  """Routes by TASK; ``special(task, n_task) -> Reply | None`` can intercept."""
  counts = {}

  def script(req, n):
    task = prompts.task_of(user_text(req))
    counts[task] = counts.get(task, 0) + 1
    if special is not None:
      r = special(task, counts[task])
      if r is not None:
        return r
    return Reply(text=answers[task])

  return script


def _options(url, **kw):
  cfg = mllm.MLLMConfig(base_url=url, model='test-vlm',
                        cache_dir=kw.pop('cache_dir', None),
                        timeout_s=kw.pop('timeout_s', 5.0),
                        max_retries=kw.pop('max_retries', 2),
                        request_deadline_s=kw.pop('request_deadline_s', 60.0),
                        scene_deadline_s=kw.pop('scene_deadline_s', 300.0),
                        backoff_s=0.0)
  return perception.PerceptionOptions(mllm=cfg, **kw)


def _run(script, names=('metal can',), **kw):
  scene = _scene(names[:1] if len(names) == 1 else names)
  with ScriptedChatServer(script) as s:
    opts = _options(s.url, **kw)
    images = {i: _VIEW for i in range(len(scene.objects))}
    choices = perception.perceive_scene(scene, opts, images=images)
    return choices, s


def _cut(text):
  """A reply the server stopped at max_tokens."""
  return Reply(body=json.dumps({'choices': [{
    'index': 0, 'finish_reason': 'length',
    'message': {'role': 'assistant', 'content': text}}]}))


class MllmPathTest(parameterized.TestCase):

  def assertValid(self, c):
    perception.choice.check_choice(c)
    self.assertIn(c.material_key, _LIB)
    self.assertGreater(c.E, 0)
    self.assertTrue(0 <= c.nu < 0.5)
    self.assertGreater(c.rho, 0)

  def test_good_answers(self):
    with self.assertLogs('absl', level='INFO') as logs:
      (c,), s = _run(_script(_answers()))
    self.assertValid(c)
    self.assertEqual((c.source, c.material_key, c.rigid, c.warnings),
                     ('mllm', 'aluminum', True, ()))
    self.assertEqual(c.candidates, ('aluminum', 'steel', 'hard_plastic'))
    self.assertIn('picked aluminum by mllm_score+text+rank', c.reason)
    self.assertEqual(c.caption, _answers()['caption'])
    self.assertAlmostEqual(c.E_real, 6.9e10)
    e = _LIB['aluminum']
    want = perception.simulation_values(e, _LIB, 6.9e10, 0.33, 2700.0)
    self.assertAlmostEqual(c.E, want[0])
    self.assertEqual((c.nu, c.rho), (0.33, 2700.0))
    self.assertEqual(s.num_requests, 4)  # caption, candidates, score, props
    # The image went out as a PNG data URL.
    url = s.requests[0]['messages'][-1]['content'][1]['image_url']['url']
    png = base64.b64decode(url.split(',', 1)[1])
    self.assertEqual(iio.imread(io.BytesIO(png)).shape, (8, 8, 3))
    line = [x for x in logs.output if "object 0 'metal can'" in x]
    self.assertLen(line, 1)
    self.assertIn('via mllm: MLLM-P3', line[0])

  def test_visual_score_decides(self):
    # The MLLM lists steel first but scores aluminium highest.
    a = _answers(material='steel', scores={
      'scores': {'steel': 0.1, 'aluminium': 0.95, 'hard plastic': 0.1}})
    a['candidates'] = json.dumps({'candidates': ['steel', 'aluminium',
                                                 'plastic'], 'rigid': True})
    (c,), _ = _run(_script(a))
    self.assertEqual(c.material_key, 'aluminum')
    self.assertIn('mllm_score+text+rank', c.reason)

  def test_malformed_json_then_fixed(self):
    bad = lambda task, n: (Reply(text='Sure! The materials are aluminium '
                                 'and steel.')
                           if task == 'candidates' and n == 1 else None)
    (c,), s = _run(_script(_answers(), bad))
    self.assertValid(c)
    self.assertEqual((c.source, c.material_key), ('mllm', 'aluminum'))
    self.assertTrue(any('candidates answer unusable (malformed JSON' in w
                        and 'asked again' in w for w in c.warnings),
                    c.warnings)
    self.assertEqual(s.num_requests, 5)
    repair = [user_text(r) for r in s.requests
              if 'could not be used' in user_text(r)]
    self.assertLen(repair, 1)

  def test_malformed_json_falls_back(self):
    bad = lambda task, n: Reply(text='{"candidates": [aluminium,')\
      if task == 'candidates' else None
    with self.assertLogs('absl', level='WARNING') as logs:
      (c,), _ = _run(_script(_answers(), bad))
    self.assertValid(c)
    self.assertEqual((c.source, c.material_key), ('library', 'aluminum'))
    self.assertIn('MLLM-P3 failed, fell back to the library', c.reason)
    self.assertIn("name 'metal can' matched alias", c.reason)
    self.assertTrue(any('candidates answer unusable: malformed JSON' in w
                        for w in c.warnings), c.warnings)
    self.assertTrue(any('via library' in x and 'warnings:' in x
                        for x in logs.output))

  @parameterized.named_parameters(
    ('nu_0p7', {'density_kg_m3': 2700, 'youngs_modulus_pa': 7e10,
                'poisson_ratio': 0.7},
     ('nu',), 'nu=0.7 is outside [0, 0.5)'),
    ('E_negative', {'density_kg_m3': 2700, 'youngs_modulus_pa': -3e9,
                    'poisson_ratio': 0.33},
     ('E',), 'is not positive and finite'),
    ('E_zero_string', {'density_kg_m3': 2700, 'youngs_modulus_pa': 'zero',
                       'poisson_ratio': 0.33},
     ('E',), "'zero' is not a number"),
    ('rho_negative', {'density_kg_m3': -1, 'youngs_modulus_pa': 7e10,
                      'poisson_ratio': 0.33},
     ('rho',), 'density=-1 is not positive'),
    ('E_absurd', {'density_kg_m3': 2700, 'youngs_modulus_pa': 2.0e3,
                  'poisson_ratio': 0.33},
     ('E',), 'outside the plausible range of aluminum'),
  )
  def test_out_of_range_values(self, props, from_lib, message):
    (c,), _ = _run(_script(_answers(props=props)))
    self.assertValid(c)
    self.assertEqual((c.source, c.material_key), ('mllm', 'aluminum'))
    e = _LIB['aluminum']
    self.assertTrue(any(message in w for w in c.warnings), c.warnings)
    self.assertTrue(any(f'{"/".join(from_lib)} from the library' in w
                        for w in c.warnings), c.warnings)
    if 'E' in from_lib:
      self.assertAlmostEqual(c.E_real, e.E_mid)
      self.assertAlmostEqual(c.E, e.E_sim)
    if 'nu' in from_lib:
      self.assertAlmostEqual(c.nu, min(e.poisson_ratio.mid, 0.45))
    if 'rho' in from_lib:
      self.assertAlmostEqual(c.rho, e.density.geometric_mid)

  def test_gpa_as_pa(self):
    props = {'density_kg_m3': 2700, 'youngs_modulus_pa': 70,
             'poisson_ratio': 0.33}
    (c,), _ = _run(_script(_answers(props=props)))
    self.assertValid(c)
    self.assertAlmostEqual(c.E_real, 7e10)
    self.assertTrue(any('read as 7e+10 Pa (unit slip x1e+09)' in w
                        for w in c.warnings), c.warnings)

  def test_units_in_strings(self):
    props = {'density': '2.7 g/cm3', 'youngs_modulus': '69 GPa', 'nu': 0.33}
    (c,), _ = _run(_script(_answers(props=props)))
    self.assertAlmostEqual(c.E_real, 6.9e10)
    self.assertAlmostEqual(c.rho, 2700.0)
    self.assertIn('youngs_modulus given in GPa', c.warnings)

  def test_http_500_then_success(self):
    flaky = lambda task, n: Reply(status=500, body='{"error": "overloaded"}')\
      if task == 'caption' and n == 1 else None
    with self.assertLogs('absl', level='WARNING') as logs:
      (c,), s = _run(_script(_answers(), flaky))
    self.assertEqual((c.source, c.material_key, c.warnings),
                     ('mllm', 'aluminum', ()))
    self.assertEqual(s.num_requests, 5)
    self.assertTrue(any('attempt 1 failed (HTTP 500' in x and 'retrying' in x
                        for x in logs.output), logs.output)

  def test_http_500_always(self):
    down = lambda task, n: Reply(status=500, body='{"error": "down"}')
    (c,), s = _run(_script(_answers(), down), max_retries=1)
    self.assertEqual((c.source, c.material_key), ('library', 'aluminum'))
    self.assertEqual(s.num_requests, 2)
    self.assertTrue(any('caption request failed: HTTP 500' in w
                        and 'after 2 attempts' in w for w in c.warnings),
                    c.warnings)

  def test_hang_past_timeout(self):
    hang = lambda task, n: Reply(text='late', delay_s=3.0)
    (c,), _ = _run(_script(_answers(), hang), timeout_s=_TIMEOUT_S,
                   max_retries=0)
    self.assertEqual((c.source, c.material_key), ('library', 'aluminum'))
    self.assertTrue(any('no answer from' in w and 'within 0.3 s' in w
                        for w in c.warnings), c.warnings)

  def test_bad_scores_use_text(self):
    bad = lambda task, n: Reply(text='I cannot score these.')\
      if task == 'score' else None
    (c,), _ = _run(_script(_answers(), bad))
    self.assertEqual((c.source, c.material_key), ('mllm', 'aluminum'))
    self.assertIn('by text+rank', c.reason)
    self.assertTrue(any('picked by text similarity and rank only' in w
                        for w in c.warnings), c.warnings)

  def test_unknown_candidates_fall_back(self):
    a = _answers()
    a['candidates'] = json.dumps({'candidates': ['unobtainium', 'vibranium'],
                                  'rigid': True})
    (c,), _ = _run(_script(a))
    self.assertEqual(c.source, 'library')
    self.assertTrue(any('none of the candidates maps to a library material'
                        in w for w in c.warnings), c.warnings)

  def test_rigid_sand_is_not_rigid(self):
    a = _answers(material='sand', props={
      'density_kg_m3': 1600, 'youngs_modulus_pa': 3e7, 'poisson_ratio': 0.3},
      caption='A pile of dry tan sand grains.')
    (c,), _ = _run(_script(a), names=('sand pile',))
    self.assertEqual((c.material_key, c.rigid), ('sand', False))
    self.assertTrue(any('rigid=true ignored' in w for w in c.warnings))

  def test_cache_makes_rerun_free(self):
    with tempfile.TemporaryDirectory() as d:
      scene = _scene(('metal can', 'drink can'))  # both answered aluminium
      images = {0: _VIEW, 1: _VIEW * 0.5}
      a = _answers()
      with ScriptedChatServer(_script(a)) as s:
        first = perception.perceive_scene(
          scene, _options(s.url, cache_dir=d), images=images)
        n1 = s.num_requests
        second = perception.perceive_scene(
          scene, _options(s.url, cache_dir=d), images=images)
        self.assertEqual(s.num_requests, n1)
    self.assertEqual(n1, 8)
    self.assertEqual(first, second)

  def test_unusable_answers_are_not_replayed(self):
    # An empty caption and a candidates answer cut at max_tokens were
    # cached: every rerun replayed them (0 requests) and failed again.
    cut = lambda task, n: (_cut('{"candidates": [{"material": "alumin')
                           if task == 'candidates' else None)
    for answers, special, want in (
        (_answers(caption=''), None, 'caption answer is empty'),
        (_answers(), cut, 'candidates answer unusable: malformed JSON: .*'
         r'answer cut at max_tokens=512 \(finish_reason=length\); raise '
         '--mllm_max_tokens')):
      with self.subTest(want), tempfile.TemporaryDirectory() as d:
        (c,), _ = _run(_script(answers, special), cache_dir=d)
        self.assertEqual(c.source, 'library')
        self.assertRegex(c.warnings[0], 'MLLM-P3 failed: ' + want)
        (c,), s = _run(_script(_answers()), cache_dir=d)
        self.assertEqual((c.source, c.warnings), ('mllm', ()))
        self.assertGreater(s.num_requests, 0)

  def test_cut_caption_is_used_with_a_warning(self):
    cut = lambda task, n: _cut('A shiny silver drink can made of') if (
      task == 'caption') else None
    (c,), _ = _run(_script(_answers(), cut))
    self.assertEqual((c.source, c.caption),
                     ('mllm', 'A shiny silver drink can made of'))
    self.assertIn('caption answer cut at max_tokens=512 (finish_reason='
                  'length); raise --mllm_max_tokens', c.warnings)

  def test_bad_cached_answer_names_the_cache(self):
    # An unusable answer left in the cache (by an older version): the
    # message names the cache file and the flag, and the entry is deleted.
    bad = lambda task, n: Reply(text='no json') if task == 'candidates' \
      else None
    with tempfile.TemporaryDirectory() as d:
      with mock.patch.object(mllm.MLLMClient, 'evict', return_value=None):
        (c,), _ = _run(_script(_answers(), bad), cache_dir=d, json_retries=0)
        (c,), s = _run(_script(_answers()), cache_dir=d, json_retries=0)
      self.assertRegex(c.warnings[0], 'candidates answer unusable: .*'
                       f'replayed from cache {d}/.*json; delete it or pass '
                       '--mllm_cache_dir=')
      (c,), s = _run(_script(_answers()), cache_dir=d, json_retries=0)
      self.assertIn(f'replayed from cache {d}/', c.warnings[0])
      self.assertIn('now deleted (the next run asks again', c.warnings[0])
      (c,), s = _run(_script(_answers()), cache_dir=d, json_retries=0)
      self.assertEqual((c.source, s.num_requests), ('mllm', 3))

  def test_401_falls_back_at_once_naming_the_key(self):
    deny = lambda task, n: Reply(status=401, body='{"error": "bad key"}')
    env = {k: v for k, v in os.environ.items() if k != 'OPENAI_API_KEY'}
    with mock.patch.dict(os.environ, env, clear=True):
      cs, s = _run(_script(_answers(), deny),
                   names=('metal can', 'rubber ball', 'sand pile'))
    self.assertEqual(s.num_requests, 1)
    self.assertEqual([c.source for c in cs], ['library'] * 3)
    for c in cs:
      self.assertIn('no API key was sent: OPENAI_API_KEY is unset '
                    '(--mllm_api_key_env)', c.warnings[0])
    self.assertIn('not asked again', cs[2].warnings[0])

  def test_rigid_answer_for_a_soft_material_warns(self):
    a = _answers(material='jelly', caption='A wobbly green jelly cube.',
                 props={'density_kg_m3': 1050, 'youngs_modulus_pa': 5e4,
                        'poisson_ratio': 0.45},
                 scores={'scores': {'jelly': 0.9, 'steel': 0.1}})
    (c,), _ = _run(_script(a), names=('jelly cube',))
    self.assertEqual((c.source, c.material_key, c.rigid),
                     ('mllm', 'jelly', True))
    self.assertTrue(any(
      "object 'jelly cube': the MLLM says rigid=true but the library "
      'simulates jelly as deformable (rigid=false' in w
      for w in c.warnings), c.warnings)

  @parameterized.named_parameters(
    ('json_retries', {'json_retries': -1}, 'json_retries', '0..10'),
    ('E_slack', {'E_slack': 0}, 'E_slack', '>= 1'),
    ('rho_slack_nan', {'rho_slack': float('nan')}, 'rho_slack', '>= 1'),
    ('nu_slack_nan', {'nu_slack': float('nan')}, 'nu_slack', r'\[0, 0.5\]'),
    ('weights_negative', {'score_weights': (-1, 0, 0)}, 'score_weights',
     'three finite numbers >= 0'),
    ('weights_two', {'score_weights': (1, 0)}, 'score_weights',
     'three finite numbers'),
    ('max_E_ratio_nan', {'max_E_ratio': float('nan')}, 'max_E_ratio',
     '>= 1'),
  )
  def test_bad_options_fail_up_front(self, kw, field, allowed):
    with ScriptedChatServer(_script(_answers())) as s:
      with self.assertRaisesRegex(
          perception.PerceptionError,
          rf'PerceptionOptions\.{field} must be .*{allowed}.*, got'):
        perception.perceive_scene(_scene(('metal can',)),
                                  _options(s.url, **kw), images={0: _VIEW})
      self.assertEqual(s.num_requests, 0)

  @parameterized.named_parameters(
    ('2d', {0: np.zeros((8, 8))}, r'images\[0\]: expected an \(H, W, 3\) '
     r'or \(H, W, 4\) image.*got shape \(8, 8\)'),
    ('bad_view', {0: [_VIEW, np.zeros((4, 4, 2))]},
     r'images\[0\]\[1\]: expected .*got shape \(4, 4, 2\)'),
    ('index', {3: _VIEW}, r'images\[3\]: no such object; .* has 1 '
     r'object\(s\), indices 0\.\.0'),
  )
  def test_bad_images(self, images, want):
    with self.assertRaisesRegex(perception.PerceptionError, want):
      perception.perceive_scene(_scene(('metal can',)), images=images)

  @parameterized.named_parameters(
    ('name', 'metal can', 'A wobbly green jelly.',
     "'jelly' (food) contradicts the name 'metal can', which says "
     'aluminum (metal), steel (metal)'),
    # 'beverage can' names no material (keywords only): the caption decides.
    ('appearance', 'beverage can',
     'A shiny silver drink can made of aluminium.',
     "'jelly' (food) contradicts the caption 'A shiny silver drink can "
     "made of aluminium.', which says aluminum (metal)"))
  def test_implausible_answer_is_rejected(self, name, caption, why):
    a = _answers(material='jelly', caption=caption, scores={
      'scores': {'jelly': 0.9, 'steel': 0.1, 'hard plastic': 0.1}})
    with self.assertLogs('absl', level='WARNING') as logs:
      (c,), _ = _run(_script(a), names=(name,))
    self.assertEqual((c.source, c.material_key), ('library', 'aluminum'))
    self.assertEqual(c.warnings[0],
                     'MLLM-P3 answer rejected as implausible: ' + why)
    line = [x for x in logs.output if f"object 0 '{name}'" in x]
    self.assertLen(line, 1)
    self.assertIn('implausible', line[0])
    self.assertNotIn('\n', line[0])

  def test_plausible_answers_are_kept(self):
    lib = _LIB
    self.assertIsNone(perception.plausibility(
      'thing', 'A wobbly green jelly cube.', lib['jelly'], lib))
    self.assertIsNone(perception.plausibility(
      'rubber ball', 'A red ball.', lib['silicone'], lib))  # both elastomer
    self.assertIsNone(perception.plausibility(
      'gizmo', 'A small object.', lib['jelly'], lib))  # no evidence
    self.assertIn('contradicts the name', perception.plausibility(
      'rubber ball', 'A red ball.', lib['steel'], lib))

  def test_scene_deadline_with_slow_drip_server(self):
    # The server drips one byte every 50 ms (no per-read timeout fires);
    # 0.3 s per question and 0.5 s per scene end it: every object falls
    # back to the library and the third asks nothing.
    drip = lambda req, n: Reply(text='A can.', drip_s=0.05)
    scene = _scene(('metal can', 'rubber ball', 'sand pile'))
    with ScriptedChatServer(drip) as s:
      opts = _options(s.url, timeout_s=2.0, request_deadline_s=0.3,
                      scene_deadline_s=0.5)
      t0 = time.perf_counter()
      cs = perception.perceive_scene(scene, opts,
                                     images={i: _VIEW for i in range(3)})
      elapsed = time.perf_counter() - t0
      self.assertEqual(s.num_requests, 2)
    self.assertLess(elapsed, 2.0)
    self.assertEqual([c.source for c in cs], ['library'] * 3)
    self.assertEqual([c.material_key for c in cs],
                     ['aluminum', 'rubber', 'sand'])
    self.assertIn('within the 0.3 s deadline', cs[0].warnings[0])
    self.assertIn('deadline', cs[1].warnings[0])
    self.assertEqual(cs[2].warnings[0], 'MLLM-P3 skipped: the scene '
                     'deadline (0.5 s) has passed')

  def test_scene_material_first(self):
    scene = _scene(('thing',), ('rubber',))
    with ScriptedChatServer(_script(_answers())) as s:
      (c,) = perception.perceive_scene(
        scene, _options(s.url, scene_material_first=True),
        images={0: _VIEW})
      self.assertEqual(s.num_requests, 0)
    self.assertEqual((c.source, c.material_key), ('library', 'rubber'))


class OfflineTest(parameterized.TestCase):

  def test_names_and_scene_keys(self):
    scene = _scene(('metal can', 'Ficus leaves', 'thing', 'blob'),
                   (None, None, 'terracotta', None))
    with self.assertLogs('absl', level='INFO') as logs:
      cs = perception.perceive_scene(scene)
    self.assertEqual([c.material_key for c in cs],
                     ['aluminum', 'leaf', 'terracotta', 'jelly'])
    self.assertEqual({c.source for c in cs}, {'library'})
    self.assertIn("scene material key 'terracotta'", cs[2].reason)
    self.assertIn("name 'blob' matched nothing", ' '.join(cs[3].warnings)
                  .replace('matched no library material', 'matched nothing'))
    # The warning says how to choose a material and names library keys.
    self.assertIn('--material_override="blob=KEY"', cs[3].warnings[-1])
    self.assertIn('steel', cs[3].warnings[-1])
    lines = [x for x in logs.output if 'perception: object' in x]
    self.assertLen(lines, 4)
    self.assertIn('offline (library)', ' '.join(logs.output))
    self.assertTrue(lines[3].startswith('WARNING'))
    leaf = _LIB['leaf']
    self.assertEqual((cs[1].E, cs[1].nu, cs[1].rho),
                     (leaf.E_sim, leaf.nu_sim, leaf.rho_sim))

  def test_no_default_raises(self):
    scene = _scene(('blob',))
    with self.assertRaisesRegex(perception.MaterialNotFoundError,
                                "object 'blob'.*override"):
      perception.perceive_scene(
        scene, perception.PerceptionOptions(default_material=None))

  def test_overrides_and_config(self):
    scene = _scene(('metal can', 'rubber ball', 'cube'))
    opts = perception.PerceptionOptions(
      overrides={'metal can': 'sheet metal',
                 'rubber ball': {'E': 3e5, 'nu': 0.4}},
      config_materials={'*': {'material': 'jelly', 'E': 2e4}})
    a, b, c = perception.perceive_scene(scene, opts)
    self.assertEqual((a.source, a.material_key, a.rigid),
                     ('override', 'sheet_metal', False))
    self.assertEqual((b.source, b.material_key, b.E, b.nu),
                     ('override', 'rubber', 3e5, 0.4))
    self.assertIn("with ['E', 'nu']", b.reason)
    self.assertEqual((c.source, c.material_key, c.E), ('config', 'jelly',
                                                       2e4))

  def test_keys_naming_no_object_are_refused(self):
    # A misspelt name was ignored: the object silently got another
    # material. Names, indices as strings and '*' all match.
    scene = _scene(('metal can', 'cube'))
    for field in ('overrides', 'config_materials'):
      for key in ('metal cam', 2, '2'):
        opts = perception.PerceptionOptions(**{field: {key: 'rubber'}})
        with self.subTest(field=field, key=key), self.assertRaisesRegex(
            perception.MaterialChoiceError,
            rf"PerceptionOptions\.{field} names \[{key!r}\] but scene .* has "
            r"no such object; its objects are \['metal can', 'cube'\]"):
          perception.perceive_scene(scene, opts)
    a, b = perception.perceive_scene(scene, perception.PerceptionOptions(
      overrides={'1': 'wood'}, config_materials={'*': 'jelly',
                                                 'metal can': 'rubber'}))
    self.assertEqual((a.source, a.material_key), ('config', 'rubber'))
    self.assertEqual((b.source, b.material_key), ('override', 'wood'))

  def test_physgaussian_config(self):
    from physsplat_jax.physgaussian import parse_config
    cfg = parse_config({'material': 'metal', 'E': 1e5, 'nu': 0.3,
                        'density': 1000, 'yield_stress': 1e2})
    spec = perception.spec_from_physgaussian(cfg)
    (c,) = perception.perceive_scene(
      _scene(('plane',)),
      perception.PerceptionOptions(config_materials={'*': spec}))
    self.assertEqual((c.source, c.model, c.E, c.nu, c.rho),
                     ('config', 'von_mises', 1e5, 0.3, 1000.0))
    self.assertEqual(c.params_dict['yield_stress'], 1e2)

  def test_override_names_read_as_keys_aliases_and_phrases(self):
    scene = _scene(('cube',))
    for spec in ('rubber', 'Rubber', 'rubber ball', 'natural rubber'):
      with self.subTest(spec):
        (m,) = perception.perceive_scene(
          scene, perception.PerceptionOptions(overrides={'cube': spec}))
        self.assertEqual((m.source, m.material_key), ('override', 'rubber'))

  def test_override_beats_mllm(self):
    scene = _scene(('metal can',))
    with ScriptedChatServer(_script(_answers())) as s:
      (c,) = perception.perceive_scene(
        scene, _options(s.url, overrides={'metal can': 'wood'}),
        images={0: _VIEW})
      self.assertEqual(s.num_requests, 0)
    self.assertEqual((c.source, c.material_key), ('override', 'wood'))

  @parameterized.named_parameters(
    ('unknown_key', 'unobtainium', 'not in the library; give a library '
     "key or alias, such as 'titanium'"),
    ('unknown_key_nothing_close', 'xyzzy', 'give a library key or alias, '
     r"such as 'aluminum', .* \(all 54: "),
    # A close spelling was taken for the key without a word ('rubbr' ran
    # as rubber); a typo's nearest key may be another material.
    ('typo', 'rubbr', r"not in the library; did you mean 'rubber'\? Write "
     'the key exactly'),
    ('typo_in_mapping', {'material': 'steal', 'E': 1e9},
     r"did you mean 'steel'\?"),
    ('bad_nu', {'material': 'jelly', 'nu': 0.6}, 'nu=0.6'),
    ('bad_field', {'material': 'jelly', 'colour': 'red'},
     r"unknown field\(s\) \['colour'\]"),
    ('bad_model', {'material': 'jelly', 'model': 'gooey'}, "'gooey'"),
    # Out-of-range model parameters (accepted before; they blew up a frame
    # later, blamed on the time step).
    ('bad_angle', {'material': 'sand', 'friction_angle': 95.0},
     r'friction_angle=95\.0 \(use an angle in \[0, 90\) deg\)'),
    ('bad_theta', {'material': 'snow', 'theta_c': -0.1},
     r'theta_c=-0\.1 \(use a critical compression'),
    # One of an alias pair silently won; a parameter the model does not
    # take was silently ignored.
    ('alias_pair', {'material': 'jelly', 'rho': 1000, 'density': 5},
     r"both 'rho' \(1000\) and 'density' \(5\) are given"),
    ('param_not_taken', {'material': 'jelly', 'yield_stress': 5},
     r"model 'fixed_corotated' \(jelly\) takes no parameter\(s\) "
     r"\['yield_stress'\]; its parameters: \['viscosity', 'maxwell_E'"),
    ('negative_viscosity', {'material': 'jelly', 'viscosity': -1.0},
     r'viscosity=-1\.0 \(use a viscosity >= 0'),
  )
  def test_bad_override(self, spec, pattern):
    scene = _scene(('cube',))
    with self.assertRaisesRegex(ValueError, "override for object 'cube'.*"
                                + pattern):
      perception.perceive_scene(
        scene, perception.PerceptionOptions(overrides={'cube': spec}))

  def test_a_solids_viscosity_override_is_kept(self):
    # A solid's Kelvin-Voigt damping (docs/mpm.md): the pipeline turns the
    # solver's dashpot on from this parameter.
    scene = _scene(('cube',))
    (m,) = perception.perceive_scene(
      scene, perception.PerceptionOptions(
        overrides={'cube': {'material': 'jelly', 'viscosity': 20.0}}))
    self.assertEqual(m.model, 'fixed_corotated')
    self.assertEqual(m.params_dict['viscosity'], 20.0)
    # A Maxwell branch (docs/mpm.md), checked against its ranges.
    (m,) = perception.perceive_scene(
      scene, perception.PerceptionOptions(overrides={'cube': {
        'material': 'jelly', 'maxwell_E': 2e4, 'maxwell_viscosity': 50.0}}))
    self.assertEqual(m.params_dict['maxwell_E'], 2e4)
    with self.assertRaisesRegex(ValueError, r'maxwell_nu=0\.7 \(use a '):
      perception.perceive_scene(scene, perception.PerceptionOptions(
        overrides={'cube': {'material': 'jelly', 'maxwell_nu': 0.7}}))
    # On a foam, likely meant as its flow's plastic_viscosity: said so.
    with self.assertLogs(level='WARNING') as logs:
      perception.perceive_scene(scene, perception.PerceptionOptions(
        overrides={'cube': {'material': 'foam', 'viscosity': 5.0}}))
    self.assertIn('its flow\'s viscosity is "plastic_viscosity"',
                  ' '.join(logs.output))

  def test_parse_overrides(self):
    self.assertEqual(
      perception.parse_overrides(['a=wood;b=sand', 'c={"E": 1e4}']),
      {'a': 'wood', 'b': 'sand', 'c': {'E': 1e4}})
    with self.assertRaisesRegex(ValueError, 'expected name=key'):
      perception.parse_overrides(['rubber'])
    self.assertEqual(
      perception.parse_overrides(['a={"E": 1e4, "nu": 0.3}', 'b=wood;']),
      {'a': {'E': 1e4, 'nu': 0.3}, 'b': 'wood'})
    for items, want in (
        (['a={"material":"jelly"};b=wood'],
         "pass 'b=wood' as a separate --material_override"),
        (['a=wood', 'a=sand'], "object 'a' is already given"),
        ('a=wood;a={"E": 1}', "object 'a' is already given")):
      with self.subTest(items), self.assertRaisesRegex(
          perception.MaterialChoiceError, want):
        perception.parse_overrides(items)

  def test_flags(self):
    from absl import flags
    fv = flags.FlagValues()
    perception.define_flags(fv)
    perception.define_flags(fv)
    fv(['p', '--material_override=ball=rubber', '--default_material=',
        '--perception_candidates=3', '--mllm_base_url=http://127.0.0.1:1/v1',
        '--perception_views=2', '--mllm_scene_deadline=30'])
    o = perception.options_from_flags(fv)
    self.assertEqual((o.overrides, o.default_material, o.num_candidates,
                      o.mllm.base_url, o.num_views, o.mllm.scene_deadline_s),
                     ({'ball': 'rubber'}, None, 3, 'http://127.0.0.1:1/v1',
                      2, 30.0))


class ParsingTest(absltest.TestCase):

  def test_extract_json(self):
    self.assertEqual(parsing.extract_json('```json\n{"a": 1}\n```'),
                     {'a': 1})
    self.assertEqual(parsing.extract_json('Here: {"a": {"b": "}"}} ok'),
                     {'a': {'b': '}'}})
    self.assertEqual(parsing.extract_json("{'a': True}"), {'a': True})
    for bad in ('', 'no json here', '[1, 2]', '{"a": '):
      with self.assertRaises(parsing.AnswerError):
        parsing.extract_json(bad)

  def test_property_strings(self):
    al = _LIB['aluminum']
    for props, key, want in (
        # '× 10^n' read as '×' a unit: 7 Pa, then a 'unit slip' to 7e9.
        ({'E': '7.0 × 10^10 Pa'}, 'aluminum', ('E', 7e10)),
        ({'E': '7*10**10', 'nu': '0,33'}, 'aluminum', ('E', 7e10)),
        ({'E': '7×10¹⁰ Pa'}, 'aluminum', ('E', 7e10)),
        ({'E': '0,05 GPa'}, 'rubber', ('E', 5e7)),  # was 5e6 ('slip')
        # rho was read from the '3' of 'kg/m3', then 'repaired' to 3000.
        ({'density_unit': 'kg/m3', 'density_value': 2700}, 'aluminum',
         ('rho', 2700.0)),
        ({'density': '~2.7 g/cm³'}, 'aluminum', ('rho', 2700.0)),
        ({'E': {'value': 70, 'unit': 'GPa'}}, 'aluminum', ('E', 7e10))):
      with self.subTest(props):
        p = parsing.validate_properties(json.dumps(props), _LIB[key])
        self.assertAlmostEqual(getattr(p, want[0]) / want[1], 1.0)
        self.assertNotIn(want[0], p.from_library)
        self.assertFalse([n for n in p.notes if 'slip' in n], p.notes)
    for props, field, note in (
        ({'E': '−70 GPa'}, 'E', 'is not positive'),  # Unicode minus
        ({'E': '1,5,6 GPa'}, 'E', "E='1,5,6 GPa' has an ambiguous comma"),
        ({'density': 'kg/m3'}, 'rho', "density='kg/m3' is not a number"),
        ({'E': '70 bananas'}, 'E', "unknown unit 'bananas'")):
      with self.subTest(props):
        p = parsing.validate_properties(json.dumps(props), al)
        self.assertIn(field, p.from_library)
        self.assertTrue(any(note in n for n in p.notes), p.notes)

  def test_rigid_flags_in_words(self):
    for word, want in (('Yes.', True), ('rigid', True), ('not rigid', False),
                       ('Non-rigid', False), ('soft', False),
                       ('maybe', None)):
      with self.subTest(word):
        self.assertIs(parsing._as_bool(word), want)

  def test_ranges_tolerances_and_prose(self):
    rubber = _LIB['rubber']
    for value, want in (
        # The power of ten written once applies to both bounds (was 1.25e6:
        # the midpoint of 1.5 Pa and 2.5e6 Pa).
        ('1.5-2.5 × 10^6 Pa', 2e6),
        ('0.5-1.0e7 Pa', 7.5e6),
        ('5e5-1e7 Pa', 5.25e6),  # (each bound its own power: as before)
        # A unit after each bound (the second bound was dropped: 1e6).
        ('1e6 Pa to 1e7 Pa', 5.5e6),
        ('1 MPa - 5 MPa', 3e6),
        ('500 kPa to 5 MPa', 2.75e6),
        ('5 ± 1 MPa', 5e6),  # was unreadable: unknown unit '±1 MPa'
        # Ranges in words, '~' on each bound (were unreadable).
        ('between 1 and 5 MPa', 3e6), ('from 1 to 3 MPa', 2e6),
        ('~1e6 - ~1e7 Pa', 5.5e6)):
      with self.subTest(value):
        p = parsing.validate_properties(
          json.dumps({'youngs_modulus': value}), rubber)
        self.assertNotIn('E', p.from_library)
        self.assertAlmostEqual(p.E / want, 1.0)
    # 'kg/m^-3', a common slip for kg/m^3 (was an unknown unit).
    p = parsing.validate_properties('{"density": "1100 kg/m^-3"}',
                                    _LIB['rubber'])
    self.assertEqual(p.rho, 1100.0)
    # A fraction (was read as 1 and refused).
    p = parsing.validate_properties('{"poisson_ratio": "1/3"}',
                                    _LIB['aluminum'])
    self.assertAlmostEqual(p.nu, 1 / 3)
    # Of two unit slips that fit foam's band [1e4, 1e6] Pa (x10), the one
    # nearest its mid (1e5 Pa): 5 -> 5 kPa, not 5 MPa.
    p = parsing.validate_properties('{"youngs_modulus": 5}', _LIB['foam'])
    self.assertEqual(p.E, 5e3)
    # A '{name}' in prose, or a fence that is not JSON, before the object.
    for text in ('For the {object} shown: {"a": 1}',
                 '```text\nsteel\n```\n```json\n{"a": 1}\n```'):
      self.assertEqual(parsing.extract_json(text), {'a': 1})
    with self.assertRaises(parsing.AnswerError):  # not an inner object
      parsing.extract_json('{"a": {"b": 1}, oops}')

  def test_scores_scale(self):
    s, notes = parsing.parse_scores('{"scores": {"rubber": 8, "wood": 2}}',
                                    _LIB, ('rubber', 'wood'))
    self.assertEqual(s, {'rubber': 0.8, 'wood': 0.2})
    self.assertIn('0-10 scale', notes[0])

  def test_selection_text_only(self):
    key, comb, method = perception.select_candidate(
      ['steel', 'jelly'], 'a wobbly translucent green dessert', _LIB)
    self.assertEqual((key, method), ('jelly', 'text+rank'))
    self.assertTrue(all(0 <= v <= 1 for v in comb.values()))
    with self.assertRaisesRegex(perception.PerceptionError, 'no candidates'):
      perception.select_candidate([], 'a cube', _LIB)
    with self.assertRaisesRegex(perception.PerceptionError,
                                'three non-negative numbers'):
      perception.select_candidate(['steel'], 'a cube', _LIB,
                                  weights=(1.0, -1.0, 0.0))
    # validate_properties' slacks as PerceptionOptions': factors >= 1
    # (0.5 was accepted though the message said >= 1).
    with self.assertRaisesRegex(perception.PerceptionError, 'E_slack=0.5'):
      parsing.validate_properties('{}', _LIB['steel'], E_slack=0.5)


class RenderViewTest(absltest.TestCase):

  def test_several_views_and_cached_run_renders_nothing(self):
    scene = _scene(('metal can',))
    real = p3.render_object_view
    with tempfile.TemporaryDirectory() as d, ScriptedChatServer(
        _script(_answers())) as s:
      opts = _options(s.url, cache_dir=d, image_size=32, num_views=3)
      with mock.patch.object(p3, 'render_object_view',
                             side_effect=real) as render:
        (c1,) = perception.perceive_scene(scene, opts)
        self.assertEqual(render.call_count, 3)  # 3 views, once per object
        azimuths = [call.args[3] for call in render.call_args_list]
        np.testing.assert_allclose(azimuths, [30.0, 150.0, 270.0])
        n1 = s.num_requests
        self.assertEqual(n1, 4)
        for req in s.requests:  # every question carries all three views
          kinds = [p['type'] for p in req['messages'][-1]['content']]
          self.assertEqual(kinds, ['text'] + ['image_url'] * 3)
        urls = [p['image_url']['url'] for p in
                s.requests[0]['messages'][-1]['content'][1:]]
        self.assertLen(set(urls), 3)  # three different images
        # A rerun (new client): everything from the cache, nothing rendered.
        (c2,) = perception.perceive_scene(scene, opts)
        self.assertEqual(render.call_count, 3)
        self.assertEqual(s.num_requests, n1)
    self.assertEqual(c1, c2)
    self.assertEqual(c1.source, 'mllm')

  def test_object_cache_id(self):
    scene = _scene(('metal can', 'rubber ball'))
    opts = perception.PerceptionOptions()
    a = perception.object_cache_id(scene, 0, opts)
    self.assertEqual(a, perception.object_cache_id(scene, 0, opts))
    self.assertNotEqual(a, perception.object_cache_id(scene, 1, opts))
    moved = scene.replace(gaussians=scene.gaussians.replace(
      means=scene.gaussians.means + 1e-3))
    self.assertNotEqual(a, perception.object_cache_id(moved, 0, opts))
    import dataclasses
    self.assertNotEqual(a, perception.object_cache_id(
      scene, 0, dataclasses.replace(opts, num_views=2)))

  def test_object_view_and_real_render_path(self):
    scene = _scene(('metal can', 'rubber ball'))
    img = perception.render_object_view(scene, 1, size=32)
    self.assertEqual(img.shape, (32, 32, 3))
    bg = np.all(img > 0.99, axis=-1)
    # The object fills the centre and not the corners.
    self.assertFalse(bg[12:20, 12:20].any())
    self.assertTrue(bg[0, 0] and bg[-1, -1])
    # Its colour, not the other object's.
    np.testing.assert_allclose(img[16, 16], (0.8, 0.5, 0.2), atol=0.1)
    with ScriptedChatServer(_script(_answers())) as s:
      (c,) = perception.perceive_scene(_scene(('metal can',)),
                                       _options(s.url, image_size=32))
      url = s.requests[0]['messages'][-1]['content'][1]['image_url']['url']
    png = iio.imread(io.BytesIO(base64.b64decode(url.split(',', 1)[1])))
    self.assertEqual(png.shape, (32, 32, 3))
    self.assertEqual(c.source, 'mllm')


if __name__ == '__main__':
  absltest.main()
