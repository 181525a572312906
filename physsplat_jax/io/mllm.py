"""HTTP client for OpenAI-compatible chat-completions endpoints with images.

Works with OpenAI, vLLM, Ollama (``http://localhost:11434/v1``), LM Studio
(``http://localhost:1234/v1``) and any server that speaks the protocol::

  POST {base_url}/chat/completions
  {"model": ..., "temperature": 0, "max_tokens": ...,
   "messages": [{"role": "system", "content": ...},
                {"role": "user", "content": [
                   {"type": "text", "text": prompt},
                   {"type": "image_url",
                    "image_url": {"url": "data:image/png;base64,..."}}]}]}
  -> {"choices": [{"message": {"content": "..."}}]}

Standard library only (urllib). The API key comes from an environment
variable (``OPENAI_API_KEY`` by default, or the one named by
``MLLMConfig.api_key_env``); local servers need none.

Robustness:
* per-request ``timeout_s`` (applies to connecting and to each socket read,
  so a server that hangs is abandoned after ``timeout_s``);
* a total ``request_deadline_s`` per question (all attempts, reads and
  backoff included): a server that drips its answer a byte at a time never
  trips the per-read timeout, so a watchdog shuts the socket down when the
  deadline passes; callers may pass an earlier absolute ``deadline`` (the
  per-scene deadline of perception);
* up to ``max_retries`` retries with exponential backoff
  ``backoff_s * 2**attempt`` (capped at ``backoff_max_s``; a numeric
  ``Retry-After`` header is honoured up to the cap) on timeouts, connection
  errors, HTTP 429 and 5xx, and on malformed (non-JSON) response bodies;
  other 4xx fail at once (a bad request does not improve by repetition);
* an on-disk cache keyed by ``sha256(model, temperature, max_tokens,
  system, prompt, sha256 of each image's bytes)``, or, when the caller
  passes a ``cache_id`` (e.g. a hash of the object's Gaussians and the view
  settings), by that instead of the images: then ``images`` may be a
  callable that renders them, called only on a cache miss, so a cached run
  renders nothing. Only successful answers are cached: not failures, not
  empty answers, not answers cut at ``max_tokens`` (``finish_reason:
  "length"``; :attr:`MLLMReply.cut` says so), and a caller that finds an
  answer unusable removes it with :meth:`MLLMClient.evict`. Default
  directory ``.mllm_cache/`` (in .gitignore); ``cache_dir=None`` disables
  it.
* HTTP 401/403 end the run's questions: the message says whether an API
  key was sent and which variable (``--mllm_api_key_env``) provides it, and
  later questions fail at once.

Scripts get absl flags from :func:`define_flags` (nothing is defined at
import time) and an :class:`MLLMConfig` from :func:`config_from_flags`.
"""

from __future__ import annotations

import base64
import dataclasses
import hashlib
import http.client
import json
import math
import os
import socket
import struct
import tempfile
import threading
import time
import urllib.error
import urllib.request
import zlib
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import numpy as np
from absl import logging

from physsplat_jax.errors import PhysSplatError

DEFAULT_CACHE_DIR = '.mllm_cache'
_CACHE_VERSION = 2  # 2: model settings in the key; cache_id
_BODY_EXCERPT = 300  # characters of an error body quoted in messages


class MLLMError(PhysSplatError, RuntimeError):
  """A request failed for good.

  Attributes:
    kind: 'timeout', 'deadline', 'connection', 'http', 'protocol' or
      'config'.
    status: the HTTP status for kind 'http', else None.
    attempts: how many requests were made.
    retry_after: the server's Retry-After header, if any.
  """

  def __init__(self, message: str, kind: str, status: int | None = None,
               attempts: int = 0, retry_after: str | None = None):
    super().__init__(message)
    self.kind = kind
    self.status = status
    self.attempts = attempts
    self.retry_after = retry_after


