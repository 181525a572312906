"""PLY 1.0 files in NumPy: a header parser, a reader and a writer.

What is read: binary little- and big-endian and ASCII PLY 1.0 with any scalar
types (``char/int8 uchar/uint8 short/int16 ushort/uint16 int/int32
uint/uint32 float/float32 double/float64``); every element is parsed (so
list properties such as faces are skipped correctly). What is written:
binary little-endian (default) or ASCII with ``\\n`` line endings. The 3DGS
layer on top of it is :mod:`physsplat_jax.io.ply`.
"""

from __future__ import annotations

import dataclasses
import os
import re

import numpy as np

from physsplat_jax.errors import PhysSplatError
from physsplat_jax.io import paths

PathLike = str | os.PathLike

# PLY scalar type names (and their aliases) -> NumPy type codes.
PLY_TYPES = {
  'char': 'i1', 'int8': 'i1',
  'uchar': 'u1', 'uint8': 'u1',
  'short': 'i2', 'int16': 'i2',
  'ushort': 'u2', 'uint16': 'u2',
  'int': 'i4', 'int32': 'i4',
  'uint': 'u4', 'uint32': 'u4',
  'float': 'f4', 'float32': 'f4',
  'double': 'f8', 'float64': 'f8',
}  # fmt: skip
# NumPy type codes -> the canonical PLY names we write.
_WRITE_NAMES = {
  'i1': 'char', 'u1': 'uchar', 'i2': 'short', 'u2': 'ushort',
  'i4': 'int', 'u4': 'uint', 'f4': 'float', 'f8': 'double',
}  # fmt: skip
FORMATS = ('binary_little_endian', 'binary_big_endian', 'ascii')
_ENDIAN = {'binary_little_endian': '<', 'binary_big_endian': '>', 'ascii': '<'}

_MAX_HEADER_BYTES = 1 << 20
_NAME_RE = re.compile(r'^[^\s]+$')



class PlyError(PhysSplatError, ValueError):
  """A PLY file that cannot be read (or Gaussians that cannot be written)."""


@dataclasses.dataclass(frozen=True)
class PlyProperty:
  """One property of a PLY element.

  Attributes:
    name: property name.
    dtype: NumPy type code of the value (or of the list items), e.g. ``'f4'``.
    count_dtype: for a list property, the type code of its length prefix;
      None for a scalar property.
  """

  name: str
  dtype: str
  count_dtype: str | None = None

  @property
  def is_list(self) -> bool:
    return self.count_dtype is not None


@dataclasses.dataclass(frozen=True)
class PlyElement:
  """One element of a PLY header: a name, a row count and its properties."""

  name: str
  count: int
  properties: tuple[PlyProperty, ...]

  @property
  def property_names(self) -> tuple[str, ...]:
    return tuple(p.name for p in self.properties)

  @property
  def has_lists(self) -> bool:
    return any(p.is_list for p in self.properties)


@dataclasses.dataclass(frozen=True)
class PlyHeader:
  """A parsed PLY header.

  Attributes:
    format: ``'binary_little_endian'``, ``'binary_big_endian'`` or
      ``'ascii'``.
    elements: the elements in file order.
    comments: the ``comment`` lines (without the keyword).
    size: header length in bytes, including the ``end_header`` line.
  """

  format: str
  elements: tuple[PlyElement, ...]
  comments: tuple[str, ...] = ()
  size: int = 0

  def element(self, name: str) -> PlyElement | None:
    for e in self.elements:
      if e.name == name:
        return e
    return None


# ----------------------------------------------------------------------------
# Header.


