"""Converts 3DGS scene files between INRIA PLY, PlayCanvas compressed PLY,
antimatter15 .splat and Niantic .spz, one file or a folder of frames.

  python -m experiments.convert --input=point_cloud.ply --out=scene.spz
  python -m experiments.convert --input=capture.spz --out=capture.ply
  python -m experiments.convert --input=out/run/ply --out=out/run/spz

The format is each path's extension (``.compressed.ply`` writes the
PlayCanvas/SuperSplat form; any PLY reads); a folder converts each of its
files of the ``--input_format`` (default: ply) into ``--out`` with the
output format ``--out_format`` (default: spz), keeping the names (a run's
``ply/frame_%04d.ply`` -> ``frame_%04d.spz``). The Gaussians are copied as
stored: no up-axis turn and no scaling (``load_scene`` orients a scene for
simulating; this does not). A PLY's extra per-Gaussian properties (object
ids...) are kept in a PLY and dropped elsewhere.

What each format keeps (docs/scenes.md, "Scene file formats"): PLY
everything (float32); compressed PLY 11-10-11-bit positions and scales per
chunk of 256 Gaussians, 8-bit colour and SH, ~16 bytes a Gaussian; .spz
the SH up to degree 3, quantised (positions to 1/4096 of a unit, SH to 4-5
bits) and gzipped, about a tenth of the PLY; .splat the DC colour only,
8-bit, 32 bytes a Gaussian, its rows sorted biggest first as
antimatter15's converter sorts them. A .spz of centres beyond 2048 units
gets fewer fraction bits (a coarser step), and .spz to .spz keeps the
antialiasing flag. ``--sh_degree`` truncates (or zero-pads) the SH first.
A PLY is written with zero normals, the INRIA layout that viewers expect.
"""

import os
import time

import numpy as np
from absl import flags
from absl import logging

from experiments.lib import cli
from physsplat_jax.io import export
from physsplat_jax.io import ply
from physsplat_jax.io import spz
from physsplat_jax.io.splat import load_splat
from physsplat_jax.io.splat import save_splat

FORMATS = ('ply', 'compressed', 'splat', 'spz')
# File name endings of the formats ('compressed': PlayCanvas's name).
_ENDINGS = {'ply': '.ply', 'compressed': '.compressed.ply',
            'splat': '.splat', 'spz': '.spz'}

_INPUT = flags.DEFINE_string(
  'input', None, 'A .ply (INRIA or PlayCanvas compressed), .splat or .spz '
  'file, or a folder of such files.')
_OUT = flags.DEFINE_string(
  'out', None, 'Output file (.ply, .splat, .spz), or a folder for an input '
  'folder.')
_INPUT_FORMAT = flags.DEFINE_enum(
  'input_format', 'ply', FORMATS, 'A folder input: the files converted.')
_OUT_FORMAT = flags.DEFINE_enum(
  'out_format', 'spz', FORMATS, 'A folder input: the format written.')
_SH_DEGREE = flags.DEFINE_integer(
  'sh_degree', None, 'SH degree written, 0..3 (truncated or zero-padded); '
  "default: the input's.")
_SPZ_FRAME = flags.DEFINE_enum(
  'spz_stored_frame', 'RUB', ('RUB', 'RDF'),
  ".spz coordinates, read and written: RUB (the format's) or RDF (the "
  "PLY's, unconverted: files from Niantic's ply_to_spz tool).")
_SPZ_VERSION = flags.DEFINE_enum('spz_version', '3', ('2', '3'),
                                 '.spz version written.')


def _format(path: str, flag: str) -> str:
  low = path.lower()
  if low.endswith(_ENDINGS['compressed']):
    return 'compressed'
  ext = os.path.splitext(low)[1].lstrip('.')
  if ext not in ('ply', 'splat', 'spz'):
    raise cli.usage_error(
      f'--{flag}={path}: unknown scene file type {"." + ext if ext else ""!r}'
      '; give a .ply, .compressed.ply, .splat or .spz path (or a folder)')
  return ext


def _load(path: str, fmt: str):
  if fmt in ('ply', 'compressed'):
    return ply.load_ply(path)
  if fmt == 'splat':
    return load_splat(path)
  return spz.load_spz(path, stored_frame=_SPZ_FRAME.value)