@dataclasses.dataclass(frozen=True)
class MLLMConfig:
  """Endpoint and client settings (hashable).

  Attributes:
    base_url: e.g. ``'https://api.openai.com/v1'`` or
      ``'http://127.0.0.1:11434/v1'``; None or '' means no endpoint
      (offline perception). A URL ending in ``/chat/completions`` is used
      as is.
    model: model name sent in the request, e.g. ``'gpt-4o-mini'``,
      ``'qwen2.5-vl'``, ``'llava'``.
    api_key_env: environment variable holding the API key (sent as
      ``Authorization: Bearer``); a missing variable sends no key.
    timeout_s: socket timeout [s] (connect and each read).
    request_deadline_s: total time for one question, retries included [s].
    scene_deadline_s: total time for all questions about one scene [s]
      (used by perception); past it, the rest falls back to the library.
    max_retries: retries after the first attempt.
    backoff_s: first backoff delay [s]; doubles each retry.
    backoff_max_s: cap on one delay [s].
    cache_dir: cache directory, or None to disable caching.
    temperature: sampling temperature (0 for repeatable answers).
    max_tokens: answer length cap.
  """

  base_url: str | None = None
  model: str = 'gpt-4o-mini'
  api_key_env: str = 'OPENAI_API_KEY'
  timeout_s: float = 60.0
  request_deadline_s: float = 60.0
  scene_deadline_s: float = 300.0
  max_retries: int = 3
  backoff_s: float = 1.0
  backoff_max_s: float = 30.0
  cache_dir: str | None = DEFAULT_CACHE_DIR
  temperature: float = 0.0
  max_tokens: int = 512

  @property
  def enabled(self) -> bool:
    """Whether an endpoint is configured."""
    return bool(self.base_url)

  @property
  def url(self) -> str:
    """The full chat-completions URL."""
    base = (self.base_url or '').rstrip('/')
    if base.endswith('/chat/completions'):
      return base
    return base + '/chat/completions'

  def validate(self) -> MLLMConfig:
    """Returns self, or raises MLLMError(kind='config') naming the field.

    The numbers are checked offline too, so that a bad ``--mllm_*`` flag is
    reported even when no endpoint is set; the endpoint's own fields only
    when one is.
    """
    # (field, its flag, strictly positive?)
    numbers = (('timeout_s', 'mllm_timeout', True),
               ('request_deadline_s', 'mllm_deadline', True),
               ('scene_deadline_s', 'mllm_scene_deadline', True),
               ('max_tokens', 'mllm_max_tokens', True),
               ('max_retries', 'mllm_retries', False),
               ('backoff_s', 'mllm_backoff', False),
               ('backoff_max_s', None, False),
               ('temperature', None, False))
    for f, flag, strict in numbers:
      v = getattr(self, f)
      integer = f in ('max_tokens', 'max_retries')
      try:  # NaN and inf fail (an infinite deadline overflowed a timer)
        ok = (not isinstance(v, bool) and math.isfinite(v)
              and (v > 0 if strict else v >= 0)
              and (hasattr(type(v), '__index__') or not integer))
      except TypeError:
        ok = False
      if not ok:
        what = 'an integer' if integer else 'a finite number'
        raise MLLMError(
          f'MLLMConfig.{f} must be {what} {">" if strict else ">="} 0, got '
          f'{v!r}' + (f' (--{flag})' if flag else ''), 'config')
    if not self.enabled:
      return self
    if not self.base_url.startswith(('http://', 'https://')):
      raise MLLMError(
        f'mllm base_url {self.base_url!r} must start with http:// or '
        'https:// (e.g. http://127.0.0.1:11434/v1 for Ollama)', 'config')
    if not self.model:
      raise MLLMError('mllm model is empty; pass --mllm_model', 'config')
    return self


@dataclasses.dataclass(frozen=True)
class MLLMReply:
  """One answer.

  Attributes:
    text: the assistant message content.
    cached: True when it came from the on-disk cache (no request made).
    attempts: requests made for it (0 when cached).
    key: the cache key.
    cut: why the answer is incomplete ('' when it is not): the server
      stopped at ``max_tokens`` (``finish_reason: "length"``). Such
      answers are not cached.
    cache_path: the cache file it was read from or written to, or None.
  """

  text: str
  cached: bool
  attempts: int
  key: str
  cut: str = ''
  cache_path: str | None = None