def _parse_header(data: bytes, path) -> PlyHeader:
  """Parses the header at the start of ``data`` (the whole file or a prefix)."""
  if not (data.startswith(b'ply\n') or data.startswith(b'ply\r\n')):
    raise PlyError(
      f'{path}: not a PLY file (it must start with the line "ply"; '
      f'found {data[:16]!r})'
    )
  m = re.search(rb'(^|\n)end_header\r?\n', data[:_MAX_HEADER_BYTES])
  if m is None:
    if len(data) < _MAX_HEADER_BYTES and b'end_header' in data:
      # Header ends the file without a newline: an empty body.
      m = re.search(rb'(^|\n)end_header\r?$', data)
    if m is None:
      raise PlyError(
        f'{path}: PLY header has no "end_header" line (file truncated or '
        'not a PLY file)'
      )
  size = m.end()
  try:
    text = data[:size].decode('ascii')
  except UnicodeDecodeError as e:
    raise PlyError(f'{path}: PLY header is not ASCII text ({e})') from None
  fmt = None
  elements: list[tuple[str, int, list[PlyProperty]]] = []
  comments = []
  for lineno, raw in enumerate(text.splitlines()[1:], start=2):
    words = raw.split()
    if not words:
      continue
    key = words[0]
    where = f'{path}: PLY header line {lineno} ({raw.strip()!r})'
    if key == 'format':
      if len(words) != 3 or words[1] not in FORMATS:
        raise PlyError(
          f'{where}: unsupported format; expected one of {FORMATS} '
          'with version 1.0'
        )
      if words[2] not in ('1.0', '1'):
        raise PlyError(f'{where}: unsupported PLY version {words[2]!r}')
      fmt = words[1]
    elif key in ('comment', 'obj_info'):
      if key == 'comment':
        comments.append(raw.strip()[len('comment') :].strip())
    elif key == 'element':
      if len(words) != 3 or not words[2].isdigit():
        raise PlyError(f'{where}: expected "element <name> <count>"')
      if words[1] in [e[0] for e in elements]:
        raise PlyError(
          f'{where}: duplicate element {words[1]!r} (each element is '
          'declared once); merge the two declarations or re-export the file'
        )
      elements.append((words[1], int(words[2]), []))
    elif key == 'property':
      if not elements:
        raise PlyError(f'{where}: property before any element')
      if len(words) == 3:
        if words[1] not in PLY_TYPES:
          raise PlyError(
            f'{where}: unknown PLY type {words[1]!r}; known: '
            f'{sorted(PLY_TYPES)}'
          )
        prop = PlyProperty(words[2], PLY_TYPES[words[1]])
      elif len(words) == 5 and words[1] == 'list':
        for t in words[2:4]:
          if t not in PLY_TYPES:
            raise PlyError(f'{where}: unknown PLY type {t!r}')
        prop = PlyProperty(words[4], PLY_TYPES[words[3]], PLY_TYPES[words[2]])
      else:
        raise PlyError(
          f'{where}: expected "property <type> <name>" or '
          '"property list <count type> <item type> <name>"'
        )
      if prop.name in [p.name for p in elements[-1][2]]:
        raise PlyError(
          f'{where}: duplicate property {prop.name!r} in element '
          f'{elements[-1][0]!r}'
        )
      elements[-1][2].append(prop)
    elif key == 'end_header':
      break
    else:
      raise PlyError(f'{where}: unknown header keyword {key!r}')
  if fmt is None:
    raise PlyError(f'{path}: PLY header has no "format" line')
  return PlyHeader(
    format=fmt,
    elements=tuple(PlyElement(n, c, tuple(p)) for n, c, p in elements),
    comments=tuple(comments),
    size=size,
  )


def _read_bytes(path, what='PLY', error=PlyError, size=-1) -> bytes:
  """The file's bytes (the first ``size`` with size >= 0); OS errors named."""
  if not isinstance(path, (str, bytes, os.PathLike)):
    # (open() takes an int as a file descriptor: it would read another file.)
    raise error(
      f'expected a {what} file path, got {type(path).__name__} {path!r}'
    )
  try:
    with open(path, 'rb') as f:
      return f.read(size)
  except FileNotFoundError:
    raise FileNotFoundError(f'{what} file not found: {path}') from None
  except IsADirectoryError:
    raise error(f'{path}: is a directory, not a {what} file') from None
  except OSError as e:
    raise error(
      f'{path}: cannot read the {what} file ({e.strerror or e})'
    ) from None


