"""PLY files with fixed-size properties: the one reader and writer of the ``vertex`` element.

Used by the Gaussian-splat interchange (``splats/ply.py``) and the point-cloud proxy
(``proxy/pointcloud.py``). Work is bounded by the file, not by its header: an element's
count is checked against ``limits.PLY_VERTICES`` and against the bytes the file really
holds before anything is read or allocated, and error messages quote at most a short
excerpt of a bad header line.
"""
from __future__ import annotations

import re
import sys
from pathlib import Path

import numpy as np

from lsd3d_usd.errors import InputError, excerpt
from lsd3d_usd.limits import PLY_HEADER_BYTES, PLY_VERTICES
from lsd3d_usd.scene import atomic_write_bytes

PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}
MAX_HEADER_BYTES = int(PLY_HEADER_BYTES.value)
_TEXT_BYTES = frozenset(b"0123456789+-.eEnaifNAIF \t\r\n")
_MAX_LINE = 4096


def _parse_header(f, path):
    """-> (format, [(element name, count, [(prop, numpy type | 'list')])]).
    The file is left positioned at the body."""
    first = f.readline(64)
    if first.rstrip(b"\r\n") != b"ply":
        raise InputError(f"{path}: not a PLY file (missing 'ply' magic)")
    fmt, elements, size = None, [], len(first)
    while True:
        line = f.readline(_MAX_LINE + 1)
        size += len(line)
        if size > MAX_HEADER_BYTES:
            PLY_HEADER_BYTES.check(size, f"{path}: PLY header (no end_header within the limit)")
        if not line:
            raise InputError(f"{path}: PLY header has no end_header")
        if len(line) > _MAX_LINE:
            raise InputError(f"{path}: PLY header line longer than {_MAX_LINE} bytes "
                             f"(starts {excerpt(line)})")
        try:
            words = line.decode("ascii").split()
        except UnicodeDecodeError:
            raise InputError(f"{path}: PLY header is not ASCII (line {excerpt(line)})") from None
        if not words or words[0] in ("comment", "obj_info"):
            continue
        key = words[0]
        if key == "end_header":
            break
        if key == "format":
            if len(words) != 3 or words[1] not in ("binary_little_endian", "binary_big_endian", "ascii"):
                raise InputError(f"{path}: unsupported PLY format line {excerpt(line.strip())}")
            fmt = words[1]
        elif key == "element":
            if len(words) != 3 or not re.fullmatch(r"\d{1,100}", words[2]):
                raise InputError(f"{path}: bad PLY element line {excerpt(line.strip())}")
            elements.append((words[1], int(words[2]), []))
        elif key == "property":
            if not elements:
                raise InputError(f"{path}: PLY property before any element")
            if len(words) >= 2 and words[1] == "list":
                elements[-1][2].append((words[-1], "list"))
                continue
            if len(words) != 3 or words[1] not in PLY_TYPES:
                raise InputError(f"{path}: bad PLY property line {excerpt(line.strip())}")
            elements[-1][2].append((words[2], PLY_TYPES[words[1]]))
        else:
            raise InputError(f"{path}: unknown PLY header keyword {excerpt(key)}")
    if fmt is None:
        raise InputError(f"{path}: PLY header has no format line")
    return fmt, elements