# ------------------------------------------------------------------ images


def encode_png(image) -> bytes:
  """Encodes an (H, W, 3) or (H, W, 4) image as PNG (stdlib zlib only).

  Args:
    image: uint8 array, or floats in [0, 1] (clipped, rounded).

  Returns:
    The PNG file bytes (8-bit RGB or RGBA, no interlace).
  """
  a = np.asarray(image)
  if a.ndim != 3 or a.shape[2] not in (3, 4) or 0 in a.shape[:2]:
    raise ValueError(f'encode_png: expected (H, W, 3|4), got {a.shape}')
  if a.dtype != np.uint8:
    a = np.round(np.clip(np.nan_to_num(a.astype(np.float64)), 0, 1) * 255)
    a = a.astype(np.uint8)
  h, w, c = a.shape
  raw = np.concatenate([np.zeros((h, 1), np.uint8), a.reshape(h, w * c)],
                       axis=1).tobytes()

  def chunk(tag: bytes, data: bytes) -> bytes:
    return (struct.pack('>I', len(data)) + tag + data
            + struct.pack('>I', zlib.crc32(tag + data) & 0xFFFFFFFF))

  ihdr = struct.pack('>IIBBBBB', w, h, 8, 6 if c == 4 else 2, 0, 0, 0)
  return (b'\x89PNG\r\n\x1a\n' + chunk(b'IHDR', ihdr)
          + chunk(b'IDAT', zlib.compress(raw, 6)) + chunk(b'IEND', b''))


def png_data_url(png: bytes) -> str:
  """``data:image/png;base64,...`` URL of PNG bytes."""
  return 'data:image/png;base64,' + base64.b64encode(png).decode('ascii')


# ------------------------------------------------------------------- cache


def cache_key(model: str, prompt: str, images: Sequence[bytes] = (),
              system: str | None = None, *, cache_id: str | None = None,
              settings: Mapping[str, Any] | None = None) -> str:
  """sha256 hex of the model, settings, system prompt, prompt and images.

  ``cache_id`` (when given) stands for the images: a caller that can name
  what it would render (object hash, view settings) needs no render to
  find a cached answer.
  """
  h = hashlib.sha256()
  payload = {
    'v': _CACHE_VERSION, 'model': model, 'system': system or '',
    'prompt': prompt, 'settings': dict(settings or {}),
    'images': (['id:' + cache_id] if cache_id is not None else
               [hashlib.sha256(b).hexdigest() for b in images]),
  }
  h.update(json.dumps(payload, sort_keys=True).encode('utf-8'))
  return h.hexdigest()


def _cache_path(cache_dir: str, key: str) -> str:
  return os.path.join(cache_dir, key[:2], key + '.json')


def _cache_read(cache_dir: str, key: str) -> str | None:
  path = _cache_path(cache_dir, key)
  try:
    with open(path, encoding='utf-8') as f:
      data = json.load(f)
  except FileNotFoundError:
    return None
  except (OSError, json.JSONDecodeError) as e:
    logging.warning('mllm cache: ignoring unreadable entry %s (%s)', path, e)
    return None
  text = data.get('text') if isinstance(data, dict) else None
  return text if isinstance(text, str) else None


def _cache_write(cache_dir: str, key: str, text: str,
                 model: str) -> str | None:
  """Stores an answer; returns its path, or None when it cannot."""
  path = _cache_path(cache_dir, key)
  try:
    os.makedirs(os.path.dirname(path), exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=os.path.dirname(path), suffix='.tmp')
    with os.fdopen(fd, 'w', encoding='utf-8') as f:
      json.dump({'text': text, 'model': model, 'time': time.time()}, f)
    os.replace(tmp, path)
    return path
  except OSError as e:
    logging.warning('mllm cache: cannot write %s (%s); continuing without '
                    'caching', path, e)
    return None


# ------------------------------------------------------------------ client


def _content_text(content) -> str | None:
  """Message content as text (string, or a list of text parts)."""
  if isinstance(content, str):
    return content
  if isinstance(content, list):
    parts = [p.get('text', '') for p in content
             if isinstance(p, dict) and p.get('type') in ('text', None)]
    return ''.join(parts) if parts else None
  return None