def read_ply_header(path: PathLike) -> PlyHeader:
  """Reads only the header of a PLY file.

  Args:
    path: file path.

  Returns:
    The parsed :class:`PlyHeader`.

  Raises:
    PlyError: not a PLY file, a directory or a malformed header.
    FileNotFoundError: no such file (named).
  """
  return _parse_header(_read_bytes(path, size=_MAX_HEADER_BYTES), path)


def check_writable_file(path, what='PLY', error=PlyError) -> str:
  """:func:`physsplat_jax.io.paths.check_output_file` for a PLY file."""
  return paths.check_output_file(path, error, what=what)


def open_output(path, what='PLY', error=PlyError):
  """:func:`physsplat_jax.io.paths.open_output` for a PLY file."""
  return paths.open_output(path, error, what=what)


# ----------------------------------------------------------------------------
# Body.


def _scalar_dtype(element: PlyElement, endian: str) -> np.dtype:
  return np.dtype([(p.name, endian + p.dtype) for p in element.properties])


def _native(a: np.ndarray) -> np.ndarray:
  # Little-endian fields on a little-endian host stay views (no copy).
  return a.astype(a.dtype.newbyteorder('='), copy=False)


def _truncated(path, element, expected, actual):
  return PlyError(
    f'{path}: truncated PLY payload in element {element.name!r} '
    f'({element.count} rows): expected {expected} bytes, file has {actual}'
  )


def _trailing(path, header, extra, unit, row_size=None):
  """Data after the last declared element: a wrong count, not to drop."""
  declared = ', '.join(f'{e.count} {e.name}' for e in header.elements)
  last = header.elements[-1] if header.elements else None
  hint = ''
  if last is not None and row_size and extra % row_size == 0:
    hint = (
      f', that is {extra // row_size} more {last.name} rows than the '
      f'header\'s {last.count}'
    )
  return PlyError(
    f'{path}: {extra} {unit} after the declared '
    f'{declared or "(no elements)"} rows that no element of the header '
    f'accounts for{hint} (header count wrong?); fix the "element" line(s) '
    'of the header or re-export the file'
  )


