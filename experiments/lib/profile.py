"""Device time per kernel, from a JAX profiler trace.

``jax.profiler.trace`` records, on a GPU, every kernel and copy the device
ran (CUPTI activity, kernels launched from CUDA graphs included), one line
per stream of the ``/device:GPU:N`` plane; on the CPU, XLA's thunks on the
client's threads. :func:`kernel_times` reads such a trace back
(``jax.profiler.ProfileData``) and sums the time of each kernel by name, so
a benchmark can say where a substep's device time goes and how much of its
wall time the device was busy at all (the rest is launch overhead or the
host). Kernel names (after the program's name where the trace records it) are
XLA's instruction names with ``.`` written ``_``
(``input_reduce_fusion.1`` runs as ``input_reduce_fusion_1``);
``experiments/lib/hlo.py``'s ``kernel_labels`` maps them to the JAX name
scopes they came from. Used by ``benchmark_substep --profile`` and, with
:class:`FrameWindow`, ``experiments.simulate --profile_frames``.
"""

from __future__ import annotations

import collections
import glob
import os
import time

import jax

# Lines of a device plane that repeat the streams' events grouped otherwise
# (they would count each kernel twice).
_DERIVED = ('XLA Modules', 'XLA Ops', 'Async XLA Ops', 'Steps',
            'Framework Ops', 'Framework Name Scope', 'Source code',
            'XLA TraceMe', 'TensorFlow Name Scope', 'TensorFlow Ops')


def trace(fn, logdir: str):
  """Runs ``fn()`` (to completion) under the profiler; returns its result
  and the path of the trace (``*.xplane.pb``) it wrote under ``logdir``."""
  with jax.profiler.trace(logdir):
    out = jax.block_until_ready(fn())
  return out, newest_trace(logdir)


def newest_trace(logdir: str) -> str:
  """The newest ``*.xplane.pb`` under ``logdir``."""
  paths = glob.glob(os.path.join(logdir, '**', '*.xplane.pb'),
                    recursive=True)
  if not paths:
    raise FileNotFoundError(f'the profiler wrote no trace under {logdir}')
  return max(paths, key=os.path.getmtime)


def _leaves(events, host: bool):
  """The events of one line that enclose no other event of it (a CPU
  thunk such as a while loop encloses its body's; GPU streams do not
  nest), without zero-length markers and ``end:`` records, and on the
  host without the thread pool's and thunk executor's own records
  (``ThunkExecutor::Execute``; on a GPU ``::`` is in template kernels'
  names)."""
  evs = sorted((e for e in events if e.duration_ns > 0
                and not e.name.startswith('end: ')
                and not (host and '::' in e.name)),
               key=lambda e: (e.start_ns, -e.duration_ns))
  out = []
  for i, e in enumerate(evs):
    nxt = evs[i + 1] if i + 1 < len(evs) else None
    if nxt is None or nxt.start_ns >= e.start_ns + e.duration_ns:
      out.append(e)
  return out


def _name(event) -> str:
  """A kernel's name, prefixed ``module:`` where the trace says which XLA
  program launched it (GPU kernels annotated with ``hlo_module``), since
  different programs reuse names such as ``loop_add_fusion``."""
  stats = dict(event.stats)
  module = stats.get('hlo_module')
  return f'{module}:{event.name}' if module else event.name


def _lines(data):
  """``(plane name, [lines])`` whose events are the device's work: the
  streams of the first GPU/TPU plane, else the CPU client's threads."""
  for plane in data.planes:
    if plane.name.startswith(('/device:GPU', '/device:TPU')):
      lines = [ln for ln in plane.lines if ln.name not in _DERIVED]
      if lines:
        return plane.name, lines
  for plane in data.planes:
    if plane.name == '/host:CPU':
      return plane.name, [ln for ln in plane.lines if 'XLA' in ln.name]
  return None, []


