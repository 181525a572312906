"""Device time per kernel, from a JAX profiler trace.

``jax.profiler.trace`` records, on a GPU, every kernel and copy the device
ran (CUPTI activity, kernels launched from CUDA graphs included), one line
per stream of the ``/device:GPU:N`` plane; on the CPU, XLA's thunks on the
client's threads. :func:`kernel_times` reads such a trace back
(``jax.profiler.ProfileData``) and sums the time of each kernel by name, so
a benchmark can say where a substep's device time goes and how much of its
wall time the device was busy at all (the rest is launch overhead or the
host). Kernel names are XLA's instruction names with ``.`` written ``_``
(``input_reduce_fusion.1`` runs as ``input_reduce_fusion_1``);
``experiments/lib/hlo.py``'s ``kernel_labels`` maps them to the JAX name
scopes they came from. Used by ``benchmark_substep --profile``.
"""

from __future__ import annotations

import collections
import glob
import os

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
      k = kernels[e.name]
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
    top=[dict(kernel=name, label=labels.get(name, ''),
              us=k['ns'] / calls / 1e3, launches=k['count'] / calls)
         for name, k in rows[:top]])
