"""Binary PLY point clouds / meshes and COLMAP's ``.ply.vis`` visibility files.

Point clouds are written exactly like COLMAP's ``WriteBinaryPlyPoints``: a
``binary_little_endian 1.0`` PLY whose vertex element has the properties
``float x y z``, ``float nx ny nz`` and ``uchar red green blue`` (in that order), so
COLMAP's ``poisson_mesher`` / ``delaunay_mesher``, open3d and MeshLab all read it.

The visibility file (COLMAP ``src/colmap/mvs/fusion.cc``, ``WritePointsVisibility``) is
little-endian: ``uint64 num_points``, then per point ``uint32 num_visible_images``
followed by that many ``uint32`` image indices. An image index is the position of the
image in the dense workspace's sparse model (``mvs::Model``: the order in which the
registered images are listed in ``sparse/images.bin``), not a COLMAP image id.
``delaunay_mesher`` uses it to cast visibility rays; ``poisson_mesher`` ignores it.

All writers are atomic (temporary file in the same folder, then rename).
"""

from __future__ import annotations

import logging
import os
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import MapFormatError, OutputError, ShapeError
from .files import atomic_write_bytes, write_temp_file

logger = logging.getLogger(__name__)

__all__ = [
    "PointCloud",
    "write_point_cloud",
    "read_point_cloud",
    "write_mesh",
    "read_mesh",
    "write_visibility",
    "read_visibility",
    "write_cloud_pair",
    "CloudPairStream",
    "commit_cloud_pair",
    "cloud_pair_is_complete",
    "vis_path_of",
]

_PLY_TYPES = {
    "char": "i1",
    "int8": "i1",
    "uchar": "u1",
    "uint8": "u1",
    "short": "i2",
    "int16": "i2",
    "ushort": "u2",
    "uint16": "u2",
    "int": "i4",
    "int32": "i4",
    "uint": "u4",
    "uint32": "u4",
    "float": "f4",
    "float32": "f4",
    "double": "f8",
    "float64": "f8",
}


@dataclass(frozen=True, eq=False)
class PointCloud:
    """A coloured, oriented point cloud.

    Attributes:
        xyz: ``[N, 3]`` float32 world coordinates.
        normals: ``[N, 3]`` float32 unit normals (zero where unknown).
        colors: ``[N, 3]`` uint8 RGB.
    """

    xyz: np.ndarray
    normals: np.ndarray
    colors: np.ndarray

    def __len__(self) -> int:
        return int(self.xyz.shape[0])


def _check_rows(name: str, array: np.ndarray | None, n: int, path: Path) -> None:
    if array is not None and (array.ndim != 2 or array.shape != (n, 3)):
        raise ShapeError(f"cannot write {str(path)!r}: {name} must be [{n}, 3], got shape {array.shape}")


