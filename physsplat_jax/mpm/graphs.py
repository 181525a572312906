"""How a CUDA GPU launches a compiled frame (``SimConfig.gpu_graphs``).

XLA:GPU runs a program's kernels as CUDA graphs ("command buffers"), by
default one per run of straight-line kernels: each substep of a frame's
``lax.scan`` is one graph, launched by the host once per iteration.
'frame' asks for the loop itself in the graph too (``WHILE``,
``CONDITIONAL``), 'off' for none. The choice is a compile option of the
frame's executable only; it changes no value. On an H200 'frame' was no
faster than the default (docs/benchmarks.md).
"""

from __future__ import annotations

import warnings

import jax

# XLA's command-buffer (CUDA graph) kinds per SimConfig.gpu_graphs, most
# complete first: a kind this XLA does not know fails the compile, and the
# next list is tried. 'substep' passes nothing (XLA's own default).
_GRAPH_KINDS = {
  'frame': ('FUSION,CUBLAS,CUBLASLT,CUSTOM_CALL,CUDNN,DYNAMIC_SLICE_FUSION,'
            'WHILE,CONDITIONAL',
            'FUSION,CUBLAS,CUSTOM_CALL,WHILE,CONDITIONAL'),
  'off': ('',),
}


def compile_frame(lowered, gpu_graphs: str, *, force: bool = False):
  """Compiles a lowered frame program with ``SimConfig.gpu_graphs``' XLA
  command buffers on a GPU (elsewhere, or with ``'substep'``, as XLA
  compiles by default; ``force`` passes them on any backend: the CPU's XLA
  accepts and ignores them, which tests use). Falls back to XLA's default,
  with a warning, when this XLA rejects them.
  """
  kinds = _GRAPH_KINDS.get(gpu_graphs, ()) if (
    force or jax.default_backend() == 'gpu') else ()
  for i, k in enumerate(kinds):
    try:
      compiled = lowered.compile(
        compiler_options={'xla_gpu_enable_command_buffer': k})
    except Exception as e:  # noqa: BLE001 - an XLA without these kinds
      if 'xla_gpu_enable_command_buffer' in str(e):
        continue  # this XLA lacks a kind of the list: the next list
      # Not the option: XLA's default compile, or its error.
      compiled = lowered.compile()
      warnings.warn(
        f'SimConfig.gpu_graphs = {gpu_graphs!r}: the frame did not compile '
        f'with command buffers {k!r} ({str(e).splitlines()[0][:200]}); '
        "compiled with XLA's default (gpu_graphs='substep') instead.",
        RuntimeWarning, stacklevel=2)
      return compiled
    if i:
      warnings.warn(
        f'SimConfig.gpu_graphs = {gpu_graphs!r}: this XLA lacks a kind of '
        f'{kinds[0]!r}; compiled with {k!r}.', RuntimeWarning, stacklevel=2)
    return compiled
  if kinds:
    warnings.warn(
      f'SimConfig.gpu_graphs = {gpu_graphs!r}: this XLA knows none of the '
      f'command-buffer lists {list(kinds)}; compiled with its default '
      "(gpu_graphs='substep').", RuntimeWarning, stacklevel=2)
  return lowered.compile()