def _read_binary(
  data: bytes, header: PlyHeader, path, matrices: dict | None = None
) -> dict:
  """Binary payload -> columns; homogeneous elements also go to matrices."""
  endian = _ENDIAN[header.format]
  offset = header.size
  out = {}
  # Fast path: a total size check up front gives one clear message.
  if not any(e.has_lists for e in header.elements):
    expected = sum(
      e.count * _scalar_dtype(e, endian).itemsize for e in header.elements
    )
    actual = len(data) - header.size
    if actual < expected:
      shapes = ', '.join(
        f'{e.name}: {e.count} x {_scalar_dtype(e, endian).itemsize} B'
        for e in header.elements
      )
      raise PlyError(
        f'{path}: truncated PLY payload: expected {expected} bytes after '
        f'the header ({shapes}), file has {actual}'
      )
  for e in header.elements:
    if not e.has_lists:
      dt = _scalar_dtype(e, endian)
      nbytes = e.count * dt.itemsize
      if offset + nbytes > len(data):
        raise _truncated(path, e, nbytes, len(data) - offset)
      codes = {p.dtype for p in e.properties}
      if matrices is not None and len(codes) == 1:
        # One (count, P) matrix: column blocks are then cheap slices.
        mat = np.frombuffer(
          data, endian + codes.pop(), e.count * len(e.properties), offset
        ).reshape(e.count, len(e.properties))
        mat = _native(mat)
        matrices[e.name] = mat
        out[e.name] = {p.name: mat[:, i] for i, p in enumerate(e.properties)}
      else:
        rows = np.frombuffer(data, dt, e.count, offset)
        out[e.name] = {p.name: _native(rows[p.name]) for p in e.properties}
      offset += nbytes
      continue
    cols = {p.name: [] for p in e.properties}
    for _ in range(e.count):
      for p in e.properties:
        if p.is_list:
          cdt = np.dtype(endian + p.count_dtype)
          if offset + cdt.itemsize > len(data):
            raise _truncated(path, e, offset + cdt.itemsize, len(data))
          n = int(np.frombuffer(data, cdt, 1, offset)[0])
          if n < 0:
            raise PlyError(
              f'{path}: negative list length {n} in {e.name}.{p.name} '
              f'(byte {offset}); the file is corrupt'
            )
          offset += cdt.itemsize
          idt = np.dtype(endian + p.dtype)
          if offset + n * idt.itemsize > len(data):
            raise _truncated(path, e, offset + n * idt.itemsize, len(data))
          cols[p.name].append(_native(np.frombuffer(data, idt, n, offset)))
          offset += n * idt.itemsize
        else:
          dt = np.dtype(endian + p.dtype)
          if offset + dt.itemsize > len(data):
            raise _truncated(path, e, offset + dt.itemsize, len(data))
          cols[p.name].append(np.frombuffer(data, dt, 1, offset)[0])
          offset += dt.itemsize
    out[e.name] = {
      p.name: (
        cols[p.name]
        if p.is_list
        else np.asarray(cols[p.name], np.dtype(p.dtype))
      )
      for p in e.properties
    }
  if offset < len(data):
    last = header.elements[-1] if header.elements else None
    size = None
    if last is not None and not last.has_lists:
      size = _scalar_dtype(last, endian).itemsize
    raise _trailing(path, header, len(data) - offset, 'bytes', size)
  return out


def _parse_tokens(tokens, dtype: str, path, what):
  """ASCII tokens -> values of one PLY type (row i of ``what`` is token i)."""
  tokens = np.asarray(tokens, dtype=bytes)
  try:
    vals = tokens.astype(np.float64)
  except ValueError:
    i = 0
    for i, t in enumerate(tokens.tolist()):
      try:
        float(t)
      except ValueError:
        break
    raise PlyError(
      f'{path}: bad ASCII value {tokens[i].decode(errors="replace")!r} in '
      f'{what} (value {i}): not a number'
    ) from None
  if dtype.startswith('f'):
    with np.errstate(over='ignore'):
      out = vals.astype(dtype)
    over = np.flatnonzero(np.isinf(out) & np.isfinite(vals))
    if over.size:
      i = over[0]
      raise PlyError(
        f'{path}: ASCII value {tokens[i].decode()} in {what} (value {i}) is '
        f'out of range for the declared type {_WRITE_NAMES[dtype]} '
        f'(|v| <= {np.finfo(dtype).max:.4g}); declare it "double" or fix '
        'the value'
      )
    return out
  if np.any(vals != np.round(vals)):
    raise PlyError(
      f'{path}: non-integer ASCII value in integer property {what}'
    )
  info = np.iinfo(dtype)
  if vals.size and (vals.min() < info.min or vals.max() > info.max):
    raise PlyError(f'{path}: ASCII value out of range for {what} ({dtype})')
  return vals.astype(dtype)


