"""Tests of the chat-completions client against a real local HTTP server."""

import base64
import io
import json
import os
import socket
import tempfile
import time

import imageio.v3 as iio
import numpy as np
from absl import flags
from absl.testing import absltest

from physsplat_jax.io import mllm
from mllm_test_server import Reply
from mllm_test_server import ScriptedChatServer

_PNG = mllm.encode_png(np.linspace(0, 1, 4 * 5 * 3).reshape(4, 5, 3))
# Short client timeout for the hang tests [s]; the server hangs longer.
_TIMEOUT_S = 0.3
_HANG_S = 3.0


def _config(url, cache_dir=None, **kw):
  return mllm.MLLMConfig(base_url=url, model='test-vlm', cache_dir=cache_dir,
                         timeout_s=kw.pop('timeout_s', 5.0), **kw)


def _cut(text):
  """A reply the server stopped at max_tokens."""
  return Reply(body=json.dumps({'choices': [{
    'index': 0, 'finish_reason': 'length',
    'message': {'role': 'assistant', 'content': text}}]}))


class Sleeps:
  """Records backoff delays instead of sleeping."""

  def __init__(self):
    self.delays = []

  def __call__(self, d):
    self.delays.append(d)


class ClientTest(absltest.TestCase):

  def test_good_answer_and_request_format(self):
    with ScriptedChatServer(lambda req, n: Reply(text='a red ball')) as s:
      c = mllm.MLLMClient(_config(s.url), environ={'OPENAI_API_KEY': 'sk-x'})
      r = c.complete('what is it?', [_PNG], system='be brief')
      self.assertEqual((r.text, r.cached, r.attempts), ('a red ball', False,
                                                        1))
      req, hdr = s.requests[0], s.headers[0]
    self.assertEqual(req['model'], 'test-vlm')
    self.assertEqual(req['temperature'], 0.0)
    self.assertEqual(req['messages'][0], {'role': 'system',
                                          'content': 'be brief'})
    parts = req['messages'][1]['content']
    self.assertEqual(parts[0], {'type': 'text', 'text': 'what is it?'})
    url = parts[1]['image_url']['url']
    self.assertTrue(url.startswith('data:image/png;base64,'))
    self.assertEqual(base64.b64decode(url.split(',', 1)[1]), _PNG)
    self.assertEqual(hdr['Authorization'], 'Bearer sk-x')

  def test_no_key_sends_no_authorization(self):
    with ScriptedChatServer(lambda req, n: Reply(text='ok')) as s:
      mllm.MLLMClient(_config(s.url), environ={}).complete('hi')
      self.assertNotIn('Authorization', s.headers[0])

  def test_500_then_success(self):
    script = lambda req, n: (Reply(status=500, body='{"error": "boom"}')
                             if n == 1 else Reply(text='fine'))
    sleeps = Sleeps()
    with ScriptedChatServer(script) as s:
      c = mllm.MLLMClient(_config(s.url, backoff_s=0.5), sleep=sleeps)
      with self.assertLogs(level='WARNING') as logs:
        r = c.complete('x')
      self.assertEqual(s.num_requests, 2)
    self.assertEqual((r.text, r.attempts), ('fine', 2))
    self.assertEqual(sleeps.delays, [0.5])
    self.assertIn('HTTP 500', '\n'.join(logs.output))

  def test_backoff_doubles_and_gives_up(self):
    sleeps = Sleeps()
    with ScriptedChatServer(lambda req, n: Reply(status=503, body='down')) as s:
      c = mllm.MLLMClient(_config(s.url, max_retries=3, backoff_s=0.1,
                                  backoff_max_s=0.3), sleep=sleeps)
      with self.assertRaises(mllm.MLLMError) as cm:
        c.complete('x')
      self.assertEqual(s.num_requests, 4)
    self.assertEqual(sleeps.delays, [0.1, 0.2, 0.3])
    e = cm.exception
    self.assertEqual((e.kind, e.status, e.attempts), ('http', 503, 4))
    self.assertIn('after 4 attempts', str(e))

  def test_429_honours_retry_after(self):
    script = lambda req, n: (Reply(status=429, body='slow down',
                                   headers=(('Retry-After', '2'),))
                             if n == 1 else Reply(text='ok'))
    sleeps = Sleeps()
    with ScriptedChatServer(script) as s:
      c = mllm.MLLMClient(_config(s.url, backoff_s=0.1), sleep=sleeps)
      self.assertEqual(c.complete('x').text, 'ok')
    self.assertEqual(sleeps.delays, [2.0])

  def test_4xx_is_not_retried(self):
    with ScriptedChatServer(
        lambda req, n: Reply(status=400, body='{"error": "bad model"}')) as s:
      c = mllm.MLLMClient(_config(s.url), sleep=Sleeps())
      with self.assertRaises(mllm.MLLMError) as cm:
        c.complete('x')
      self.assertEqual(s.num_requests, 1)
    self.assertEqual((cm.exception.kind, cm.exception.status), ('http', 400))
    self.assertIn('not retried', str(cm.exception))
    self.assertIn('bad model', str(cm.exception))

  def test_hang_past_timeout(self):
    with ScriptedChatServer(lambda req, n: Reply(text='late',
                                                 delay_s=_HANG_S)) as s:
      c = mllm.MLLMClient(_config(s.url, timeout_s=_TIMEOUT_S, max_retries=1),
                          sleep=Sleeps())
      t0 = time.perf_counter()
      with self.assertRaises(mllm.MLLMError) as cm:
        c.complete('x')
      elapsed = time.perf_counter() - t0
    self.assertEqual((cm.exception.kind, cm.exception.attempts),
                     ('timeout', 2))
    self.assertIn('within 0.3 s', str(cm.exception))
    self.assertLess(elapsed, _HANG_S)

  def test_hang_once_then_answer(self):
    script = lambda req, n: Reply(text='ok', delay_s=_HANG_S if n == 1 else 0)
    with ScriptedChatServer(script) as s:
      c = mllm.MLLMClient(_config(s.url, timeout_s=_TIMEOUT_S),
                          sleep=Sleeps())
      r = c.complete('x')
    self.assertEqual((r.text, r.attempts), ('ok', 2))

  def test_slow_drip_hits_the_request_deadline(self):
    # One byte every 50 ms: the 1 s per-read timeout never fires and the
    # ~200-byte answer would take ~10 s; the 0.4 s deadline ends it.
    with ScriptedChatServer(lambda req, n: Reply(text='dripped',
                                                 drip_s=0.05)) as s:
      c = mllm.MLLMClient(_config(s.url, timeout_s=1.0, max_retries=3,
                                  request_deadline_s=0.4), sleep=Sleeps())
      t0 = time.perf_counter()
      with self.assertRaises(mllm.MLLMError) as cm:
        c.complete('x')
      elapsed = time.perf_counter() - t0
      # An earlier absolute deadline (a scene's) wins over the request's.
      c2 = mllm.MLLMClient(_config(s.url, timeout_s=1.0,
                                   request_deadline_s=30.0))
      t1 = time.perf_counter()
      with self.assertRaisesRegex(mllm.MLLMError, 'deadline'):
        c2.complete('x', deadline=time.monotonic() + 0.3)
      elapsed2 = time.perf_counter() - t1
    self.assertEqual((cm.exception.kind, cm.exception.attempts),
                     ('deadline', 1))
    self.assertIn('within the 0.4 s deadline', str(cm.exception))
    self.assertLess(elapsed, 1.5)
    self.assertGreater(elapsed, 0.35)
    self.assertLess(elapsed2, 1.5)
    # The same drip within a generous deadline completes.
    with ScriptedChatServer(lambda req, n: Reply(text='ok', drip_s=0.001)) as s:
      r = mllm.MLLMClient(_config(s.url, request_deadline_s=20.0)).complete(
        'x')
    self.assertEqual(r.text, 'ok')

  def test_deadline_stops_retries(self):
    with ScriptedChatServer(lambda req, n: Reply(text='late',
                                                 delay_s=_HANG_S)) as s:
      c = mllm.MLLMClient(_config(s.url, timeout_s=0.2, max_retries=10,
                                  backoff_s=0.0, request_deadline_s=0.5))
      t0 = time.perf_counter()
      with self.assertRaises(mllm.MLLMError) as cm:
        c.complete('x')
      elapsed = time.perf_counter() - t0
    self.assertLess(cm.exception.attempts, 5)
    self.assertLess(elapsed, 1.5)

  def test_lazy_images_and_cache_id(self):
    calls = []

    def render():
      calls.append(1)
      return [_PNG, mllm.encode_png(np.zeros((4, 5, 3)))]

    with tempfile.TemporaryDirectory() as d, ScriptedChatServer(
        lambda req, n: Reply(text=f'answer {n}')) as s:
      c = mllm.MLLMClient(_config(s.url, cache_dir=d))
      self.assertEqual(c.complete('p', render, cache_id='obj1').text,
                       'answer 1')
      content = s.requests[0]['messages'][-1]['content']
      self.assertEqual([p['type'] for p in content],
                       ['text', 'image_url', 'image_url'])
      r = mllm.MLLMClient(_config(s.url, cache_dir=d)).complete(
        'p', render, cache_id='obj1')
      self.assertEqual((r.text, r.cached), ('answer 1', True))
      self.assertEqual(len(calls), 1)  # the cached answer rendered nothing
      # Another id or other model settings are other keys.
      c.complete('p', render, cache_id='obj2')
      mllm.MLLMClient(_config(s.url, cache_dir=d, max_tokens=9)).complete(
        'p', render, cache_id='obj1')
      self.assertEqual((len(calls), s.num_requests), (3, 3))
      with self.assertRaisesRegex(mllm.MLLMError, 'need a cache_id'):
        c.complete('p', render)

  def test_connection_refused(self):
    sock = socket.socket()
    sock.bind(('127.0.0.1', 0))
    port = sock.getsockname()[1]
    sock.close()
    c = mllm.MLLMClient(_config(f'http://127.0.0.1:{port}/v1', max_retries=1),
                        sleep=Sleeps())
    with self.assertRaises(mllm.MLLMError) as cm:
      c.complete('x')
    self.assertEqual((cm.exception.kind, cm.exception.attempts),
                     ('connection', 2))
    self.assertIn('cannot connect', str(cm.exception))
    # The next question (e.g. the scene's next object) fails at once.
    with self.assertRaisesRegex(mllm.MLLMError, 'not asked again') as cm:
      c.complete('y')
    self.assertEqual((cm.exception.kind, cm.exception.attempts, c.num_requests),
                     ('connection', 0, 2))

  def test_malformed_response_body(self):
    script = lambda req, n: (Reply(body='<html>proxy error</html>')
                             if n == 1 else Reply(text='ok'))
    with ScriptedChatServer(script) as s:
      c = mllm.MLLMClient(_config(s.url), sleep=Sleeps())
      self.assertEqual(c.complete('x').text, 'ok')
      self.assertEqual(s.num_requests, 2)
    with ScriptedChatServer(lambda req, n: Reply(body='{"choices": []}')) as s:
      c = mllm.MLLMClient(_config(s.url, max_retries=0), sleep=Sleeps())
      with self.assertRaisesRegex(mllm.MLLMError, 'malformed') as cm:
        c.complete('x')
    self.assertEqual(cm.exception.kind, 'protocol')

  def test_cache_makes_rerun_free(self):
    with tempfile.TemporaryDirectory() as d, ScriptedChatServer(
        lambda req, n: Reply(text=f'answer {n}')) as s:
      c1 = mllm.MLLMClient(_config(s.url, cache_dir=d))
      self.assertEqual(c1.complete('p', [_PNG]).text, 'answer 1')
      # A new client (a rerun) with the same inputs: no request at all.
      c2 = mllm.MLLMClient(_config(s.url, cache_dir=d))
      r = c2.complete('p', [_PNG])
      self.assertEqual((r.text, r.cached, r.attempts), ('answer 1', True, 0))
      self.assertEqual((s.num_requests, c2.num_requests,
                        c2.num_cache_hits), (1, 0, 1))
      # Another image, prompt or model is another key.
      other = mllm.encode_png(np.zeros((4, 5, 3)))
      self.assertEqual(c2.complete('p', [other]).text, 'answer 2')
      self.assertEqual(c2.complete('q', [_PNG]).text, 'answer 3')
      c3 = mllm.MLLMClient(_config(s.url, cache_dir=d).__class__(
        base_url=s.url, model='other', cache_dir=d))
      self.assertEqual(c3.complete('p', [_PNG]).text, 'answer 4')
      self.assertEqual(s.num_requests, 4)

  def test_failures_are_not_cached(self):
    script = lambda req, n: (Reply(status=500, body='x') if n == 1
                             else Reply(text='ok'))
    with tempfile.TemporaryDirectory() as d, ScriptedChatServer(script) as s:
      c = mllm.MLLMClient(_config(s.url, cache_dir=d, max_retries=0),
                          sleep=Sleeps())
      with self.assertRaises(mllm.MLLMError):
        c.complete('p')
      self.assertEqual(c.complete('p').text, 'ok')

  def test_cut_and_empty_answers_are_not_cached(self):
    # Answers 1 (cut at max_tokens) and 2 (empty) were cached and replayed
    # forever; an answer the caller finds unusable can be evicted.
    script = lambda req, n: {1: _cut('{"candidates": [{"mat'),
                             2: Reply(text='  ')}.get(n, Reply(text='ok'))
    with tempfile.TemporaryDirectory() as d, ScriptedChatServer(script) as s:
      c = mllm.MLLMClient(_config(s.url, cache_dir=d, max_tokens=64))
      r = c.complete('p')
      self.assertEqual(r.cut, 'answer cut at max_tokens=64 (finish_reason='
                       'length); raise --mllm_max_tokens')
      self.assertIsNone(r.cache_path)
      self.assertEqual(c.complete('p').text, '  ')
      r = c.complete('p')
      self.assertEqual((r.text, r.cut, s.num_requests), ('ok', '', 3))
      r = c.complete('p')
      self.assertTrue(r.cached and r.cache_path.startswith(d))
      self.assertEqual(c.evict(r.key), r.cache_path)
      self.assertFalse(os.path.exists(r.cache_path))
      self.assertFalse(c.complete('p').cached)
      self.assertEqual(s.num_requests, 4)

  def test_401_names_the_key_and_stops_asking(self):
    deny = lambda req, n: Reply(status=401, body='{"error": "bad key"}')
    for environ, cfg, want in (
        ({}, {}, 'no API key was sent: OPENAI_API_KEY is unset '
         r'\(--mllm_api_key_env\)'),
        ({'MY_KEY': ''}, {'api_key_env': 'MY_KEY'},
         'no API key was sent: MY_KEY is empty'),
        ({'OPENAI_API_KEY': 'sk-x'}, {},
         'an API key from OPENAI_API_KEY was sent and refused')):
      with self.subTest(want), ScriptedChatServer(deny) as s:
        c = mllm.MLLMClient(_config(s.url, **cfg), environ=environ,
                            sleep=Sleeps())
        with self.assertRaisesRegex(mllm.MLLMError, 'HTTP 401.*' + want):
          c.complete('x')
        # The next question (the scene's next object) is not asked.
        with self.assertRaisesRegex(mllm.MLLMError,
                                    want + '.*not asked again') as cm:
          c.complete('y')
        self.assertEqual((cm.exception.attempts, s.num_requests), (0, 1))
    with ScriptedChatServer(lambda req, n: Reply(status=403, body='no')) as s:
      c = mllm.MLLMClient(_config(s.url), environ={'OPENAI_API_KEY': 'k'})
      with self.assertRaisesRegex(mllm.MLLMError,
                                  "lacks access to model 'test-vlm'"):
        c.complete('x')

  def test_bad_config(self):
    with self.assertRaisesRegex(mllm.MLLMError, 'no MLLM endpoint'):
      mllm.MLLMClient(mllm.MLLMConfig())
    with self.assertRaisesRegex(mllm.MLLMError, 'request_deadline_s must'):
      mllm.MLLMClient(mllm.MLLMConfig(base_url='http://h/v1',
                                      request_deadline_s=0))
    with self.assertRaisesRegex(mllm.MLLMError, 'must start with http'):
      mllm.MLLMClient(mllm.MLLMConfig(base_url='localhost:1234'))
    # The numbers are checked offline too (a bad --mllm_* flag is reported
    # even when no endpoint is set); an offline default config is fine.
    self.assertIs(mllm.MLLMConfig().validate().enabled, False)
    for field, value, flag in (('timeout_s', -1.0, 'mllm_timeout'),
                               ('max_tokens', 0, 'mllm_max_tokens'),
                               ('backoff_s', -2.0, 'mllm_backoff'),
                               ('scene_deadline_s', float('nan'),
                                'mllm_scene_deadline'),
                               # inf overflowed the deadline watchdog.
                               ('request_deadline_s', float('inf'),
                                'mllm_deadline'),
                               ('timeout_s', float('inf'), 'mllm_timeout'),
                               ('max_tokens', 1.5, 'mllm_max_tokens')):
      with self.subTest(field), self.assertRaisesRegex(
          mllm.MLLMError, f'{field} must .* 0, got .*--{flag}'):
        mllm.MLLMConfig(**{field: value}).validate()
    self.assertEqual(mllm.MLLMConfig(base_url='http://h/v1/').url,
                     'http://h/v1/chat/completions')
    self.assertEqual(
      mllm.MLLMConfig(base_url='http://h/x/chat/completions').url,
      'http://h/x/chat/completions')


