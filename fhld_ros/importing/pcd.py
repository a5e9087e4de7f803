"""PCD (Point Cloud Library) files: header, DATA ascii / binary / binary_compressed, LZF.

Format (PCL's PCD v0.7): a text header of VERSION, FIELDS, SIZE, TYPE, COUNT, WIDTH, HEIGHT,
VIEWPOINT, POINTS and DATA lines, then the points. `binary` stores them as packed little-endian
records; `binary_compressed` stores uint32 compressed size, uint32 uncompressed size and an
LZF stream that expands to the fields column by column (every point's first field, then every
point's second field, ...). Fields named `_` are padding and are dropped on reading.
"""
from __future__ import annotations

import io
import struct
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from fhld_ros.errors import ConfigError

INTENSITY_NAMES = ('intensity', 'reflectivity', 'i', 'I')  # first present wins
XYZI_DTYPE = np.dtype([('x', '<f4'), ('y', '<f4'), ('z', '<f4'), ('intensity', '<f4')])
XYZIR_DTYPE = np.dtype(XYZI_DTYPE.descr + [('ring', '<u2')])  # the Velodyne driver's ring
DATA_KINDS = ('ascii', 'binary', 'binary_compressed')
IDENTITY_VIEWPOINT = (0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0)  # tx ty tz qw qx qy qz
_SIZES = {'F': (4, 8), 'I': (1, 2, 4, 8), 'U': (1, 2, 4, 8)}
_KIND = {'F': 'f', 'I': 'i', 'U': 'u'}
_KEYS = ('VERSION', 'FIELDS', 'SIZE', 'TYPE', 'COUNT', 'WIDTH', 'HEIGHT', 'VIEWPOINT',
         'POINTS', 'DATA')
_MAX_HEADER_BYTES = 1 << 16  # a PCD header is a dozen short lines


class PcdError(ConfigError, ValueError):
    """A PCD file cannot be read; the message names the file and the problem."""


@dataclass
class PcdHeader:
    fields: list[str]
    sizes: list[int]
    types: list[str]
    counts: list[int]
    width: int
    height: int
    points: int
    data: str
    viewpoint: tuple[float, ...] = IDENTITY_VIEWPOINT
    version: str = ''

    def file_dtype(self) -> np.dtype:
        """Packed little-endian record of one point as stored, padding fields included."""
        formats = []
        for ftype, size, count in zip(self.types, self.sizes, self.counts):
            base = np.dtype(f'<{_KIND[ftype]}{size}')
            formats.append(base if count == 1 else (base, (count,)))
        return np.dtype({'names': self.storage_names(), 'formats': formats})

    def storage_names(self) -> list[str]:
        """Field names with each padding `_` made unique (numpy needs distinct names)."""
        return [f'_pad{k}' if name == '_' else name for k, name in enumerate(self.fields)]


@dataclass
class PcdCloud:
    """A PCD file's points (padding dropped, file field types and COUNTs kept)."""

    points: np.ndarray  # structured, shape (width * height,)
    width: int
    height: int
    viewpoint: tuple[float, ...] = field(default=IDENTITY_VIEWPOINT)