def _read_ascii(data: bytes, header: PlyHeader, path) -> dict:
  """One line per row (PLY 1.0): a row with a value too many or too few is
  an error, not a shift of every later value."""
  lines = data[header.size :].splitlines()
  first = data[: header.size].count(b'\n') + 1  # file line of lines[0]
  rows = [(first + i, t) for i, line in enumerate(lines) if (t := line.split())]
  pos = 0
  out = {}

  def row_error(e, r, line, got, want):
    if pos + r == len(rows) - 1 and got < want:
      return PlyError(
        f'{path}: truncated ASCII PLY payload in element {e.name!r}: its '
        f'last row {r} (line {line}) has {got} of {want} values'
      )
    return PlyError(
      f'{path}: ASCII row {r} has {got} values, the header declares {want} '
      f'properties (element {e.name!r}, line {line}); each row is one line '
      'with one value per property: fix that line or the header'
    )

  for e in header.elements:
    # (Rows of an element without properties are empty lines.)
    count = e.count if e.properties else 0
    if pos + count > len(rows):
      raise PlyError(
        f'{path}: truncated ASCII PLY payload in element {e.name!r}: '
        f'expected {e.count} rows (lines), found {len(rows) - pos}'
      )
    block = rows[pos : pos + count]
    if not e.has_lists:
      n = len(e.properties)
      for r, (line, t) in enumerate(block):
        if len(t) != n:
          raise row_error(e, r, line, len(t), n)
      mat = np.asarray([t for _, t in block], dtype=bytes).reshape(count, n)
      pos += count
      out[e.name] = {
        p.name: _parse_tokens(mat[:, i], p.dtype, path, f'{e.name}.{p.name}')
        for i, p in enumerate(e.properties)
      }
      continue
    cols = {p.name: [] for p in e.properties}
    for r, (line, t) in enumerate(block):
      k = 0
      for p in e.properties:
        what = f'{e.name}.{p.name} (row {r}, line {line})'
        if k >= len(t):
          raise row_error(e, r, line, len(t), k + 1)
        if p.is_list:
          n = int(_parse_tokens([t[k]], p.count_dtype, path, what)[0])
          if n < 0 or k + 1 + n > len(t):
            raise PlyError(
              f'{path}: ASCII list {what} declares {n} items but the line '
              f'has {len(t) - k - 1} values left; fix that line'
            )
          cols[p.name].append(
            _parse_tokens(t[k + 1 : k + 1 + n], p.dtype, path, what)
          )
          k += 1 + n
        else:
          cols[p.name].append(_parse_tokens([t[k]], p.dtype, path, what)[0])
          k += 1
      if k != len(t):
        raise PlyError(
          f'{path}: ASCII row {r} of element {e.name!r} (line {line}) has '
          f'{len(t)} values, its properties take {k}; fix that line'
        )
    pos += e.count
    out[e.name] = {
      p.name: (
        cols[p.name]
        if p.is_list
        else np.asarray(cols[p.name], np.dtype(p.dtype))
      )
      for p in e.properties
    }
  if pos < len(rows):
    line, t = rows[pos]
    raise _trailing(
      path, header, len(rows) - pos,
      f'line(s) of data (from line {line}: {b" ".join(t[:6]).decode()!r})',
    )
  return out


def read_ply(
  path: PathLike,
) -> tuple[PlyHeader, dict[str, dict[str, np.ndarray]]]:
  """Reads every element of a PLY file into NumPy arrays.

  Args:
    path: file path.

  Returns:
    ``(header, elements)`` where ``elements[element][property]`` is a
    native-endian ``(count,)`` array for a scalar property (its PLY type) or
    a list of arrays for a list property.

  Raises:
    PlyError: not a PLY file, a directory, malformed header, truncated
      payload, data that no declared element accounts for, or an ASCII row
      whose value count does not match the header.
    FileNotFoundError: no such file (named).
  """
  header, elements, _ = _read(path)
  return header, elements


def _read(path):
  """(header, elements, {element: (count, P) matrix if homogeneous})."""
  data = _read_bytes(path)
  header = _parse_header(data, path)
  matrices = {}
  if header.format == 'ascii':
    return header, _read_ascii(data, header, path), matrices
  return header, _read_binary(data, header, path, matrices), matrices


# ----------------------------------------------------------------------------
# Writer.


