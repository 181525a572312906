"""Registers, spills and occupancy of compiled GPU kernels, without a GPU.

XLA writes the PTX of every kernel it compiles when given
``--xla_dump_to=DIR`` (deviceless compilation included) and a
``*.thunk_sequence.txt`` with each launch's threads and shared memory.
NVIDIA's ``ptxas -v`` (in the ``nvidia-cuda-nvcc`` wheels that CUDA builds
of jaxlib install, or on ``PATH``) reports the registers per thread and the
bytes spilled to local memory; with the GPU's limits from its
``GpuTargetConfigProto`` that gives the resident warps per SM. Used by
``experiments/gpu_kernels.py --targets=render``.
"""

from __future__ import annotations

import glob
import os
import re
import shutil
import subprocess


def find_ptxas() -> str | None:
  """Path of ``ptxas`` (NVIDIA's pip wheels first, then ``PATH``)."""
  try:
    import nvidia  # noqa: PLC0415
    for root in nvidia.__path__:
      for sub in ('cu13/bin', 'cuda_nvcc/bin', 'cu12/bin'):
        path = os.path.join(root, sub, 'ptxas')
        if os.access(path, os.X_OK):
          return path
  except ImportError:
    pass
  return shutil.which('ptxas')


def spec_limits(spec_text: str) -> dict:
  """The per-SM limits of a ``GpuTargetConfigProto`` (text) that bound
  occupancy, and its ptxas architecture (``sm_90a`` for an H100)."""
  def field(name, default):
    m = re.search(rf'\b{name}: (\d+)', spec_text)
    return int(m.group(1)) if m else default

  major = field('major', 9)
  minor = field('minor', 0)
  return dict(
    arch=f'sm_{major}{minor}' + ('a' if major >= 9 else ''),
    registers=field('registers_per_core_limit', 65536),
    threads=field('threads_per_core_limit', 2048),
    shared=field('shared_memory_per_core', 233472),
    blocks=32,  # resident blocks per SM, compute capability >= 8.6
  )


def _launches(dump_dir: str) -> dict[str, tuple[int, int]]:
  """{kernel: (threads per block, dynamic shared memory bytes)}."""
  out = {}
  for path in glob.glob(os.path.join(dump_dir, '*.thunk_sequence.txt')):
    with open(path) as f:
      for line in f:
        m = re.search(r'\] (\S+) grid: \[[^]]*\] threads: \[(\d+), (\d+), '
                      r'(\d+)\]\s+shared_memory: (\d+)', line)
        if m:
          threads = int(m.group(2)) * int(m.group(3)) * int(m.group(4))
          out[m.group(1)] = (threads, int(m.group(5)))
  return out


def occupancy(regs: int, threads: int, shared: int, limits: dict) -> int:
  """Resident warps per SM (registers allocated per warp in units of 256)."""
  warps = -(-threads // 32)
  per_warp = -(-regs * 32 // 256) * 256
  blocks = min(limits['blocks'], limits['threads'] // threads,
               limits['registers'] // max(per_warp * warps, 1),
               limits['shared'] // shared if shared else limits['blocks'])
  return blocks * warps


def kernel_resources(dump_dir: str, names: tuple[str, ...], limits: dict,
                     ptxas: str) -> dict[str, dict]:
  """ptxas' report for the kernels ``names`` found in ``dump_dir``:
  ``{name: dict(registers, spill_bytes, threads, shared_bytes, warps_per_sm,
  ptx_instructions)}`` (the last counts PTX statements, a size measure)."""
  launches = _launches(dump_dir)
  out = {}
  for path in sorted(glob.glob(os.path.join(dump_dir, '*.ptx'))):
    with open(path) as f:
      text = f.read()
    m = re.search(r'\.entry (\w+)', text)
    if not m or m.group(1) not in names or m.group(1) in out:
      continue
    name = m.group(1)
    report = subprocess.run(
      [ptxas, '-v', f"-arch={limits['arch']}", path, '-o', os.devnull],
      capture_output=True, text=True, check=True).stderr
    regs = int(re.search(r'Used (\d+) registers', report).group(1))
    spill = int(re.search(r'(\d+) bytes spill stores', report).group(1))
    threads, shared = launches.get(name, (0, 0))
    out[name] = dict(
      registers=regs, spill_bytes=spill, threads=threads,
      shared_bytes=shared,
      warps_per_sm=occupancy(regs, threads, shared, limits) if threads
      else None,
      ptx_instructions=sum(
        1 for line in text.splitlines()
        if line.strip().endswith(';')
        and not line.strip().startswith(('.', '//'))))
  return out
