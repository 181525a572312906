"""A scripted OpenAI-compatible chat-completions server on 127.0.0.1 (tests).

Not a test module (no ``_test`` suffix): imported by mllm_client_test.py and
perception_test.py. Each request is answered by ``script(request, n)``,
which returns a :class:`Reply`: an assistant text, an HTTP status with a raw
body, an optional delay before answering (to simulate a hang), and an
optional drip (the body sent one byte every ``drip_s`` seconds, a server
that never trips a per-read timeout).
"""

from __future__ import annotations

import dataclasses
import http.server
import json
import threading
from collections.abc import Callable


@dataclasses.dataclass
class Reply:
  text: str | None = None  # assistant content (wrapped as chat.completion)
  status: int = 200
  body: str | None = None  # raw body (overrides text)
  delay_s: float = 0.0  # sleep before answering (hang)
  headers: tuple[tuple[str, str], ...] = ()
  drip_s: float = 0.0  # seconds between body bytes (slow drip)


def chat_body(text: str) -> str:
  return json.dumps({
    'id': 'chatcmpl-test', 'object': 'chat.completion', 'model': 'test',
    'choices': [{'index': 0, 'finish_reason': 'stop',
                 'message': {'role': 'assistant', 'content': text}}],
  })


class ScriptedChatServer:
  """``with ScriptedChatServer(script) as s: ... s.url ... s.requests``."""

  def __init__(self, script: Callable[[dict, int], Reply]):
    self.script = script
    self.requests: list[dict] = []
    self.headers: list[dict] = []
    self._stop = threading.Event()
    self._lock = threading.Lock()
    outer = self

    class Handler(http.server.BaseHTTPRequestHandler):
      protocol_version = 'HTTP/1.1'

      def log_message(self, *args):  # keep test output quiet
        del args

      def do_POST(self):  # noqa: N802 - http.server API
        n = int(self.headers.get('Content-Length', 0))
        raw = self.rfile.read(n)
        try:
          req = json.loads(raw)
        except json.JSONDecodeError:
          req = {'_raw': raw.decode('utf-8', 'replace')}
        with outer._lock:
          outer.requests.append(req)
          outer.headers.append(dict(self.headers))
          count = len(outer.requests)
        reply = outer.script(req, count)
        if reply.delay_s and outer._stop.wait(reply.delay_s):
          return
        body = reply.body if reply.body is not None else chat_body(
          reply.text or '')
        data = body.encode('utf-8')
        try:
          self.send_response(reply.status)
          self.send_header('Content-Type', 'application/json')
          self.send_header('Content-Length', str(len(data)))
          for k, v in reply.headers:
            self.send_header(k, v)
          self.end_headers()
          if not reply.drip_s:
            self.wfile.write(data)
            return
          for i in range(len(data)):
            self.wfile.write(data[i:i + 1])
            self.wfile.flush()
            if outer._stop.wait(reply.drip_s):
              return
        except (BrokenPipeError, ConnectionResetError):
          pass  # the client gave up (timeout test)

    self._server = http.server.ThreadingHTTPServer(('127.0.0.1', 0), Handler)
    self._server.daemon_threads = True
    self._server.handle_error = lambda *a: None
    self.port = self._server.server_address[1]
    self.url = f'http://127.0.0.1:{self.port}/v1'
    self._thread = threading.Thread(
      target=lambda: self._server.serve_forever(poll_interval=0.02),
      daemon=True)

  def __enter__(self):
    self._thread.start()
    return self

  def __exit__(self, *exc):
    self._stop.set()
    self._server.shutdown()
    self._server.server_close()
    self._thread.join(timeout=5)

  @property
  def num_requests(self) -> int:
    with self._lock:
      return len(self.requests)


def user_text(req: dict) -> str:
  """The text part of the last user message of a request."""
  msg = req['messages'][-1]['content']
  if isinstance(msg, str):
    return msg
  return ''.join(p.get('text', '') for p in msg if p.get('type') == 'text')