def _ply_type_name(dtype: np.dtype, what: str) -> str:
  code = np.dtype(dtype).str[1:]
  if np.dtype(dtype) == np.bool_:
    code = 'u1'
  if code == 'i8' or code == 'u8':
    code = code[0] + '4'
  if code not in _WRITE_NAMES:
    raise PlyError(
      f'{what}: dtype {np.dtype(dtype)} has no PLY type; use one of '
      'int8/uint8/int16/uint16/int32/uint32/float32/float64'
    )
  return _WRITE_NAMES[code]


def _format_ascii(col: np.ndarray) -> list[str]:
  if col.dtype.kind == 'f':
    fmt = '%.9g' if col.dtype.itemsize <= 4 else '%.17g'
    return [fmt % v for v in col.tolist()]
  return [str(v) for v in col.tolist()]


def _header_start(format, comments):  # noqa: A002
  return ['ply', f'format {format} 1.0'] + [f'comment {c}' for c in comments]


def write_ply(
  path: PathLike,
  elements: Mapping[str, Mapping[str, np.ndarray]],
  *,
  format: str = 'binary_little_endian',  # noqa: A002
  comments: tuple[str, ...] = (),
) -> None:
  """Writes scalar-property elements to a PLY file.

  Args:
    path: output path.
    elements: ``{element: {property: (count,) array}}`` in file order; each
      array's dtype picks the PLY type (int64/uint64 are narrowed to 32 bits
      after a range check, bool becomes uchar).
    format: ``'binary_little_endian'``, ``'binary_big_endian'`` or
      ``'ascii'``.
    comments: header comment lines.

  Raises:
    PlyError: unknown format, bad names, ragged columns, unsupported dtypes
      or a path that cannot be written (parent folders are created).
  """
  if format not in FORMATS:
    raise PlyError(f'{path}: unknown PLY format {format!r}; use {FORMATS}')
  lines = _header_start(format, comments)
  blocks = []
  for ename, props in elements.items():
    if not _NAME_RE.match(ename):
      raise PlyError(f'{path}: bad PLY element name {ename!r}')
    cols = {}
    count = None
    for pname, arr in props.items():
      what = f'{path}: property {ename}.{pname}'
      if not _NAME_RE.match(pname):
        raise PlyError(f'{what}: PLY names may not contain whitespace')
      a = np.asarray(arr)
      if a.ndim != 1:
        raise PlyError(f'{what} has shape {a.shape}; expected (count,)')
      if count is None:
        count = a.shape[0]
      elif a.shape[0] != count:
        raise PlyError(
          f'{what} has {a.shape[0]} rows but the element has {count}'
        )
      tname = _ply_type_name(a.dtype, what)
      code = PLY_TYPES[tname]
      if a.dtype.kind in 'iub' and a.dtype.itemsize == 8:
        info = np.iinfo(code)
        if a.size and (a.min() < info.min or a.max() > info.max):
          raise PlyError(f'{what}: values out of range for {tname}')
      cols[pname] = a.astype(code)
      lines.append(f'property {tname} {pname}')
    count = 0 if count is None else count
    lines.insert(len(lines) - len(cols), f'element {ename} {count}')
    blocks.append((count, cols))
  lines.append('end_header')
  head = ('\n'.join(lines) + '\n').encode('ascii')
  with open_output(path) as f:
    f.write(head)
    for count, cols in blocks:
      if not cols:
        continue
      if format == 'ascii':
        strs = [_format_ascii(c) for c in cols.values()]
        f.write(''.join(' '.join(r) + '\n' for r in zip(*strs)).encode())
        continue
      endian = _ENDIAN[format]
      codes = {c.dtype.str[1:] for c in cols.values()}
      if len(codes) == 1:
        # Homogeneous rows (the INRIA case): one (count, P) matrix.
        mat = np.stack(list(cols.values()), axis=1)
        f.write(mat.astype(endian + codes.pop(), copy=False).tobytes())
        continue
      dt = np.dtype([(k, endian + c.dtype.str[1:]) for k, c in cols.items()])
      rows = np.empty(count, dt)
      for k, c in cols.items():
        rows[k] = c
      f.write(rows.tobytes())