def _tracking(cls, socks: list):
  """A connection factory that records each connected socket in ``socks``.

  urllib drops ``conn.sock`` once the headers are in (the response keeps
  the socket through its file), so the socket itself is recorded.
  """

  def factory(host, **kw):
    c = cls(host, **kw)
    connect = c.connect

    def tracked_connect():
      connect()
      socks.append(c.sock)

    c.connect = tracked_connect
    return c

  return factory


class _TrackingHTTPHandler(urllib.request.HTTPHandler):
  """Records its sockets so a watchdog can shut them down."""

  def __init__(self, socks: list):
    super().__init__()
    self._socks = socks

  def http_open(self, req):
    return self.do_open(_tracking(http.client.HTTPConnection, self._socks),
                        req)


class _TrackingHTTPSHandler(urllib.request.HTTPSHandler):
  """HTTPS twin of :class:`_TrackingHTTPHandler`."""

  def __init__(self, socks: list):
    super().__init__()
    self._socks = socks

  def https_open(self, req):
    return self.do_open(_tracking(http.client.HTTPSConnection, self._socks),
                        req, context=self._context)


def _shutdown(socks: list, fired: threading.Event) -> None:
  """Deadline watchdog: wakes any blocked read with end-of-stream."""
  fired.set()
  for sock in list(socks):
    try:
      sock.shutdown(socket.SHUT_RDWR)
    except OSError:
      pass


