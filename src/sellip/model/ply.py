"""PLY meshes with per-vertex parameters (docs/design.md §4 ``final/model.ply``): a small binary PLY writer
and reader, and the model's vertex properties (x y z nx ny nz eta rho_d_rgb rho_s sigma_s rho_ss_rgb
sigma_ss, float32).
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

import numpy as np


class PlyError(ValueError):
    """A PLY file this reader does not handle; the message names the file, the place and what was expected."""

    def __init__(self, file: str, where: str | None, problem: str):
        self.file, self.where, self.problem = str(file), where, problem
        super().__init__(f"{self.file}: {where}: {problem}" if where else f"{self.file}: {problem}")


MODEL_VERTEX_PROPERTIES = ("x", "y", "z", "nx", "ny", "nz", "eta", "rho_d_r", "rho_d_g", "rho_d_b", "rho_s",
                           "sigma_s", "rho_ss_r", "rho_ss_g", "rho_ss_b", "sigma_ss")
"""Vertex properties of a model PLY (docs/design.md §4), all float32, in this order."""

_PLY_TYPES = {"char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
              "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
              "float": "f4", "float32": "f4", "double": "f8", "float64": "f8"}
_PLY_NAMES = {"i1": "char", "u1": "uchar", "i2": "short", "u2": "ushort", "i4": "int", "u4": "uint",
              "f4": "float", "f8": "double"}


def write_ply(path: str | Path, vertex: Mapping[str, np.ndarray], faces: np.ndarray | None = None) -> None:
    """Binary little-endian PLY: one vertex property per entry of ``vertex`` ((V,) arrays, their own dtype,
    in the mapping's order) and triangles ``faces`` (F, 3) as ``vertex_indices`` lists."""
    names = list(vertex)
    count = len(next(iter(vertex.values())))
    dtype = np.dtype([(name, np.asarray(vertex[name]).dtype.newbyteorder("<")) for name in names])
    table = np.empty(count, dtype)
    for name in names:
        table[name] = vertex[name]
    header = ["ply", "format binary_little_endian 1.0", "comment written by sellip", f"element vertex {count}"]
    header += [f"property {_PLY_NAMES[dtype[name].str[1:]]} {name}" for name in names]
    if faces is not None:
        header += [f"element face {len(faces)}", "property list uchar int vertex_indices"]
    header.append("end_header")
    with open(path, "wb") as f:
        f.write(("\n".join(header) + "\n").encode("ascii"))
        f.write(table.tobytes())
        if faces is not None:
            face_table = np.empty(len(faces), np.dtype([("n", "u1"), ("v", "<i4", (3,))]))
            face_table["n"] = 3
            face_table["v"] = faces
            f.write(face_table.tobytes())


def read_ply(path: str | Path) -> tuple[dict[str, np.ndarray], np.ndarray | None]:
    """Read a binary little-endian PLY with triangle faces: ({property: (V,) array}, faces (F, 3) int64 or None).

    Raises PlyError naming the file for formats this reader does not handle.
    """
    path = Path(path)
    with open(path, "rb") as f:
        if f.readline().strip() != b"ply":
            raise PlyError(str(path), None, "not a PLY file")
        elements: list[list] = []
        fmt = None
        while True:
            line = f.readline()
            if not line:
                raise PlyError(str(path), None, "PLY header has no end_header")
            words = line.decode("ascii", "replace").split()
            if not words or words[0] in ("comment", "obj_info"):
                continue
            if words[0] == "end_header":
                break
            if words[0] == "format":
                fmt = words[1]
            elif words[0] == "element":
                elements.append([words[1], int(words[2]), []])
            elif words[0] == "property":
                elements[-1][2].append(words[1:])
        if fmt != "binary_little_endian":
            raise PlyError(str(path), "format", f"expected binary_little_endian, got {fmt}")
        vertex, faces = {}, None
        for name, count, props in elements:
            if name == "face":
                if len(props) != 1 or props[0][0] != "list":
                    raise PlyError(str(path), "element face", "expected one vertex_indices list property")
                row = np.dtype([("n", _PLY_TYPES[props[0][1]]), ("v", "<" + _PLY_TYPES[props[0][2]], (3,))])
                table = np.frombuffer(f.read(row.itemsize * count), row, count)
                if count and np.any(table["n"] != 3):
                    raise PlyError(str(path), "element face", "expected triangles only")
                faces = table["v"].astype(np.int64)
            else:
                if any(p[0] == "list" for p in props):
                    raise PlyError(str(path), f"element {name}", "list properties are only read on faces")
                row = np.dtype([(p[1], "<" + _PLY_TYPES[p[0]]) for p in props])
                table = np.frombuffer(f.read(row.itemsize * count), row, count)
                if name == "vertex":
                    vertex = {p[1]: table[p[1]].copy() for p in props}
    return vertex, faces


def write_param_mesh(path: str | Path, mesh, extra: Mapping[str, np.ndarray] | None = None) -> None:
    """Write a :class:`sellip.model.render.ParamMesh` as a model PLY (MODEL_VERTEX_PROPERTIES, float32; plus an
    int32 ``material`` property when the mesh has region labels, and the (V,) arrays of ``extra``
    in their own dtype, e.g. ``confidence`` float32 and ``model`` uint8)."""
    p = mesh.params
    columns = [mesh.vertices, mesh.normals, np.asarray(p.eta)[:, None], p.rho_d, np.asarray(p.rho_s)[:, None],
               np.asarray(p.sigma_s)[:, None], p.rho_ss, np.asarray(p.sigma_ss)[:, None]]
    table = np.concatenate([np.asarray(c, np.float64).reshape(mesh.num_vertices, -1) for c in columns], axis=1)
    vertex = {name: table[:, k].astype(np.float32) for k, name in enumerate(MODEL_VERTEX_PROPERTIES)}
    if mesh.material is not None:
        vertex["material"] = np.asarray(mesh.material, np.int32)
    for name, values in (extra or {}).items():
        values = np.asarray(values)
        if values.shape != (mesh.num_vertices,):
            raise ValueError(f"{path}: extra property {name!r} has shape {values.shape}, "
                             f"expected ({mesh.num_vertices},)")
        vertex[name] = values
    write_ply(path, vertex, np.asarray(mesh.faces))


def read_param_mesh(path: str | Path):
    """Read a model PLY into a :class:`sellip.model.render.ParamMesh` (float64 arrays)."""
    from sellip.model.pbrdf import PBRDFParams
    from sellip.model.render import ParamMesh

    vertex, faces = read_ply(path)
    missing = [name for name in MODEL_VERTEX_PROPERTIES if name not in vertex]
    if missing:
        raise PlyError(str(path), "element vertex", f"missing properties {missing}; "
                                                        f"expected {list(MODEL_VERTEX_PROPERTIES)}")

    def stack(*names):
        return np.stack([vertex[n].astype(np.float64) for n in names], axis=-1)

    params = PBRDFParams(eta=vertex["eta"].astype(np.float64), rho_d=stack("rho_d_r", "rho_d_g", "rho_d_b"),
                         rho_s=vertex["rho_s"].astype(np.float64), sigma_s=vertex["sigma_s"].astype(np.float64),
                         rho_ss=stack("rho_ss_r", "rho_ss_g", "rho_ss_b"),
                         sigma_ss=vertex["sigma_ss"].astype(np.float64))
    return ParamMesh(vertices=stack("x", "y", "z"), faces=faces, normals=stack("nx", "ny", "nz"), params=params,
                     material=vertex["material"].astype(np.int64) if "material" in vertex else None)