def lzf_decompress(data: bytes, out_size: int) -> bytes:
    """Expand an LZF stream (liblzf's format, as PCL writes it) to exactly out_size bytes.

    Each command is a literal run (control byte < 32: copy the next ctrl + 1 bytes) or a
    back-reference (length ctrl >> 5, 7 meaning "7 + next byte", plus 2; distance from the
    low 5 bits and the next byte, plus 1). The loop is over commands, not bytes; a reference
    that overlaps its own output repeats its period. Raises ValueError naming the problem.
    """
    src = bytes(data)
    end = len(src)
    out = bytearray()
    ip = 0
    while ip < end:
        ctrl = src[ip]
        ip += 1
        if ctrl < 32:
            length = ctrl + 1
            if ip + length > end:
                raise ValueError(f'LZF literal run of {length} bytes at input byte {ip - 1} '
                                 f'runs past the end of the {end}-byte stream')
            out += src[ip:ip + length]
            ip += length
        else:
            length = ctrl >> 5
            if length == 7:
                if ip >= end:
                    raise ValueError('LZF stream ends inside a back-reference')
                length += src[ip]
                ip += 1
            if ip >= end:
                raise ValueError('LZF stream ends inside a back-reference')
            distance = ((ctrl & 0x1F) << 8) + src[ip] + 1
            ip += 1
            length += 2
            start = len(out) - distance
            if start < 0:
                raise ValueError(f'LZF back-reference {distance} bytes back at output byte '
                                 f'{len(out)} points before the start')
            if distance >= length:
                out += out[start:start + length]
            else:  # overlapping copy: the last `distance` bytes repeat
                out += (out[start:] * -(-length // distance))[:length]
        if len(out) > out_size:
            raise ValueError(f'LZF stream expands past the {out_size} bytes the header states')
    if len(out) != out_size:
        raise ValueError(f'LZF stream expands to {len(out)} bytes, the header states {out_size}')
    return bytes(out)


def _ints(path: Path, key: str, values: list[str]) -> list[int]:
    try:
        return [int(v) for v in values]
    except ValueError:
        raise PcdError(f'{path}: bad PCD header: {key} must be integers, got '
                       f'{" ".join(values)!r}') from None


def _header_lines(raw: bytes, path: Path) -> tuple[dict[str, list[str]], int]:
    """Header key -> values up to and including DATA, and the offset of the first data byte."""
    entries: dict[str, list[str]] = {}
    pos = 0
    while 'DATA' not in entries:
        newline = raw.find(b'\n', pos, _MAX_HEADER_BYTES)
        if newline < 0:
            raise PcdError(f'{path}: bad PCD header: no DATA line in the first '
                           f'{min(len(raw), _MAX_HEADER_BYTES)} bytes')
        try:
            line = raw[pos:newline].decode('ascii').strip()
        except UnicodeDecodeError:
            raise PcdError(f'{path}: bad PCD header: line at byte {pos} is not text (no DATA '
                           'line before the data, or not a PCD file)') from None
        pos = newline + 1
        if not line or line.startswith('#'):
            continue
        key, *values = line.split()
        if key.upper() not in _KEYS:
            raise PcdError(f'{path}: bad PCD header: unknown line {line[:60]!r}')
        if key.upper() in entries:
            raise PcdError(f'{path}: bad PCD header: {key.upper()} given twice')
        entries[key.upper()] = values
    return entries, pos


def parse_header(raw: bytes, path: str | Path = '<pcd>') -> tuple[PcdHeader, int]:
    """The header of a PCD file's bytes and the offset where its data starts."""
    path = Path(path)
    entries, offset = _header_lines(raw, path)
    missing = [k for k in ('FIELDS', 'SIZE', 'TYPE', 'WIDTH', 'HEIGHT') if k not in entries]
    if missing:
        raise PcdError(f'{path}: bad PCD header: no {", ".join(missing)} line')
    fields = entries['FIELDS']
    sizes = _ints(path, 'SIZE', entries['SIZE'])
    types = [t.upper() for t in entries['TYPE']]
    counts = _ints(path, 'COUNT', entries.get('COUNT', ['1'] * len(fields)))
    for key, values in (('SIZE', sizes), ('TYPE', types), ('COUNT', counts)):
        if len(values) != len(fields):
            raise PcdError(f'{path}: bad PCD header: {len(fields)} FIELDS but {len(values)} '
                           f'{key} values')
    for name, ftype, size, count in zip(fields, types, sizes, counts):
        if size not in _SIZES.get(ftype, ()):
            raise PcdError(f"{path}: field '{name}' has TYPE {ftype} with SIZE {size}, an "
                           'unknown combination (F: 4/8, I and U: 1/2/4/8)')
        if count < 1:
            raise PcdError(f"{path}: bad PCD header: field '{name}' has COUNT {count}")
    named = [n for n in fields if n != '_']
    if len(set(named)) != len(named):
        raise PcdError(f'{path}: bad PCD header: duplicate FIELDS in {" ".join(fields)}')
    (width,), (height,) = (_ints(path, k, entries[k][:1] or ['?']) for k in ('WIDTH', 'HEIGHT'))
    points = _ints(path, 'POINTS', entries.get('POINTS', [str(width * height)])[:1])[0]
    if width < 0 or height < 1 or points != width * height:
        raise PcdError(f'{path}: bad PCD header: WIDTH {width} x HEIGHT {height} does not '
                       f'match POINTS {points}')
    try:
        viewpoint = tuple(float(v) for v in entries.get('VIEWPOINT', '0 0 0 1 0 0 0'.split()))
    except ValueError:
        viewpoint = ()
    if len(viewpoint) != 7:
        raise PcdError(f'{path}: bad PCD header: VIEWPOINT needs 7 numbers, got '
                       f'{" ".join(entries["VIEWPOINT"])!r}')
    data = ' '.join(entries['DATA']).lower()
    if data not in DATA_KINDS:
        raise PcdError(f'{path}: bad PCD header: DATA {data!r} is not one of '
                       f'{", ".join(DATA_KINDS)}')
    version = ' '.join(entries.get('VERSION', []))
    return PcdHeader(fields, sizes, types, counts, width, height, points, data, viewpoint,
                     version), offset


def _read_ascii(raw: bytes, offset: int, header: PcdHeader, path: Path) -> np.ndarray:
    dtype = header.file_dtype()
    if header.points == 0:
        return np.zeros(0, dtype)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter('ignore', UserWarning)  # "input contained no data"
            points = np.loadtxt(io.StringIO(raw[offset:].decode('ascii')), dtype=dtype,
                                ndmin=1, comments=None)
    except (ValueError, UnicodeDecodeError) as exc:
        raise PcdError(f'{path}: DATA ascii: {exc}') from None
    if len(points) != header.points:
        what = 'truncated' if len(points) < header.points else 'too long'
        raise PcdError(f'{path}: DATA ascii {what}: {len(points)} rows, POINTS says '
                       f'{header.points}')
    return points


def _read_binary(raw: bytes, offset: int, header: PcdHeader, path: Path) -> np.ndarray:
    dtype = header.file_dtype()
    need = header.points * dtype.itemsize
    if len(raw) - offset < need:
        raise PcdError(f'{path}: DATA binary truncated: {header.points} points of '
                       f'{dtype.itemsize} bytes need {need} bytes, the file has '
                       f'{len(raw) - offset}')
    return np.frombuffer(raw, dtype=dtype, count=header.points, offset=offset)


def _read_compressed(raw: bytes, offset: int, header: PcdHeader, path: Path) -> np.ndarray:
    dtype = header.file_dtype()
    need = header.points * dtype.itemsize
    if need == 0:  # PCL writes no size words for an empty cloud
        return np.zeros(0, dtype)
    if len(raw) - offset < 8:
        raise PcdError(f'{path}: DATA binary_compressed truncated: no size words')
    compressed, uncompressed = struct.unpack_from('<II', raw, offset)
    if uncompressed != need:
        raise PcdError(f'{path}: DATA binary_compressed states {uncompressed} bytes '
                       f'uncompressed, {header.points} points of {dtype.itemsize} bytes '
                       f'are {need}')
    start = offset + 8
    if len(raw) - start < compressed:
        raise PcdError(f'{path}: DATA binary_compressed truncated: {compressed} compressed '
                       f'bytes stated, the file has {len(raw) - start}')
    try:
        flat = lzf_decompress(raw[start:start + compressed], uncompressed)
    except ValueError as exc:
        raise PcdError(f'{path}: DATA binary_compressed: {exc}') from None
    points = np.empty(header.points, dtype=dtype)
    column = 0
    for name in dtype.names:  # one vectorised copy per field (column-wise storage)
        ftype = dtype.fields[name][0]
        nbytes = header.points * ftype.itemsize
        points[name] = np.frombuffer(flat, dtype=ftype.base, count=nbytes // ftype.base.itemsize,
                                     offset=column).reshape(points[name].shape)
        column += nbytes
    return points


def read_pcd(path: str | Path) -> PcdCloud:
    """A PCD file's points as a packed structured array (padding fields dropped)."""
    path = Path(path)
    try:
        raw = path.read_bytes()
    except OSError as exc:
        raise PcdError(f'cannot read {path}: {exc.strerror or exc}') from None
    header, offset = parse_header(raw, path)
    reader = {'ascii': _read_ascii, 'binary': _read_binary,
              'binary_compressed': _read_compressed}[header.data]
    stored = reader(raw, offset, header, path)
    names = [n for n, f in zip(header.storage_names(), header.fields) if f != '_']
    points = np.empty(len(stored), dtype=np.dtype([(n, stored.dtype.fields[n][0])
                                                   for n in names]))
    for name in names:
        points[name] = stored[name]
    return PcdCloud(points, header.width, header.height, header.viewpoint)


def intensity_field(names: tuple[str, ...] | list[str]) -> str | None:
    """The intensity-like field: intensity, else reflectivity, else i / I."""
    return next((n for n in INTENSITY_NAMES if n in names), None)


def to_xyzi(cloud: PcdCloud, path: str | Path = '<pcd>') -> np.ndarray:
    """float32 x, y, z, intensity (in the file's own units) of every point, layout kept."""
    names = cloud.points.dtype.names or ()
    found = ' '.join(names) or 'none'
    missing = [a for a in 'xyz' if a not in names]
    if missing:
        raise PcdError(f'{path}: no {"/".join(missing)} field (fields: {found})')
    source = intensity_field(names)
    if source is None:
        raise PcdError(f'{path}: no intensity-like field (intensity, reflectivity, i or I); '
                       f'fields: {found}')
    for name in (*'xyz', source):
        if cloud.points.dtype.fields[name][0].shape:
            raise PcdError(f"{path}: field '{name}' has COUNT > 1; it must be a single value")
    out = np.empty(len(cloud.points), dtype=XYZI_DTYPE)
    for target, name in zip(XYZI_DTYPE.names, (*'xyz', source)):
        out[target] = cloud.points[name]
    return out


def cloud_points(sweep: np.ndarray) -> np.ndarray:
    """A sweep's x y z intensity, packed (XYZI_DTYPE), and its laser index as a uint16 `ring`
    (XYZIR_DTYPE) when it has one: the fields a driver's PointCloud2 carries."""
    dtype = XYZIR_DTYPE if 'ring' in (sweep.dtype.names or ()) else XYZI_DTYPE
    out = np.empty(len(sweep), dtype=dtype)
    for name in dtype.names:
        out[name] = sweep[name]
    return out