class MLLMClient:
  """Chat-completions client with retries, backoff and an on-disk cache.

  Attributes:
    config: the :class:`MLLMConfig`.
    num_requests: HTTP requests made so far.
    num_cache_hits: answers served from the cache so far.
  """

  def __init__(self, config: MLLMConfig, *,
               sleep: Callable[[float], None] = time.sleep,
               environ: Mapping[str, str] | None = None):
    """Creates a client.

    Args:
      config: endpoint settings; must be enabled (``base_url`` set).
      sleep: delay function (tests pass a recorder).
      environ: environment for the API key (default ``os.environ``).

    Raises:
      MLLMError: kind 'config' for a missing or malformed endpoint.
    """
    if not config.enabled:
      raise MLLMError('no MLLM endpoint configured (base_url is empty); '
                      'pass --mllm_base_url or use offline perception',
                      'config')
    self.config = config.validate()
    self._sleep = sleep
    env = os.environ if environ is None else environ
    self._api_key = env.get(config.api_key_env) if config.api_key_env else None
    self._key_set = bool(config.api_key_env) and config.api_key_env in env
    if not self._api_key and config.api_key_env != 'OPENAI_API_KEY':
      logging.warning('mllm: environment variable %s is not set; sending no '
                      'API key', config.api_key_env)
    self.num_requests = 0
    self.num_cache_hits = 0
    # Set when a question ended because the endpoint could not be reached
    # at all (refused, unknown host): later questions fail at once instead
    # of spending their retries on a server that is not there.
    self.unreachable: str | None = None
    # Set on HTTP 401/403 (the credentials were refused): later questions
    # fail at once, naming the key's variable.
    self.refused: str | None = None

  def _key_note(self, status: int) -> str:
    """Whether a key was sent on a 401/403, and where it comes from."""
    env = self.config.api_key_env
    if self._api_key:
      access = (f' or lacks access to model {self.config.model!r} '
                '(--mllm_model)' if status == 403 else '')
      return (f'an API key from {env} was sent and refused{access}; check '
              'it, or name another variable with --mllm_api_key_env')
    if not env:
      return ('no API key was sent: MLLMConfig.api_key_env is empty '
              '(--mllm_api_key_env)')
    state = 'is empty' if self._key_set else 'is unset'
    return f'no API key was sent: {env} {state} (--mllm_api_key_env)'

  def evict(self, key: str) -> str | None:
    """Deletes the cached answer ``key`` (one the caller found unusable,
    so that the next run asks again); returns the deleted file's path, or
    None when there was none or it cannot be deleted."""
    if not self.config.cache_dir:
      return None
    path = _cache_path(self.config.cache_dir, key)
    try:
      os.remove(path)
    except FileNotFoundError:
      return None
    except OSError as e:
      logging.warning('mllm cache: cannot delete unusable answer %s (%s)',
                      path, e)
      return None
    return path

  def _body(self, prompt, images, system) -> bytes:
    content = [{'type': 'text', 'text': prompt}]
    for png in images:
      content.append({'type': 'image_url',
                      'image_url': {'url': png_data_url(png)}})
    messages = []
    if system:
      messages.append({'role': 'system', 'content': system})
    messages.append({'role': 'user', 'content': content})
    body = {
      'model': self.config.model, 'messages': messages,
      'temperature': self.config.temperature,
      'max_tokens': self.config.max_tokens,
    }
    return json.dumps(body).encode('utf-8')

  def _deadline_error(self, budget: float) -> MLLMError:
    return MLLMError(f'no complete answer from {self.config.url} within the '
                     f'{budget:g} s deadline', 'deadline')

  def _request_once(self, body: bytes, end: float,
                    budget: float) -> tuple[str, str | None]:
    """One POST that ends by ``end`` (monotonic); returns the content and
    the finish_reason, or raises a classified MLLMError."""
    headers = {'Content-Type': 'application/json',
               'Accept': 'application/json'}
    if self._api_key:
      headers['Authorization'] = f'Bearer {self._api_key}'
    req = urllib.request.Request(self.config.url, data=body, headers=headers,
                                 method='POST')
    remaining = end - time.monotonic()
    if remaining <= 0:
      raise self._deadline_error(budget)
    self.num_requests += 1
    socks: list = []
    fired = threading.Event()
    opener = urllib.request.build_opener(_TrackingHTTPHandler(socks),
                                         _TrackingHTTPSHandler(socks))
    watchdog = threading.Timer(remaining, _shutdown, (socks, fired))
    watchdog.daemon = True
    timeout = min(self.config.timeout_s, remaining)

    def fetch() -> bytes:
      with opener.open(req, timeout=timeout) as r:
        return r.read()

    watchdog.start()
    try:
      raw = self._open_errors(fetch)
    except MLLMError:
      if fired.is_set():
        raise self._deadline_error(budget) from None
      raise
    finally:
      watchdog.cancel()
    if fired.is_set():
      raise self._deadline_error(budget)
    return self._parse(raw)

  def _parse(self, raw: bytes) -> tuple[str, str | None]:
    """The answer text and finish_reason of a response body (or a
    'protocol' MLLMError)."""
    try:
      data = json.loads(raw.decode('utf-8'))
      choice = data['choices'][0]
      text = _content_text(choice['message']['content'])
      finish = choice.get('finish_reason')
    except (UnicodeDecodeError, json.JSONDecodeError, KeyError, IndexError,
            TypeError) as e:
      raise MLLMError(
        f'malformed chat-completions response from {self.config.url} '
        f'({type(e).__name__}): {raw[:_BODY_EXCERPT]!r}', 'protocol'
      ) from None
    if text is None:
      raise MLLMError(f'response from {self.config.url} has no text content',
                      'protocol')
    return text, finish if isinstance(finish, str) else None

  def _open_errors(self, fn):
    """Runs ``fn`` mapping urllib/socket errors to classified MLLMErrors."""
    try:
      return fn()
    except urllib.error.HTTPError as e:
      try:
        detail = e.read().decode('utf-8', 'replace')[:_BODY_EXCERPT]
      except Exception:  # noqa: BLE001 - best effort for the message
        detail = ''
      raise MLLMError(
        f'HTTP {e.code} {e.reason} from {self.config.url}: {detail}', 'http',
        status=e.code,
        retry_after=e.headers.get('Retry-After') if e.headers else None,
      ) from None
    except (TimeoutError, socket.timeout) as e:
      raise MLLMError(f'no answer from {self.config.url} within '
                      f'{self.config.timeout_s:g} s ({e})', 'timeout'
                      ) from None
    except urllib.error.URLError as e:
      if isinstance(e.reason, (TimeoutError, socket.timeout)):
        raise MLLMError(f'no answer from {self.config.url} within '
                        f'{self.config.timeout_s:g} s', 'timeout') from None
      raise MLLMError(f'cannot connect to {self.config.url}: {e.reason}',
                      'connection') from None
    except (http.client.HTTPException, ConnectionError, OSError) as e:
      raise MLLMError(f'connection to {self.config.url} failed: {e!r}',
                      'connection') from None

  def _delay(self, attempt: int, err: MLLMError) -> float:
    d = min(self.config.backoff_s * 2.0 ** attempt, self.config.backoff_max_s)
    ra = err.retry_after
    if ra:
      try:
        d = min(max(d, float(ra)), self.config.backoff_max_s)
      except ValueError:
        pass
    return d

  def complete(self, prompt: str,
               images: Sequence[bytes] | Callable[[], Sequence[bytes]] = (),
               system: str | None = None, *, cache_id: str | None = None,
               deadline: float | None = None) -> MLLMReply:
    """Asks the model; answers from the cache when possible.

    Args:
      prompt: the user text.
      images: PNG file bytes, sent as data URLs in order after the text; or
        a callable returning them, called only when a request is made
        (with ``cache_id``, a cached answer renders nothing).
      system: optional system prompt.
      cache_id: names the images in the cache key instead of their bytes
        (required when ``images`` is a callable and the cache is on).
      deadline: optional absolute ``time.monotonic()`` time by which to
        give up, when earlier than ``request_deadline_s`` from now.

    Returns:
      An :class:`MLLMReply`.

    Raises:
      MLLMError: after the retries are spent, at once on a non-retryable
        HTTP status, or when the deadline passes (kind 'deadline'); ``kind``
        says what happened.
    """
    budget = self.config.request_deadline_s
    end = time.monotonic() + budget
    if deadline is not None and deadline < end:
      budget = max(deadline - time.monotonic(), 0.0)
      end = deadline
    lazy = callable(images)
    if lazy and cache_id is None and self.config.cache_dir:
      raise MLLMError('mllm: images given as a callable need a cache_id',
                      'config')
    settings = {'temperature': self.config.temperature,
                'max_tokens': self.config.max_tokens}
    key = cache_key(self.config.model, prompt,
                    () if lazy else tuple(images), system,
                    cache_id=cache_id, settings=settings)
    if self.config.cache_dir:
      text = _cache_read(self.config.cache_dir, key)
      if text is not None and text.strip():  # an empty one: ask again
        self.num_cache_hits += 1
        return MLLMReply(text=text, cached=True, attempts=0, key=key,
                         cache_path=_cache_path(self.config.cache_dir, key))
    if self.unreachable:
      raise MLLMError(f'{self.unreachable}; not asked again in this run',
                      'connection', attempts=0)
    if self.refused:
      raise MLLMError(f'{self.refused}; not asked again in this run', 'http',
                      attempts=0)
    if end <= time.monotonic():
      raise self._deadline_error(budget)
    body = self._body(prompt, tuple(images() if lazy else images), system)
    attempts = 0
    while True:
      attempts += 1
      try:
        text, finish = self._request_once(body, end, budget)
        break
      except MLLMError as e:
        retryable = (e.kind in ('timeout', 'connection', 'protocol')
                     or (e.kind == 'http'
                         and (e.status == 429 or e.status >= 500)))
        delay = self._delay(attempts - 1, e) if retryable else 0.0
        if (not retryable or attempts > self.config.max_retries
            or time.monotonic() + delay >= end):
          what = 'not retried' if not retryable else (
            f'after {attempts} attempts')
          if retryable and attempts <= self.config.max_retries:
            what = f'after {attempts} attempts; no time left to retry'
          if e.kind == 'connection':
            self.unreachable = f'{e} ({what})'
          msg = f'{e} ({what})'
          if e.kind == 'http' and e.status in (401, 403):
            note = self._key_note(e.status)
            self.refused = (f'{self.config.url} refused an earlier request '
                            f'with HTTP {e.status} ({note})')
            msg += f'; {note}; the endpoint is not asked again in this run'
          raise MLLMError(msg, e.kind, e.status, attempts) from None
        logging.warning('mllm: attempt %d failed (%s); retrying in %.2f s',
                        attempts, e, delay)
        self._sleep(delay)
    cut = '' if finish != 'length' else (
      f'answer cut at max_tokens={self.config.max_tokens} '
      '(finish_reason=length); raise --mllm_max_tokens')
    path = None
    if self.config.cache_dir and text.strip() and not cut:
      path = _cache_write(self.config.cache_dir, key, text, self.config.model)
    return MLLMReply(text=text, cached=False, attempts=attempts, key=key,
                     cut=cut, cache_path=path)