def _save(path: str, fmt: str, g, antialiased: bool = False) -> None:
  if _SH_DEGREE.value is not None:
    g = g.with_sh_degree(_SH_DEGREE.value)
  if fmt == 'ply':
    ply.save_ply(path, g.replace(normals=np.zeros((g.num, 3), np.float32)))
  elif fmt == 'compressed':
    ply.save_compressed_ply(path, g.replace(extras={}))
  elif fmt == 'splat':
    save_splat(path, g.replace(extras={}))
  else:
    # Positions beyond +-2048 units get fewer fraction bits (a coarser
    # step), as the pipeline's frames do, instead of an error naming an
    # option this script has not.
    spz.save_spz(path, g.replace(extras={}), stored_frame=_SPZ_FRAME.value,
                 version=int(_SPZ_VERSION.value), antialiased=antialiased,
                 fractional_bits=export.spz_fractional_bits(g.means))


def _pairs() -> list[tuple[str, str, str, str]]:
  """``(input, its format, output, its format)`` per file to convert."""
  src, out = _INPUT.value, _OUT.value
  if not os.path.exists(src):
    raise cli.usage_error(f'--input={src}: no such file or folder')
  if not os.path.isdir(src):
    if os.path.isdir(out):
      raise cli.usage_error(f'--out={out} is a folder; give an output file '
                            '(.ply, .compressed.ply, .splat, .spz) for a '
                            'file input')
    return [(src, _format(src, 'input'), out, _format(out, 'out'))]
  if os.path.exists(out) and not os.path.isdir(out):
    raise cli.usage_error(f'--out={out} is a file; give a folder for the '
                          f'folder --input={src}')
  fin, fout = _INPUT_FORMAT.value, _OUT_FORMAT.value
  names = sorted(n for n in os.listdir(src)
                 if _ends(n, fin) and os.path.isfile(os.path.join(src, n)))
  if not names:
    raise cli.usage_error(f'--input={src} has no {_ENDINGS[fin]} files; '
                          'give --input_format for another kind')
  stem = lambda n: n[:len(n) - len(_ENDINGS[fin])]  # noqa: E731
  pairs = [(os.path.join(src, n), fin,
            os.path.join(out, stem(n) + _ENDINGS[fout]), fout)
           for n in names]
  inputs = {os.path.realpath(p[0]) for p in pairs}
  clash = [p[2] for p in pairs if os.path.realpath(p[2]) in inputs]
  if clash:
    raise cli.usage_error(
      f'--out={out}: converting would overwrite the input {clash[0]} '
      f'({len(clash)} in all); give another folder')
  return pairs


def _ends(name: str, fmt: str) -> bool:
  """Whether file ``name`` is of ``fmt`` (a plain PLY is not a
  ``.compressed.ply``)."""
  low = name.lower()
  if fmt == 'ply' and low.endswith(_ENDINGS['compressed']):
    return False
  return low.endswith(_ENDINGS[fmt])


def main(argv):
  del argv
  if _SH_DEGREE.value is not None and not 0 <= _SH_DEGREE.value <= 3:
    raise cli.usage_error(f'--sh_degree={_SH_DEGREE.value}: give 0..3, or '
                          "leave it out for the input's")
  pairs = _pairs()
  for _, _, out, _ in pairs[:1]:
    cli.check_output_file('out', out)
  t0, read, written = time.perf_counter(), 0, 0
  for i, (src, fin, out, fout) in enumerate(pairs):
    if os.path.abspath(src) == os.path.abspath(out):
      raise cli.usage_error(f'--out={out} is the input itself; give '
                            'another path')
    g = _load(src, fin)
    # (.spz to .spz keeps the antialiasing flag: Gaussians do not hold it.)
    aa = (fin == fout == 'spz'
          and spz.read_spz_header(src).antialiased)
    _save(out, fout, g, antialiased=aa)
    read += os.path.getsize(src)
    written += os.path.getsize(out)
    logging.info('%d/%d %s (%d Gaussians, SH %d) -> %s', i + 1, len(pairs),
                 src, g.num, g.sh_degree, out)
  print(f'{len(pairs)} file(s): {read / 1e6:.2f} MB -> {written / 1e6:.2f} '
        f'MB ({written / max(read, 1):.3f}x) in '
        f'{time.perf_counter() - t0:.1f} s')


if __name__ == '__main__':
  flags.mark_flags_as_required(['input', 'out'])
  cli.run(main)
