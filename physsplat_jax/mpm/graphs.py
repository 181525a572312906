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
  error = None
  for k in kinds:
    try:
      return lowered.compile(
        compiler_options={'xla_gpu_enable_command_buffer': k})
    except Exception as e:  # noqa: BLE001 - an XLA without these kinds
      error = e
      if 'xla_gpu_enable_command_buffer' not in str(e):
        break  # not the option: XLA's default compile says what it is
  if error is not None:
    warnings.warn(
      f'SimConfig.gpu_graphs = {gpu_graphs!r}: this XLA could not compile '
      f'the frame with command buffers {kinds[0]!r} '
      f'({str(error).splitlines()[0][:200]}); using its default '
      "(gpu_graphs='substep').", RuntimeWarning, stacklevel=2)
  return lowered.compile()
