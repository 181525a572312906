"""Kernels in an optimised XLA program (``compiled.as_text()``).

Counts what a GPU launches: every instruction of a computation that XLA
emits as a kernel (fusions, copies, custom calls, sorts, ...), loops
expanded by their known trip counts. Used by ``experiments/gpu_kernels.py``.
"""

from __future__ import annotations

import collections
import re

# Instructions that launch nothing: buffers, views and control.
_FREE = frozenset((
  'parameter', 'get-tuple-element', 'tuple', 'bitcast', 'constant',
  'after-all', 'partition-id', 'replica-id', 'opt-barrier', 'add-dependency',
))


def parse_hlo(text: str) -> tuple[dict[str, list[tuple[str, str]]], str]:
  """``({computation: [(opcode, line), ...]}, entry name)`` of an HLO
  module's text (``compiled.as_text()``)."""
  comps: dict[str, list[tuple[str, str]]] = {}
  entry, cur = '', None
  for line in text.splitlines():
    head = re.match(r'^(ENTRY )?%?([\w.\-]+) .*\{$', line)
    if head:
      cur = head.group(2)
      comps[cur] = []
      if head.group(1):
        entry = cur
      continue
    inst = re.match(r'^\s+(?:ROOT )?%?[\w.\-]+ = .*? ([a-z][\w\-]*)\(', line)
    if cur is not None and inst:
      comps[cur].append((inst.group(1), line))
  return comps, entry


def _loop(line: str) -> tuple[str, int | None]:
  """Body computation and known trip count (None if unknown) of a while."""
  body = re.search(r'body=%?([\w.\-]+)', line).group(1)
  trip = re.search(r'"known_trip_count":\{"n":"(\d+)"', line)
  return body, int(trip.group(1)) if trip else None


def _callee(op: str, line: str) -> str | None:
  """The computation a ``call`` runs inline (XLA:CPU wraps loops in them,
  ``xla_cpu_small_call``, in JAX 0.12), else None."""
  if op != 'call':
    return None
  return re.search(r'to_apply=%?([\w.\-]+)', line).group(1)


def kernels(comps, name: str) -> collections.Counter:
  """Kernel launches of computation ``name`` by kind, nested loops
  counted as body kernels times their known trip count (key 'loop'),
  calls as what they run."""
  out: collections.Counter = collections.Counter()
  for op, line in comps[name]:
    if op in _FREE:
      continue
    callee = _callee(op, line)
    if callee is not None:
      out.update(kernels(comps, callee))
      continue
    if op == 'while':
      body, trip = _loop(line)
      n = 1 if trip is None else trip
      out['loop'] += n * sum(kernels(comps, body).values())
      continue
    if op == 'fusion':
      out['fusion:' + re.search(r'kind=(\w+)', line).group(1)] += 1
      continue
    out[op] += 1
  return out


def substep_kernels(text: str, substeps: int) -> dict:
  """Kernels of one substep: the body of the loop with trip count
  ``substeps`` reachable from the entry (the scan over substeps)."""
  comps, entry = parse_hlo(text)
  stack, seen = [entry], set()
  while stack:
    name = stack.pop()
    if name in seen:
      continue
    seen.add(name)
    for op, line in comps[name]:
      callee = _callee(op, line)
      if callee is not None:
        stack.append(callee)
      if op != 'while':
        continue
      body, trip = _loop(line)
      if trip == substeps:
        k = kernels(comps, body)
        return dict(kernels=sum(k.values()), by_kind=dict(sorted(k.items())))
      stack.append(body)
  raise ValueError(f'no loop with trip count {substeps} in the program')


# Name-scope components of a substep that say nothing of its steps.
_PLUMBING = frozenset(('checkpoint', 'while', 'body', 'cond', 'closed_call',
                       'remat', 'scan'))


def kernel_labels(text: str) -> dict[str, str]:
  """``{kernel name: name scope}`` of an optimised program's instructions.

  Kernel names are instruction names with ``.`` written ``_`` (as the
  profiler and XLA's thunk dumps show them); the label is the JAX name
  scope of the instruction's ``op_name`` metadata (``p2g/scatter-add``),
  without the jit and loop plumbing.
  """
  out = {}
  for m in re.finditer(r'^\s+(?:ROOT )?%?([\w.\-]+) = (.*)$', text,
                       re.MULTILINE):
    op = re.search(r'metadata=\{op_name="([^"]*)"', m.group(2))
    parts = op.group(1).split('/')[1:] if op else []
    label = '/'.join(p for p in parts if p not in _PLUMBING)
    out[m.group(1).replace('.', '_')] = label
    out.setdefault(m.group(1), label)
  return out