_CLOUD_DTYPE = np.dtype(
    [("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("nx", "<f4"), ("ny", "<f4"), ("nz", "<f4"),
     ("red", "u1"), ("green", "u1"), ("blue", "u1")]
)


def _cloud_header(n: int) -> bytes:
    return (
        "ply\nformat binary_little_endian 1.0\n"
        f"element vertex {n}\n"
        "property float x\nproperty float y\nproperty float z\n"
        "property float nx\nproperty float ny\nproperty float nz\n"
        "property uchar red\nproperty uchar green\nproperty uchar blue\n"
        "end_header\n"
    ).encode("ascii")


def _point_records(
    path: Path, xyz: np.ndarray, normals: np.ndarray | None, colors: np.ndarray | None
) -> bytes:
    """The PLY body of the points (no header)."""
    xyz = np.asarray(xyz)
    if xyz.ndim != 2 or xyz.shape[1] != 3:
        raise ShapeError(f"cannot write {str(path)!r}: xyz must be [N, 3], got shape {xyz.shape}")
    n = xyz.shape[0]
    normals = None if normals is None else np.asarray(normals)
    colors = None if colors is None else np.asarray(colors)
    _check_rows("normals", normals, n, path)
    _check_rows("colors", colors, n, path)
    rec = np.zeros(n, dtype=_CLOUD_DTYPE)
    for i, k in enumerate("xyz"):
        rec[k] = xyz[:, i]
    if normals is not None:
        for i, k in enumerate(("nx", "ny", "nz")):
            rec[k] = normals[:, i]
    if colors is not None:
        for i, k in enumerate(("red", "green", "blue")):
            rec[k] = colors[:, i]
    return rec.tobytes()


def _point_cloud_bytes(
    path: Path, xyz: np.ndarray, normals: np.ndarray | None, colors: np.ndarray | None
) -> bytes:
    body = _point_records(path, xyz, normals, colors)
    return _cloud_header(len(body) // _CLOUD_DTYPE.itemsize) + body


def write_point_cloud(
    path: str | os.PathLike,
    xyz: np.ndarray,
    normals: np.ndarray | None = None,
    colors: np.ndarray | None = None,
) -> Path:
    """Write a binary little-endian PLY in COLMAP's fused-cloud layout, atomically.

    Args:
        xyz: ``[N, 3]`` positions (stored as float32).
        normals: ``[N, 3]`` normals or ``None`` (written as zeros).
        colors: ``[N, 3]`` uint8 RGB or ``None`` (written as zeros).
    """
    return atomic_write_bytes(path, _point_cloud_bytes(Path(path), xyz, normals, colors))


def _parse_header(data: bytes, path: Path) -> tuple[str, list[tuple[str, int, list[tuple]]], int]:
    """``(format, [(element, count, [(prop, dtype) or (prop, 'list', count_t, item_t)])], body_offset)``."""
    end = data.find(b"end_header")
    if not data.startswith(b"ply") or end < 0:
        raise MapFormatError(f"{str(path)!r} is not a PLY file (no 'ply' magic or 'end_header')")
    nl = data.find(b"\n", end)
    if nl < 0:
        raise MapFormatError(f"{str(path)!r}: truncated PLY header")
    fmt = ""
    elements: list[tuple[str, int, list[tuple]]] = []
    for line in data[:end].decode("ascii", errors="replace").splitlines():
        parts = line.split()
        if not parts or parts[0] in ("ply", "comment", "obj_info"):
            continue
        if parts[0] == "format":
            fmt = parts[1]
        elif parts[0] == "element":
            elements.append((parts[1], int(parts[2]), []))
        elif parts[0] == "property":
            if not elements:
                raise MapFormatError(f"{str(path)!r}: PLY property before any element: {line!r}")
            if parts[1] == "list":
                elements[-1][2].append((parts[4], "list", _PLY_TYPES[parts[2]], _PLY_TYPES[parts[3]]))
            else:
                if parts[1] not in _PLY_TYPES:
                    raise MapFormatError(f"{str(path)!r}: unknown PLY property type {parts[1]!r}")
                elements[-1][2].append((parts[2], _PLY_TYPES[parts[1]]))
    return fmt, elements, nl + 1


def _read_elements(path: Path) -> dict[str, dict[str, np.ndarray]]:
    path = Path(path)
    if not path.is_file():
        raise MapFormatError(f"PLY file {str(path)!r} does not exist")
    data = path.read_bytes()
    fmt, elements, offset = _parse_header(data, path)
    out: dict[str, dict[str, np.ndarray]] = {}
    if fmt == "ascii":
        tokens = data[offset:].split()
        pos = 0
        for name, count, props in elements:
            cols: dict[str, list] = {p[0]: [] for p in props}
            for _ in range(count):
                for p in props:
                    if p[1] == "list":
                        k = int(tokens[pos])
                        cols[p[0]].append(np.array(tokens[pos + 1 : pos + 1 + k], dtype=p[3]))
                        pos += 1 + k
                    else:
                        cols[p[0]].append(tokens[pos])
                        pos += 1
            out[name] = {
                k: (v if props[i][1] == "list" else np.array(v, dtype=props[i][1]))
                for i, (k, v) in enumerate(cols.items())
            }
        return out
    if fmt not in ("binary_little_endian", "binary_big_endian"):
        raise MapFormatError(f"{str(path)!r}: unsupported PLY format {fmt!r}")
    order = "<" if fmt == "binary_little_endian" else ">"
    for name, count, props in elements:
        if all(p[1] != "list" for p in props):
            dt = np.dtype([(p[0], order + p[1]) for p in props])
            need = dt.itemsize * count
            if offset + need > len(data):
                raise MapFormatError(f"{str(path)!r}: truncated PLY body in element {name!r}")
            rec = np.frombuffer(data, dtype=dt, count=count, offset=offset)
            offset += need
            out[name] = {p[0]: rec[p[0]].astype(p[1]) for p in props}
            continue
        # Lists (faces): fast path for a single list property with a constant length.
        if len(props) == 1 and count > 0:
            _, _, ct, it = props[0]
            k = int(np.frombuffer(data, dtype=order + ct, count=1, offset=offset)[0])
            dt = np.dtype([("n", order + ct), ("v", order + it, (k,))])
            if offset + dt.itemsize * count <= len(data):
                rec = np.frombuffer(data, dtype=dt, count=count, offset=offset)
                if np.all(rec["n"] == k):
                    out[name] = {props[0][0]: rec["v"].astype(it)}
                    offset += dt.itemsize * count
                    continue
        cols = {p[0]: [] for p in props}
        for _ in range(count):
            for p in props:
                if p[1] == "list":
                    k = int(np.frombuffer(data, dtype=order + p[2], count=1, offset=offset)[0])
                    offset += np.dtype(p[2]).itemsize
                    cols[p[0]].append(np.frombuffer(data, dtype=order + p[3], count=k, offset=offset))
                    offset += k * np.dtype(p[3]).itemsize
                else:
                    cols[p[0]].append(np.frombuffer(data, dtype=order + p[1], count=1, offset=offset)[0])
                    offset += np.dtype(p[1]).itemsize
        out[name] = cols
    return out


def read_point_cloud(path: str | os.PathLike) -> PointCloud:
    """Read a PLY point cloud (binary or ASCII); missing normals/colours come back as zeros."""
    path = Path(path)
    vertex = _read_elements(path).get("vertex")
    if vertex is None or not all(k in vertex for k in "xyz"):
        raise MapFormatError(f"{str(path)!r} has no vertex element with x, y, z")
    n = len(vertex["x"])
    xyz = np.stack([vertex[k] for k in "xyz"], axis=1).astype(np.float32)
    normals = (
        np.stack([vertex[k] for k in ("nx", "ny", "nz")], axis=1).astype(np.float32)
        if all(k in vertex for k in ("nx", "ny", "nz"))
        else np.zeros((n, 3), np.float32)
    )
    colors = (
        np.stack([vertex[k] for k in ("red", "green", "blue")], axis=1).astype(np.uint8)
        if all(k in vertex for k in ("red", "green", "blue"))
        else np.zeros((n, 3), np.uint8)
    )
    return PointCloud(xyz=xyz, normals=normals, colors=colors)


def write_mesh(
    path: str | os.PathLike,
    vertices: np.ndarray,
    faces: np.ndarray,
    normals: np.ndarray | None = None,
    colors: np.ndarray | None = None,
) -> Path:
    """Write a triangle mesh as binary little-endian PLY, atomically.

    Args:
        vertices: ``[V, 3]`` positions (float32).
        faces: ``[F, 3]`` vertex indices (int32).
        normals: optional ``[V, 3]`` vertex normals.
        colors: optional ``[V, 3]`` uint8 vertex colours.
    """
    path = Path(path)
    vertices = np.asarray(vertices)
    faces = np.asarray(faces)
    if vertices.ndim != 2 or vertices.shape[1] != 3:
        raise ShapeError(f"cannot write {str(path)!r}: vertices must be [V, 3], got shape {vertices.shape}")
    if faces.ndim != 2 or faces.shape[1] != 3:
        raise ShapeError(f"cannot write {str(path)!r}: faces must be [F, 3], got shape {faces.shape}")
    nv = vertices.shape[0]
    if faces.size and (faces.min() < 0 or faces.max() >= nv):
        raise ShapeError(f"cannot write {str(path)!r}: face indices out of range [0, {nv})")
    normals = None if normals is None else np.asarray(normals)
    colors = None if colors is None else np.asarray(colors)
    _check_rows("normals", normals, nv, path)
    _check_rows("colors", colors, nv, path)
    fields = [("x", "<f4"), ("y", "<f4"), ("z", "<f4")]
    props = ["property float x", "property float y", "property float z"]
    if normals is not None:
        fields += [("nx", "<f4"), ("ny", "<f4"), ("nz", "<f4")]
        props += ["property float nx", "property float ny", "property float nz"]
    if colors is not None:
        fields += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
        props += ["property uchar red", "property uchar green", "property uchar blue"]
    rec = np.zeros(nv, dtype=np.dtype(fields))
    for i, k in enumerate("xyz"):
        rec[k] = vertices[:, i]
    if normals is not None:
        for i, k in enumerate(("nx", "ny", "nz")):
            rec[k] = normals[:, i]
    if colors is not None:
        for i, k in enumerate(("red", "green", "blue")):
            rec[k] = colors[:, i]
    frec = np.zeros(faces.shape[0], dtype=np.dtype([("n", "u1"), ("v", "<i4", (3,))]))
    frec["n"] = 3
    frec["v"] = faces
    header = (
        "\n".join(
            [
                "ply",
                "format binary_little_endian 1.0",
                f"element vertex {nv}",
                *props,
                f"element face {faces.shape[0]}",
                "property list uchar int vertex_indices",
                "end_header",
            ]
        )
        + "\n"
    )
    return atomic_write_bytes(path, header.encode("ascii") + rec.tobytes() + frec.tobytes())


def read_mesh(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray]:
    """Read a triangle mesh PLY: ``(vertices [V, 3] float64, faces [F, 3] int64)``."""
    path = Path(path)
    el = _read_elements(path)
    vertex = el.get("vertex")
    if vertex is None:
        raise MapFormatError(f"{str(path)!r} has no vertex element")
    vertices = np.stack([np.asarray(vertex[k], dtype=np.float64) for k in "xyz"], axis=1)
    face = el.get("face", {})
    key = next((k for k in face if re.match(r"vertex_ind(ices|ex)", k)), None)
    if key is None:
        return vertices, np.zeros((0, 3), np.int64)
    f = face[key]
    faces = (
        np.asarray(f, dtype=np.int64)
        if not isinstance(f, list)
        else np.array([np.asarray(x, dtype=np.int64) for x in f if len(x) == 3]).reshape(-1, 3)
    )
    return vertices, faces


def write_visibility(path: str | os.PathLike, offsets: np.ndarray, image_indices: np.ndarray) -> Path:
    """Write a COLMAP ``.ply.vis`` file from CSR visibility, atomically.

    Args:
        offsets: ``[N + 1]`` int; point ``i`` is seen by ``image_indices[offsets[i]:offsets[i + 1]]``.
        image_indices: ``[T]`` image indices into the workspace's sparse model order.
    """
    return atomic_write_bytes(path, _visibility_bytes(Path(path), offsets, image_indices))


def _visibility_bytes(path: Path, offsets: np.ndarray, image_indices: np.ndarray) -> bytes:
    body = _visibility_body(path, offsets, image_indices)
    return np.array([len(np.asarray(offsets)) - 1], dtype="<u8").tobytes() + body


def _visibility_body(path: Path, offsets: np.ndarray, image_indices: np.ndarray) -> bytes:
    """The ``.vis`` body of the points (no leading point count)."""
    offsets = np.asarray(offsets, dtype=np.int64)
    image_indices = np.asarray(image_indices, dtype=np.int64)
    if offsets.ndim != 1 or offsets.size < 1 or offsets[0] != 0 or offsets[-1] != image_indices.size:
        raise ShapeError(f"cannot write {str(path)!r}: offsets must be [N + 1] from 0 to len(image_indices)")
    counts = np.diff(offsets)
    if (counts < 0).any() or (image_indices < 0).any() or (image_indices > np.iinfo(np.uint32).max).any():
        raise ShapeError(f"cannot write {str(path)!r}: negative counts or image indices out of uint32 range")
    n = counts.size
    body = np.empty(n + image_indices.size, dtype="<u4")
    count_pos = offsets[:-1] + np.arange(n)
    body[count_pos] = counts
    mask = np.ones(body.size, dtype=bool)
    mask[count_pos] = False
    body[mask] = image_indices
    return body.tobytes()


def vis_path_of(path: str | os.PathLike) -> Path:
    """``PATH.vis``: the visibility file COLMAP keeps beside a fused ``PATH``."""
    return Path(str(path) + ".vis")


def commit_cloud_pair(tmp_ply: Path, tmp_vis: Path, path: str | os.PathLike) -> Path:
    """Rename finished temporary ``PLY`` + ``.vis`` files into ``path`` and ``path.vis``.

    Two renames cannot be atomic together, so the order makes a mismatched pair impossible: the old
    ``path`` is removed first, then the new ``.vis`` and last the new ``path`` are renamed into place.
    An interruption leaves at worst a ``.vis`` without its cloud (no cloud: not a result), never a
    cloud beside another cloud's ``.vis``. The temporaries are removed on failure.
    """
    path = Path(path)
    vis = vis_path_of(path)
    try:
        path.unlink(missing_ok=True)
        os.replace(tmp_vis, vis)
        os.replace(tmp_ply, path)
    except OSError as exc:
        raise OutputError(f"cannot write {str(path)!r}: {exc.strerror or exc}") from None
    finally:
        tmp_ply.unlink(missing_ok=True)
        tmp_vis.unlink(missing_ok=True)
    return path


def write_cloud_pair(
    path: str | os.PathLike,
    xyz: np.ndarray,
    normals: np.ndarray | None,
    colors: np.ndarray | None,
    offsets: np.ndarray,
    image_indices: np.ndarray,
) -> tuple[Path, Path]:
    """Write a fused cloud and its ``.vis`` (see :func:`write_point_cloud`, :func:`write_visibility`)
    so that they become visible together or not at all (:func:`commit_cloud_pair`)."""
    path = Path(path)
    vis = vis_path_of(path)
    ply_data = _point_cloud_bytes(path, xyz, normals, colors)
    vis_data = _visibility_bytes(vis, offsets, image_indices)
    if len(np.asarray(offsets)) - 1 != np.asarray(xyz).shape[0]:
        raise ShapeError(f"cannot write {str(path)!r}: {np.asarray(xyz).shape[0]} points but visibility "
                         f"for {len(np.asarray(offsets)) - 1}")
    tmp_ply = write_temp_file(path, ply_data)
    try:
        tmp_vis = write_temp_file(vis, vis_data)
    except BaseException:
        tmp_ply.unlink(missing_ok=True)
        raise
    return commit_cloud_pair(tmp_ply, tmp_vis, path), vis


class CloudPairStream:
    """A fused cloud and its ``.vis`` written point chunk by point chunk, in memory one chunk at a time.

    :meth:`append` adds the chunk's PLY records to a temporary body file beside ``path`` and its
    visibility to a temporary ``.vis`` beside ``path.vis`` (8 bytes left for the point count);
    :meth:`commit` writes the PLY header (it holds the count, so it comes last) and the body into
    a third temporary file, fills in the ``.vis`` count and renames both into place
    (:func:`commit_cloud_pair`: together or not at all). The bytes equal :func:`write_cloud_pair` of
    all chunks at once. :meth:`discard` (also on leaving a ``with`` block without a commit) removes
    the temporaries; a killed run leaves them to :func:`colmap_pvs.io.cleanup.remove_orphan_temps`.
    Nothing is created before the first :meth:`append`.
    """

    _COPY_CHUNK = 16 << 20

    def __init__(self, path: str | os.PathLike) -> None:
        self.path = Path(path)
        self.num_points = 0
        self._body: tuple[Path, object] | None = None
        self._vis: tuple[Path, object] | None = None

    def __len__(self) -> int:
        return self.num_points

    def __enter__(self) -> CloudPairStream:
        return self

    def __exit__(self, *exc: object) -> None:
        self.discard()

    def _open(self) -> None:
        body = write_temp_file(self.path, b"")
        try:
            vis = write_temp_file(vis_path_of(self.path), b"\0" * 8)
        except BaseException:
            body.unlink(missing_ok=True)
            raise
        self._body = (body, open(body, "r+b"))
        self._body[1].seek(0, os.SEEK_END)  # type: ignore[attr-defined]
        self._vis = (vis, open(vis, "r+b"))
        self._vis[1].seek(0, os.SEEK_END)  # type: ignore[attr-defined]

    def append(
        self,
        xyz: np.ndarray,
        normals: np.ndarray | None,
        colors: np.ndarray | None,
        offsets: np.ndarray,
        image_indices: np.ndarray,
    ) -> None:
        """Add ``[k, 3]`` points and their visibility (CSR ``offsets [k + 1]``, ``image_indices``)."""
        records = _point_records(self.path, xyz, normals, colors)
        visibility = _visibility_body(vis_path_of(self.path), offsets, image_indices)
        k = len(records) // _CLOUD_DTYPE.itemsize
        if len(np.asarray(offsets)) - 1 != k:
            raise ShapeError(f"cannot write {str(self.path)!r}: {k} points but visibility for "
                             f"{len(np.asarray(offsets)) - 1}")
        if self._body is None:
            self._open()
        try:
            self._body[1].write(records)  # type: ignore[index, attr-defined]
            self._vis[1].write(visibility)  # type: ignore[index, attr-defined]
            self._body[1].flush()  # type: ignore[index, attr-defined]
            self._vis[1].flush()  # type: ignore[index, attr-defined]
        except OSError as exc:
            self.discard()
            raise OutputError(f"cannot write {str(self.path)!r}: {exc.strerror or exc}") from None
        self.num_points += k

    def commit(self) -> tuple[Path, Path]:
        """The PLY and its ``.vis`` in place, together or not at all."""
        if self._body is None or self._vis is None:
            raise ShapeError(f"cannot write {str(self.path)!r}: no points were added")
        body_path, body = self._body
        vis_path, vis = self._vis
        ply: Path | None = None
        try:
            vis.seek(0)  # type: ignore[attr-defined]
            vis.write(np.array([self.num_points], dtype="<u8").tobytes())  # type: ignore[attr-defined]
            vis.close()  # type: ignore[attr-defined]
            ply = write_temp_file(self.path, _cloud_header(self.num_points))
            body.seek(0)  # type: ignore[attr-defined]
            with open(ply, "ab") as out:
                while chunk := body.read(self._COPY_CHUNK):  # type: ignore[attr-defined]
                    out.write(chunk)
        except BaseException as exc:
            if ply is not None:
                ply.unlink(missing_ok=True)
            self.discard()
            if isinstance(exc, OSError):
                raise OutputError(f"cannot write {str(self.path)!r}: {exc.strerror or exc}") from None
            raise
        body.close()  # type: ignore[attr-defined]
        body_path.unlink(missing_ok=True)
        self._body = self._vis = None
        return commit_cloud_pair(ply, vis_path, self.path), vis_path_of(self.path)

    def discard(self) -> None:
        """Remove the temporaries (nothing to do after :meth:`commit`)."""
        for item in (self._body, self._vis):
            if item is not None:
                item[1].close()  # type: ignore[attr-defined]
                item[0].unlink(missing_ok=True)
        self._body = self._vis = None


def cloud_pair_is_complete(path: str | os.PathLike) -> bool:
    """Whether ``path`` and ``path.vis`` both exist and describe the same number of points."""
    path = Path(path)
    vis = vis_path_of(path)
    try:
        with open(vis, "rb") as f:
            head = f.read(8)
        if len(head) != 8:
            return False
        n_vis = int(np.frombuffer(head, dtype="<u8")[0])
        with open(path, "rb") as f:
            header = f.read(4096)
    except OSError:
        return False
    match = re.search(rb"element vertex (\d+)", header)
    return match is not None and int(match.group(1)) == n_vis and b"end_header" in header


def read_visibility(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray]:
    """Read a COLMAP ``.ply.vis`` file: ``(offsets [N + 1] int64, image_indices [T] int64)``."""
    path = Path(path)
    if not path.is_file():
        raise MapFormatError(f"visibility file {str(path)!r} does not exist")
    data = path.read_bytes()
    if len(data) < 8 or (len(data) - 8) % 4:
        raise MapFormatError(f"{str(path)!r} is not a COLMAP .vis file (size {len(data)} bytes)")
    n = int(np.frombuffer(data, dtype="<u8", count=1)[0])
    body = np.frombuffer(data, dtype="<u4", offset=8).astype(np.int64)
    offsets = np.zeros(n + 1, dtype=np.int64)
    keep = np.ones(body.size, dtype=bool)
    pos = 0
    for i in range(n):  # sequential by nature; fine for the sizes we read back in tests
        if pos >= body.size:
            raise MapFormatError(f"{str(path)!r}: truncated after {i} of {n} points")
        k = int(body[pos])
        keep[pos] = False
        pos += 1 + k
        offsets[i + 1] = offsets[i] + k
    if pos != body.size:
        raise MapFormatError(f"{str(path)!r}: {body.size - pos} trailing values (or truncated)")
    return offsets, body[keep]