def make_client(config: MLLMConfig, **kwargs) -> MLLMClient:
  """``MLLMClient(config, **kwargs)``."""
  return MLLMClient(config, **kwargs)


# ------------------------------------------------------------------- flags


def define_flags(flag_values=None) -> None:
  """Defines the ``--mllm_*`` absl flags (idempotent).

  Flags: ``--mllm_base_url`` (empty = offline), ``--mllm_model``,
  ``--mllm_api_key_env``, ``--mllm_timeout`` [s], ``--mllm_deadline`` [s],
  ``--mllm_scene_deadline`` [s], ``--mllm_retries``,
  ``--mllm_backoff`` [s], ``--mllm_cache_dir`` (empty disables the cache),
  ``--mllm_max_tokens``.

  Args:
    flag_values: an ``absl.flags.FlagValues`` (default ``flags.FLAGS``).
  """
  from absl import flags

  fv = flags.FLAGS if flag_values is None else flag_values
  d = MLLMConfig()
  specs = [
    (flags.DEFINE_string, 'mllm_base_url', '',
     'OpenAI-compatible endpoint, e.g. https://api.openai.com/v1 or '
     'http://127.0.0.1:11434/v1 (Ollama); empty: offline perception from the '
     'material library.'),
    (flags.DEFINE_string, 'mllm_model', d.model, 'Model name to request.'),
    (flags.DEFINE_string, 'mllm_api_key_env', d.api_key_env,
     'Environment variable that holds the API key.'),
    (flags.DEFINE_float, 'mllm_timeout', d.timeout_s,
     'Socket timeout [s] (connect and each read).'),
    (flags.DEFINE_float, 'mllm_deadline', d.request_deadline_s,
     'Total time for one question, retries included [s].'),
    (flags.DEFINE_float, 'mllm_scene_deadline', d.scene_deadline_s,
     'Total time for all questions about one scene [s]; then the library.'),
    (flags.DEFINE_integer, 'mllm_retries', d.max_retries,
     'Retries on timeouts, connection errors, HTTP 429 and 5xx.'),
    (flags.DEFINE_float, 'mllm_backoff', d.backoff_s,
     'First retry delay [s]; doubles each retry.'),
    (flags.DEFINE_string, 'mllm_cache_dir', d.cache_dir,
     'On-disk answer cache; empty disables it.'),
    (flags.DEFINE_integer, 'mllm_max_tokens', d.max_tokens,
     'Maximum answer length [tokens].'),
  ]
  for define, name, default, help_ in specs:
    if name not in fv:
      define(name, default, help_, flag_values=fv)


def config_from_flags(flag_values=None) -> MLLMConfig:
  """An :class:`MLLMConfig` from the flags of :func:`define_flags`."""
  from absl import flags

  fv = flags.FLAGS if flag_values is None else flag_values
  return MLLMConfig(
    base_url=fv.mllm_base_url or None,
    model=fv.mllm_model,
    api_key_env=fv.mllm_api_key_env,
    timeout_s=float(fv.mllm_timeout),
    request_deadline_s=float(fv.mllm_deadline),
    scene_deadline_s=float(fv.mllm_scene_deadline),
    max_retries=int(fv.mllm_retries),
    backoff_s=float(fv.mllm_backoff),
    cache_dir=fv.mllm_cache_dir or None,
    max_tokens=int(fv.mllm_max_tokens),
  ).validate()