def kernel_times(path: str) -> dict:
  """Kernels of a trace, summed by name.

  Returns:
    ``dict(device=plane name, kernels={name: {'count', 'ns'}}, busy_ns=
    total kernel time, span_ns=first start to last end)``; ``device`` is
    None and ``kernels`` empty when the trace holds no device work. On
    the CPU (``/host:CPU``) XLA's threads run thunks side by side, and
    ``busy_ns`` is their sum over the threads.
  """
  data = jax.profiler.ProfileData.from_file(path)
  device, lines = _lines(data)
  kernels: dict = collections.defaultdict(lambda: dict(count=0, ns=0.0))
  first, last = float('inf'), float('-inf')
  for line in lines:
    for e in _leaves(line.events, device == '/host:CPU'):
      k = kernels[_name(e)]
      k['count'] += 1
      k['ns'] += e.duration_ns
      first = min(first, e.start_ns)
      last = max(last, e.start_ns + e.duration_ns)
  busy = sum(k['ns'] for k in kernels.values())
  return dict(device=device, kernels=dict(kernels), busy_ns=busy,
              span_ns=max(last - first, 0.0) if kernels else 0.0)


def per_call(times: dict, calls: int, labels: dict[str, str] | None = None,
             top: int = 12) -> dict:
  """:func:`kernel_times` per call (e.g. per substep): device-busy
  microseconds, kernel launches, and the ``top`` kernels by time with
  their labels (``{kernel: label}``, e.g. from ``hlo.kernel_labels``)."""
  labels = labels or {}
  rows = sorted(times['kernels'].items(), key=lambda kv: -kv[1]['ns'])
  return dict(
    device=times['device'],
    busy_us=times['busy_ns'] / calls / 1e3,
    launches=sum(k['count'] for k in times['kernels'].values()) / calls,
    top=[dict(kernel=name,
              label=labels.get(name) or labels.get(name.split(':', 1)[-1], ''),
              us=k['ns'] / calls / 1e3, launches=k['count'] / calls)
         for name, k in rows[:top]])


class FrameWindow:
  """A ``pipeline.run`` ``on_frame`` hook that traces frames ``start`` to
  ``stop``: the trace starts when frame ``start`` has been handed to the
  writers and stops when frame ``stop`` has, so it holds ``stop - start``
  frames of the steady-state loop (with the pipelined loop, the device
  works a frame or two ahead of the host). :meth:`summary` gives the
  device's busy time and the host's wall time per frame, and the costliest
  kernels of all the programs the frames ran (MPM, deformation, render).
  The wall time is the traced run's (the tracer's overhead included);
  ``benchmark_pipeline`` times untraced runs beside it.
  """

  def __init__(self, start: int, stop: int, logdir: str):
    if not 0 <= start < stop:
      raise ValueError(f'profile frames: need 0 <= start < stop, got '
                       f'{start}, {stop}')
    self.start, self.stop, self.logdir = start, stop, logdir
    self._t0 = self._t1 = None

  @property
  def tracing(self) -> bool:
    return self._t0 is not None and self._t1 is None

  def __call__(self, frame: int, means=None, image=None) -> None:
    del means, image
    if frame == self.start:
      jax.profiler.start_trace(self.logdir)
      self._t0 = time.perf_counter()
    elif frame == self.stop and self.tracing:
      self._t1 = time.perf_counter()
      jax.profiler.stop_trace()

  def close(self) -> None:
    """Stops a trace the run left open (it ended or failed before
    ``stop``)."""
    if self.tracing:
      self._t1 = time.perf_counter()
      jax.profiler.stop_trace()

  def summary(self, top: int = 15) -> dict | None:
    """Per traced frame: ``wall_ms`` (host), ``busy_ms`` (device), their
    ratio, kernel launches, and the ``top`` kernels; None if nothing was
    traced."""
    if self._t0 is None:
      return None
    self.close()
    frames = self.stop - self.start
    times = kernel_times(newest_trace(self.logdir))
    got = per_call(times, frames, top=top)
    wall_ms = (self._t1 - self._t0) * 1e3 / frames
    return dict(frames=[self.start, self.stop], device=got['device'],
                wall_ms=wall_ms, busy_ms=got['busy_us'] / 1e3,
                busy_fraction=got['busy_us'] / 1e3 / wall_ms,
                launches=got['launches'], top=got['top'])