class PngAndFlagsTest(absltest.TestCase):

  def test_png_round_trip(self):
    img = (np.arange(6 * 7 * 3).reshape(6, 7, 3) % 256).astype(np.uint8)
    back = iio.imread(io.BytesIO(mllm.encode_png(img)))
    np.testing.assert_array_equal(back, img)
    rgba = np.dstack([img, np.full((6, 7), 200, np.uint8)])
    np.testing.assert_array_equal(
      iio.imread(io.BytesIO(mllm.encode_png(rgba))), rgba)
    back = iio.imread(io.BytesIO(mllm.encode_png(np.full((2, 2, 3), 0.5))))
    self.assertEqual(int(back[0, 0, 0]), 128)
    with self.assertRaisesRegex(ValueError, r'expected \(H, W, 3\|4\)'):
      mllm.encode_png(np.zeros((3, 3)))

  def test_flags(self):
    fv = flags.FlagValues()
    mllm.define_flags(fv)
    mllm.define_flags(fv)  # idempotent
    fv(['prog', '--mllm_base_url=http://127.0.0.1:9/v1', '--mllm_model=llava',
        '--mllm_timeout=7', '--mllm_retries=1', '--mllm_cache_dir=',
        '--mllm_deadline=20', '--mllm_scene_deadline=90'])
    c = mllm.config_from_flags(fv)
    self.assertEqual((c.request_deadline_s, c.scene_deadline_s), (20.0, 90.0))
    self.assertEqual((c.base_url, c.model, c.timeout_s, c.max_retries,
                      c.cache_dir, c.api_key_env),
                     ('http://127.0.0.1:9/v1', 'llava', 7.0, 1, None,
                      'OPENAI_API_KEY'))
    fv2 = flags.FlagValues()
    mllm.define_flags(fv2)
    fv2(['prog'])
    self.assertFalse(mllm.config_from_flags(fv2).enabled)


if __name__ == '__main__':
  absltest.main()