def read_ply_vertices(path, max_vertices: int | None = None) -> np.ndarray:
    """The ``vertex`` element of a PLY file as a numpy structured array.

    Elements before ``vertex`` must have fixed-size properties (they are skipped);
    anything after it is ignored. More than ``limits.PLY_VERTICES`` vertices (or
    ``max_vertices``), or a count the file's size cannot hold, raise InputError before
    the body is read."""
    path = Path(path)
    try:
        f = open(path, "rb")
    except OSError as e:
        raise InputError(f"{path}: cannot open: {e.strerror}") from None
    with f:
        fmt, elements = _parse_header(f, path)
        body_start = f.tell()
        f.seek(0, 2)
        body_bytes = f.tell() - body_start
        f.seek(body_start)
        endian = ">" if fmt == "binary_big_endian" else "<"
        if fmt != "ascii":
            # a binary header over a text body reads as garbage numbers: refuse it
            sample = f.read(256)
            f.seek(body_start)
            if len(sample) >= 32 and set(sample) <= _TEXT_BYTES and any(48 <= c <= 57 for c in sample):
                raise InputError(f"{path}: PLY header says {fmt} but the body is ASCII text "
                                 f"(starts {excerpt(sample[:40])}); fix the format line")
        names = [e[0] for e in elements]
        if "vertex" not in names:
            raise InputError(f"{path}: PLY has no 'vertex' element (elements: "
                             f"{excerpt(', '.join(names) or 'none')})")
        vcount = elements[names.index("vertex")][1]
        if not PLY_VERTICES.ok(vcount, max_vertices):
            PLY_VERTICES.check(vcount, f"{path}: PLY header", max_vertices)
        # every element must fit the body, also those after 'vertex' that are never read: a
        # header claiming 1e9 faces is a file that lies (a list takes at least its length byte,
        # an ASCII value at least a digit and a separator)
        need = 0
        for name, count, props in elements:
            if fmt == "ascii":
                need += count * 2 * len(props)
                have = body_bytes + 1
            else:
                need += count * sum(1 if t == "list" else np.dtype(t).itemsize for _, t in props)
                have = body_bytes
            if need > have:
                raise InputError(f"{path}: PLY body truncated in element {excerpt(name)} (header "
                                 f"claims {count} records; the elements up to it need at least "
                                 f"{need} bytes, the body has {body_bytes})")
        if fmt == "ascii":
            text = None
            offset = 0
        for name, count, props in elements:
            if any(t == "list" for _, t in props):
                raise InputError(f"{path}: PLY element {excerpt(name)} has list properties; "
                                 "not a Gaussian-splat PLY or point cloud")
            seen = set()
            for p, _ in props:
                if p in seen:
                    raise InputError(f"{path}: PLY element {excerpt(name)} repeats property "
                                     f"{excerpt(p)}")
                seen.add(p)
            if name == "vertex" and not props:
                raise InputError(f"{path}: PLY element 'vertex' has no properties")
            dtype = np.dtype([(p, endian + t) for p, t in props])
            if fmt == "ascii":
                n_tok = count * len(props)
                # a value takes at least two bytes (digit + separator): check before reading
                if n_tok > (body_bytes + 1) // 2:
                    raise InputError(f"{path}: PLY body truncated in element {excerpt(name)} "
                                     f"(header claims {count} records of {len(props)} values; "
                                     f"the body has {body_bytes} bytes)")
                if text is None:
                    text = f.read().split()
                if offset + n_tok > len(text):
                    raise InputError(f"{path}: PLY body truncated in element {excerpt(name)} "
                                     f"({len(text) - offset} of {n_tok} values)")
                if name == "vertex":
                    try:
                        vals = np.array(text[offset:offset + n_tok], dtype=np.float64)
                    except ValueError:
                        raise InputError(f"{path}: PLY ascii body has non-numeric values") from None
                    vals = vals.reshape(count, len(props))
                    out = np.empty(count, dtype=dtype.newbyteorder("="))
                    with np.errstate(all="ignore"):   # out-of-range ints wrap; checked by callers
                        for i, (p, _) in enumerate(props):
                            out[p] = vals[:, i]
                    return out
                offset += n_tok
                continue
            nbytes = dtype.itemsize * count
            if nbytes > body_bytes - (f.tell() - body_start):
                raise InputError(f"{path}: PLY body truncated in element {excerpt(name)} "
                                 f"(header claims {count} records, {nbytes} bytes; "
                                 f"{body_bytes - (f.tell() - body_start)} bytes left)")
            data = f.read(nbytes)
            if len(data) != nbytes:
                raise InputError(f"{path}: PLY body truncated in element {excerpt(name)} "
                                 f"({len(data)} of {nbytes} bytes)")
            if name == "vertex":
                arr = np.frombuffer(data, dtype=dtype)
                return arr.astype(dtype.newbyteorder("=")) if endian != "<" or sys.byteorder != "little" else arr
    raise AssertionError("unreachable")


def write_ply_vertices(path, arr: np.ndarray, comments=()) -> Path:
    """Write a structured array as the binary little-endian ``vertex`` element, atomically."""

    inv = {v: k for k, v in PLY_TYPES.items() if k in ("char", "uchar", "short", "ushort", "int",
                                                         "uint", "float", "double")}
    lines = ["ply", "format binary_little_endian 1.0"]
    lines += [f"comment {c}" for c in comments]
    lines.append(f"element vertex {len(arr)}")
    le = []
    for name in arr.dtype.names:
        t = arr.dtype[name]
        code = t.kind + str(t.itemsize)
        if code not in inv:
            raise ValueError(f"PLY cannot hold dtype {t} of property {name}")
        lines.append(f"property {inv[code]} {name}")
        le.append((name, "<" + code))
    lines.append("end_header")
    header = ("\n".join(lines) + "\n").encode("ascii")
    body = np.ascontiguousarray(arr.astype(np.dtype(le))).tobytes()
    return atomic_write_bytes(path, header + body)


def read_header_comments(path, prefix: bytes) -> list[str]:
    """The text after ``prefix`` of each header comment line starting with it (bounded
    like the header itself)."""
    out, size = [], 0
    with open(path, "rb") as f:
        while size <= MAX_HEADER_BYTES:
            line = f.readline(_MAX_LINE + 1)
            size += len(line)
            if not line or line.strip() == b"end_header":
                break
            if line.startswith(prefix):
                out.append(line[len(prefix):].decode("ascii", "replace").strip())
    return out
