"""Minimal PLY vertex reader (ascii and binary little/big endian): the x, y, z of a point cloud."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from dualnerf.io.errors import InputError

_TYPES = {"char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
          "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
          "float": "f4", "float32": "f4", "double": "f8", "float64": "f8"}


def read_ply_points(path: Path) -> np.ndarray:
    data = Path(path).read_bytes()
    end = data.find(b"end_header")
    if not data.startswith(b"ply") or end < 0:
        raise InputError(f"{path} is not a PLY file (no 'ply' magic or end_header).")
    header = data[:end].decode("ascii", "replace").splitlines()
    body_start = data.index(b"\n", end) + 1
    fmt, count, props, in_vertex = None, 0, [], False
    for line in header:
        parts = line.split()
        if not parts:
            continue
        if parts[0] == "format":
            fmt = parts[1]
        elif parts[0] == "element":
            in_vertex = parts[1] == "vertex"
            if in_vertex:
                count = int(parts[2])
            elif count == 0:
                raise InputError(f"{path}: only PLY files whose first element is 'vertex' are supported.")
        elif parts[0] == "property" and in_vertex:
            if parts[1] == "list":
                raise InputError(f"{path}: list properties on vertices are not supported.")
            props.append((parts[2], _TYPES[parts[1]]))
    names = [p[0] for p in props]
    if not {"x", "y", "z"} <= set(names):
        raise InputError(f"{path}: vertices need x, y and z properties.")
    if fmt == "ascii":
        rows = data[body_start:].decode("ascii").split("\n")[:count]
        table = np.array([[float(v) for v in r.split()[:len(props)]] for r in rows])
        return table[:, [names.index(k) for k in "xyz"]].astype(np.float64)
    order = {"binary_little_endian": "<", "binary_big_endian": ">"}.get(fmt)
    if order is None:
        raise InputError(f"{path}: unknown PLY format '{fmt}'.")
    dtype = np.dtype([(n, order + t) for n, t in props])
    table = np.frombuffer(data, dtype=dtype, count=count, offset=body_start)
    return np.stack([table[k].astype(np.float64) for k in "xyz"], axis=1)
