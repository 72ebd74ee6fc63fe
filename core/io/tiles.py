"""Collections of LAS/LAZ/COPC tiles: an index by header bounds, and streaming region reads.

A survey rarely comes as one file: ALS deliveries are tiles of 0.5-1 km, MLS runs are cut into
20-100 m tiles. :func:`open_collection` takes one file, several files, a folder or a glob
pattern and indexes every file by its header's bounding box (no point is read). A
:class:`TileCollection` then reads the points of any rectangular region (plus a halo) by
streaming the files that overlap it:

* LAS/LAZ: laspy's chunked reading (``chunk_points`` at a time), each chunk filtered by the
  region, so memory is bounded by one chunk plus the region's points, whatever the file size;
* COPC (``*.copc.laz``, or any LAZ whose first VLR is the COPC info record): laspy's
  ``CopcReader`` spatial query, which decompresses only the octree nodes that intersect the
  region, then the same exact filter.

Regions are half-open in x and y (``xmin <= x < xmax``), so a regular grid of regions
partitions the points; z is not filtered. The points of a region come out in one canonical
order (lexicographic in x, then y, then z; ties in the files' order), so the result of a
computation on a region does not depend on how the survey was cut into files.

Tile sets as delivered (issue #31): a file delivered twice (the same header box, point count,
scales and offsets, and the same point records by a content hash) is indexed once, the copies
listed in :attr:`TileCollection.duplicates`; tiles whose header boxes overlap make the
collection deduplicate what it reads (``dedupe``): a point found in several files (the same
GpsTime, where every file read has one, and the same coordinates as stored integers) counts
once, from the first file in the collection's order; points repeated within one file are kept
as the file has them (a one-file run reads them so). ``keep_duplicates=True`` reads every
file and every point as given, for data that really is distinct.

Every error names the tile at fault: a file that is missing (also one deleted after the
index was made), a header that cannot be read, a file whose points cannot be decompressed or
that holds fewer points than its header announces, a tile whose CRS differs from the others.
"""

from __future__ import annotations

import glob as _glob
import hashlib
import logging
import math
import os
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Dict, Iterable, Iterator, List, Optional, Sequence, Tuple, Union

import numpy as np

from ..errors import InvalidParameterError, SlipMapFileError
from . import las as _las

log = logging.getLogger(__name__)

__all__ = [
    "Region",
    "TileCollection",
    "TileFile",
    "expand_paths",
    "find_duplicates",
    "is_collection_spec",
    "open_collection",
    "region_grid",
]

PathLike = Union[str, "os.PathLike[str]"]

#: file name endings read as point-cloud tiles in a folder or glob
SUFFIXES = (".las", ".laz")
_GLOB_CHARS = set("*?[")
_DEFAULT_CHUNK = 1_000_000


@dataclass(frozen=True)
class Region:
    """A rectangle of map x/y, half-open: ``xmin <= x < xmax`` and ``ymin <= y < ymax``.

    ``ix, iy`` are the region's indices in the grid it belongs to (:func:`region_grid`).
    """

    xmin: float
    ymin: float
    xmax: float
    ymax: float
    ix: int = 0
    iy: int = 0

    def grown(self, halo_m: float) -> Region:
        """The region grown by ``halo_m`` metres on every side (same indices)."""
        h = float(halo_m)
        return Region(self.xmin - h, self.ymin - h, self.xmax + h, self.ymax + h, self.ix, self.iy)

    @property
    def name(self) -> str:
        return f"tile ({self.ix}, {self.iy})"

    def contains(self, xy: np.ndarray) -> np.ndarray:
        """Boolean mask ``(N,)`` of the points ``xy`` ``(N, >=2)`` inside the region."""
        x, y = xy[:, 0], xy[:, 1]
        return (x >= self.xmin) & (x < self.xmax) & (y >= self.ymin) & (y < self.ymax)

    def as_tuple(self) -> Tuple[float, float, float, float]:
        return (self.xmin, self.ymin, self.xmax, self.ymax)


@dataclass(frozen=True)
class TileFile:
    """One file of a collection, as its header describes it.

    Attributes
    ----------
    path : pathlib.Path
    n_points : int
    mins, maxs : tuple of 3 float
        Header bounding box (CRS units).
    crs_wkt : str or None
        The file's CRS as WKT (None without a usable CRS).
    copc : bool
        The file is a COPC (cloud-optimised point cloud): regions are read by spatial query.
    scales, offsets : tuple of 3 float
        The header's coordinate scales and offsets (coordinates are integer * scale + offset).
    point_format : int
        The LAS point format id.
    gps_time : bool
        The point format has GpsTime.
    """

    path: Path
    n_points: int
    mins: Tuple[float, float, float]
    maxs: Tuple[float, float, float]
    crs_wkt: Optional[str]
    copc: bool
    scales: Tuple[float, float, float] = (0.0, 0.0, 0.0)
    offsets: Tuple[float, float, float] = (0.0, 0.0, 0.0)
    point_format: int = -1
    gps_time: bool = False

    def overlaps(self, region: Region) -> bool:
        """The header box meets the half-open region (conservatively: a closed test)."""
        return not (
            self.maxs[0] < region.xmin
            or self.mins[0] >= region.xmax
            or self.maxs[1] < region.ymin
            or self.mins[1] >= region.ymax
        )


def is_collection_spec(value) -> bool:
    """True when ``value`` names several files: a list, a folder or a glob pattern."""
    if isinstance(value, (list, tuple)):
        return len(value) != 1 or is_collection_spec(value[0])
    text = os.fspath(value)
    return Path(text).is_dir() or bool(_GLOB_CHARS & set(Path(text).name))


def expand_paths(spec) -> List[Path]:
    """The files a spec names, in a stable order (sorted within a folder or a glob); no file
    is opened. Raises SlipMapFileError for a missing file, an empty folder or glob."""
    items = list(spec) if isinstance(spec, (list, tuple)) else [spec]
    if not items:
        raise InvalidParameterError("no point-cloud file given; give files, a folder or a glob")
    out: List[Path] = []
    for item in items:
        text = os.fspath(item)
        p = Path(text)
        if p.is_dir():
            found = sorted(
                q for q in p.iterdir() if q.is_file() and q.name.lower().endswith(SUFFIXES)
            )
            if not found:
                raise SlipMapFileError(f"folder {p} holds no .las or .laz file")
            out.extend(found)
        elif _GLOB_CHARS & set(p.name) or _GLOB_CHARS & set(str(p.parent)):
            found = sorted(Path(q) for q in _glob.glob(text, recursive=True) if Path(q).is_file())
            if not found:
                raise SlipMapFileError(f"no file matches {text!r}; check the pattern")
            out.extend(found)
        else:
            if not p.exists():
                raise SlipMapFileError(f"tile {p}: file not found")
            if not p.is_file():
                raise SlipMapFileError(f"tile {p}: not a file; expected a LAS/LAZ/COPC file")
            out.append(p)
    seen = set()
    unique = []
    for p in out:
        key = p.resolve()
        if key not in seen:
            seen.add(key)
            unique.append(p)
    return unique


def _is_copc(header) -> bool:
    try:
        return any(getattr(v, "user_id", "") == "copc" for v in header.vlrs)
    except Exception:  # pragma: no cover - defensive: odd VLRs
        return False


def _index_file(p: Path, *, parse_crs: bool = True) -> Tuple[TileFile, Optional[object]]:
    """Header of one tile; errors name the tile. ``parse_crs=False`` (the user gave the CRS)
    leaves the tile's own CRS unread: no warning about it."""
    try:
        with _las._open_reader(p) as reader:
            header = reader.header
            crs = _las.crs_from_las(header, source=p) if parse_crs else None
            tf = TileFile(
                path=p,
                n_points=int(header.point_count),
                mins=tuple(float(v) for v in header.mins),
                maxs=tuple(float(v) for v in header.maxs),
                crs_wkt=crs.to_wkt() if crs is not None else None,
                copc=_is_copc(header),
                scales=tuple(float(v) for v in header.scales),
                offsets=tuple(float(v) for v in header.offsets),
                point_format=int(header.point_format.id),
                gps_time="gps_time" in set(header.point_format.dimension_names),
            )
    except SlipMapFileError as exc:
        raise SlipMapFileError(f"tile {p}: {exc}") from exc
    if tf.n_points and not all(math.isfinite(v) for v in tf.mins + tf.maxs):
        raise SlipMapFileError(f"tile {p}: the header's bounding box is not finite (corrupt?)")
    return tf, crs


@dataclass(frozen=True)
class TileCollection:
    """Point-cloud tiles indexed by their header bounds (see :func:`open_collection`).

    Attributes
    ----------
    files : tuple of TileFile
    crs_wkt : str or None
        The collection's CRS (every tile's, or the one given to :func:`open_collection`).
    label : str
        How messages name the collection (e.g. "before epoch").
    dedupe : bool
        Header boxes of some files overlap: a region read drops the points that an earlier
        file of the region already gave (identity: GpsTime where every file read has it, and
        the coordinates as stored integers).
    duplicates : tuple of (Path, Path)
        Files left out as copies: ``(copy, the file kept)``.
    """

    files: Tuple[TileFile, ...]
    crs_wkt: Optional[str] = None
    label: str = ""
    dedupe: bool = False
    duplicates: Tuple[Tuple[Path, Path], ...] = ()
    _crs_cache: Dict[str, object] = field(default_factory=dict, compare=False, repr=False)

    def __len__(self) -> int:
        return len(self.files)

    @property
    def n_points(self) -> int:
        """Points announced by the headers."""
        return int(sum(f.n_points for f in self.files))

    @property
    def crs(self):
        """The CRS as a ``pyproj.CRS`` (None without one)."""
        if self.crs_wkt is None:
            return None
        if "crs" not in self._crs_cache:
            import pyproj

            self._crs_cache["crs"] = pyproj.CRS.from_wkt(self.crs_wkt)
        return self._crs_cache["crs"]

    @property
    def bounds(self) -> Tuple[np.ndarray, np.ndarray]:
        """``(mins, maxs)`` ``(3,)`` float64: the union of the non-empty tiles' header boxes."""
        full = [f for f in self.files if f.n_points > 0]
        if not full:
            return np.zeros(3), np.zeros(3)
        return (
            np.min([f.mins for f in full], axis=0).astype(np.float64),
            np.max([f.maxs for f in full], axis=0).astype(np.float64),
        )

    def paths(self) -> Tuple[Path, ...]:
        return tuple(f.path for f in self.files)

    def _boxes(self) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(mins, maxs, non-empty)`` of the files as arrays (cached)."""
        if "boxes" not in self._crs_cache:
            lo = np.array([f.mins for f in self.files], dtype=np.float64).reshape(-1, 3)
            hi = np.array([f.maxs for f in self.files], dtype=np.float64).reshape(-1, 3)
            full = np.array([f.n_points > 0 for f in self.files], dtype=bool)
            self._crs_cache["boxes"] = (lo, hi, full)
        return self._crs_cache["boxes"]

    def overlapping(self, region: Region) -> Tuple[TileFile, ...]:
        """The files whose header box meets ``region`` (closed test, as TileFile.overlaps)."""
        lo, hi, full = self._boxes()
        hit = full & ~(
            (hi[:, 0] < region.xmin)
            | (lo[:, 0] >= region.xmax)
            | (hi[:, 1] < region.ymin)
            | (lo[:, 1] >= region.ymax)
        )
        return tuple(self.files[i] for i in np.flatnonzero(hit))

    def restricted(self, region: Region, halo_m: float = 0.0) -> TileCollection:
        """The same collection with only the files that a read of ``region`` (and halo)
        opens: what a task needs to carry (not the index of the whole survey)."""
        box = region.grown(halo_m) if halo_m else region
        return TileCollection(
            files=self.overlapping(box), crs_wkt=self.crs_wkt, label=self.label,
            dedupe=self.dedupe,
        )  # fmt: skip

    def overlap_pairs(self) -> List[Tuple[TileFile, TileFile]]:
        """Pairs of non-empty files whose header boxes meet in x and y (closed test: a box
        touching another may share the points on the edge)."""
        lo, hi, full = self._boxes()
        idx = np.flatnonzero(full)
        if idx.size < 2:
            return []
        order = idx[np.argsort(lo[idx, 0], kind="stable")]
        xmin = lo[order, 0]
        pairs = []
        for k, i in enumerate(order):  # sweep in x: the files starting before i's box ends
            end = int(np.searchsorted(xmin, hi[i, 0], side="right"))
            for j in order[k + 1 : end]:
                if lo[j, 1] <= hi[i, 1] and lo[i, 1] <= hi[j, 1]:
                    a, b = sorted((int(i), int(j)))
                    pairs.append((self.files[a], self.files[b]))
        return pairs

    def read_region(
        self,
        region: Region,
        *,
        halo_m: float = 0.0,
        attributes: Sequence[str] = (),
        chunk_points: int = _DEFAULT_CHUNK,
    ) -> _las.PointCloud:
        """The points in ``region`` grown by ``halo_m``, streamed from the overlapping tiles.

        Parameters
        ----------
        region : Region
            Half-open in x and y; z is not filtered.
        halo_m : float
            Extra margin on every side, metres (CRS units).
        attributes : sequence of str
            Per-point attributes to read (PDAL names, as :func:`~.las.read_las`); a tile that
            lacks one gives zeros for its points (and a debug log line), so that tiles of
            different point formats can be read together.
        chunk_points : int
            Points decompressed at once per LAS/LAZ file (memory bound).

        Returns
        -------
        PointCloud
            ``xyz`` ``(N, 3)`` float64 in canonical order (x, then y, then z), the
            attributes, the collection's CRS; ``source`` is None (several files).

        Raises
        ------
        SlipMapFileError
            A tile missing, unreadable or truncated (the message names the tile).
        """
        box = region.grown(halo_m) if halo_m else region
        files = self.overlapping(box)
        dedupe = self.dedupe and len(files) > 1
        use_gps = dedupe and all(f.gps_time for f in files)
        wanted = tuple(attributes)
        if use_gps and "GpsTime" not in wanted:
            wanted += ("GpsTime",)
        xyz_parts: List[np.ndarray] = []
        file_parts: List[np.ndarray] = []
        attr_parts: Dict[str, List[np.ndarray]] = {a: [] for a in wanted}
        for i, tf in enumerate(files):
            for xyz, attrs in _read_file_region(tf, box, wanted, chunk_points):
                xyz_parts.append(xyz)
                file_parts.append(np.full(xyz.shape[0], i, dtype=np.int32))
                for a in wanted:
                    attr_parts[a].append(attrs[a])
        if xyz_parts:
            xyz = np.concatenate(xyz_parts)
        else:
            xyz = np.zeros((0, 3))
        if dedupe and xyz.shape[0] > 1:
            quantum = np.min([f.scales for f in files], axis=0)
            gps = np.concatenate(attr_parts["GpsTime"]) if use_gps else None
            keep = _first_copies(xyz, np.concatenate(file_parts), gps, quantum)
            if not keep.all():
                log.debug(
                    "%s%s: %d point(s) read from several overlapping tiles counted once",
                    f"{self.label}: " if self.label else "", region.name, keep.size - keep.sum(),
                )  # fmt: skip
                xyz = xyz[keep]
                for a in wanted:
                    attr_parts[a] = [np.concatenate(attr_parts[a])[keep]]
        order = np.lexsort((xyz[:, 2], xyz[:, 1], xyz[:, 0])) if xyz.shape[0] > 1 else None
        attrs_out = {}
        for a in attributes:
            arr = np.concatenate(attr_parts[a]) if attr_parts[a] else np.zeros(0)
            attrs_out[a] = arr[order] if order is not None else arr
        if order is not None:
            xyz = np.ascontiguousarray(xyz[order])
        return _las.PointCloud(xyz=xyz, attributes=attrs_out, crs=self.crs)


def _first_copies(
    xyz: np.ndarray, file_index: np.ndarray, gps: Optional[np.ndarray], quantum: np.ndarray
) -> np.ndarray:
    """Mask ``(N,)`` of the points to keep when overlapping files give the same point: of a
    group of identical points (coordinates as integers of ``quantum`` ``(3,)``, the finest
    scale of the files; GpsTime too when given), those of its first file (lowest
    ``file_index``); copies within that file are kept."""
    ijk = np.round(xyz / quantum).astype(np.int64)
    keys = [file_index, ijk[:, 2], ijk[:, 1], ijk[:, 0]]
    if gps is not None:
        keys.insert(1, np.asarray(gps, dtype=np.float64))
    order = np.lexsort(keys)
    ident = [k[order] for k in keys[1:]]
    start = np.ones(order.size, dtype=bool)
    same = np.ones(order.size - 1, dtype=bool)
    for k in ident:
        same &= k[1:] == k[:-1]
    start[1:] = ~same
    group = np.cumsum(start) - 1
    f_sorted = file_index[order]
    first = f_sorted[np.flatnonzero(start)][group]
    keep = np.empty(order.size, dtype=bool)
    keep[order] = f_sorted == first
    return keep


def _records_digest(tf: TileFile) -> str:
    """A content hash (BLAKE2b) of a file's point records, decompressed (the header's dates
    and software fields do not enter)."""
    h = hashlib.blake2b(digest_size=20)
    try:
        with _las._open_reader(tf.path) as reader:
            for points in reader.chunk_iterator(_DEFAULT_CHUNK):
                h.update(np.ascontiguousarray(points.array).tobytes())
    except SlipMapFileError as exc:
        raise SlipMapFileError(f"tile {tf.path}: {exc}") from exc
    except Exception as exc:
        raise SlipMapFileError(
            f"tile {tf.path}: the points cannot be read ({type(exc).__name__}: {exc}); "
            "the file is corrupt or truncated: replace it"
        ) from exc
    return h.hexdigest()


def find_duplicates(files: Sequence[TileFile]) -> List[Tuple[int, int]]:
    """Files that are copies of an earlier one: ``(copy index, original index)``.

    Candidates share the header's point count, bounding box, scales, offsets and point
    format (no point is read otherwise); among them, the same content hash of the point
    records makes a copy.
    """
    groups: Dict[tuple, List[int]] = {}
    for i, f in enumerate(files):
        if f.n_points > 0:
            key = (f.n_points, f.mins, f.maxs, f.scales, f.offsets, f.point_format)
            groups.setdefault(key, []).append(i)
    out = []
    for members in groups.values():
        if len(members) < 2:
            continue
        seen: Dict[str, int] = {}
        for i in members:
            digest = _records_digest(files[i])
            if digest in seen:
                out.append((i, seen[digest]))
            else:
                seen[digest] = i
    return sorted(out)


def _read_file_region(
    tf: TileFile, box: Region, attributes: Tuple[str, ...], chunk_points: int
) -> Iterator[Tuple[np.ndarray, Dict[str, np.ndarray]]]:
    """(xyz, attributes) of the points of one tile inside ``box``, chunk by chunk."""
    p = tf.path
    if not p.exists():
        raise SlipMapFileError(
            f"tile {p}: file not found (it was indexed, then removed or moved); "
            "restore it or index the collection again"
        )
    if tf.copc:
        yield from _read_copc_region(tf, box, attributes)
        return
    n_read = 0
    try:
        reader = _las._open_reader(p)
    except SlipMapFileError as exc:
        raise SlipMapFileError(f"tile {p}: {exc}") from exc
    with reader:
        names = _present(reader.header.point_format, attributes, p)
        it = reader.chunk_iterator(int(chunk_points))
        while True:
            try:
                points = next(it)
            except StopIteration:
                break
            except Exception as exc:
                raise SlipMapFileError(
                    f"tile {p}: the points cannot be read ({type(exc).__name__}: {exc}); "
                    "the file is corrupt or truncated: replace it"
                ) from exc
            n_read += len(points)
            out = _filter_points(points, box, names, attributes)
            if out is not None:
                yield out
    if n_read != tf.n_points:
        raise SlipMapFileError(
            f"tile {p}: the header announces {tf.n_points} points but {n_read} could be read "
            "(truncated file?): replace it"
        )


def _present(pf, attributes: Tuple[str, ...], p: Path) -> Tuple[str, ...]:
    available = set(_las.available_attributes(pf))
    missing = [a for a in attributes if a not in available]
    if missing:
        log.debug("tile %s has no %s; zeros are read", p, ", ".join(missing))
    return tuple(a for a in attributes if a in available)


def _filter_points(points, box: Region, names, attributes):
    x = np.asarray(points["x"], dtype=np.float64)
    y = np.asarray(points["y"], dtype=np.float64)
    keep = (x >= box.xmin) & (x < box.xmax) & (y >= box.ymin) & (y < box.ymax)
    k = int(np.count_nonzero(keep))
    if k == 0:
        return None
    sub = points[keep] if k < keep.size else points
    xyz = np.empty((k, 3))
    xyz[:, 0] = x[keep]
    xyz[:, 1] = y[keep]
    xyz[:, 2] = np.asarray(sub["z"], dtype=np.float64)
    attrs = {}
    for a in attributes:
        if a in names:
            attrs[a] = _las._extract(sub, a)
        else:
            attrs[a] = np.zeros(k, dtype=_default_dtype(a))
    return xyz, attrs


def _default_dtype(name: str):
    entry = _las._STANDARD.get(name)
    return entry[1] if entry is not None else np.float64


def _read_copc_region(tf: TileFile, box: Region, attributes: Tuple[str, ...]):
    """A COPC tile: decompress only the octree nodes meeting the box (laspy CopcReader)."""
    import laspy
    from laspy.copc import Bounds

    p = tf.path
    zlo, zhi = tf.mins[2] - 1.0, tf.maxs[2] + 1.0
    try:
        with laspy.CopcReader.open(p) as reader:
            names = _present(reader.header.point_format, attributes, p)
            bounds = Bounds(
                mins=np.array([box.xmin, box.ymin, zlo]), maxs=np.array([box.xmax, box.ymax, zhi])
            )
            points = reader.query(bounds=bounds)
    except SlipMapFileError:
        raise
    except Exception as exc:
        raise SlipMapFileError(
            f"tile {p}: the COPC file cannot be queried ({type(exc).__name__}: {exc}); "
            "the file is corrupt: replace it"
        ) from exc
    out = _filter_points(points, box, names, attributes)
    if out is not None:
        yield out


def open_collection(
    spec,
    *,
    crs=None,
    label: str = "",
    keep_duplicates: bool = False,
) -> TileCollection:
    """Index one file, several files, a folder or a glob of LAS/LAZ/COPC tiles.

    Parameters
    ----------
    spec : path-like, str or sequence of them
        A file; a folder (every ``*.las``/``*.laz`` in it, sorted by name); a glob pattern
        (``tiles/*.laz``, ``**`` allowed); or a list mixing these.
    crs : pyproj.CRS, str or None
        Replaces the tiles' CRS (nothing is reprojected), as the jobs' CRS option does.
    label : str
        How messages name the collection ("before epoch").
    keep_duplicates : bool
        Read every file and every point as given. By default a file that is a copy of an
        earlier one is left out (listed in ``duplicates``) and, where header boxes overlap,
        a point given by several files counts once (``dedupe``).

    Returns
    -------
    TileCollection

    Raises
    ------
    SlipMapFileError
        A file missing, unreadable, or with a CRS different from the first tile's (each
        message names the tile).
    """
    paths = expand_paths(spec)
    files = []
    first_crs = None
    first_path = None
    for p in paths:
        tf, tcrs = _index_file(p, parse_crs=crs is None)
        files.append(tf)
        if crs is None and tcrs is not None:
            if first_crs is None:
                first_crs, first_path = tcrs, p
            elif not _las.same_crs(first_crs, tcrs):
                what = f"{label}: " if label else ""
                raise SlipMapFileError(
                    f"{what}tile {p} is in {tcrs.name} but tile {first_path} is in "
                    f"{first_crs.name}; reproject the tiles to one CRS, or give the CRS option"
                )
    if crs is not None:
        from .crs import parse_crs

        wkt = parse_crs(crs).to_wkt()
    else:
        wkt = first_crs.to_wkt() if first_crs is not None else None
    coll = TileCollection(files=tuple(files), crs_wkt=wkt, label=label)
    if not keep_duplicates and len(files) > 1:
        dups = find_duplicates(files)
        drop = {i for i, _ in dups}
        kept = tuple(f for i, f in enumerate(files) if i not in drop)
        coll = TileCollection(
            files=kept, crs_wkt=wkt, label=label,
            duplicates=tuple((files[i].path, files[j].path) for i, j in dups),
        )  # fmt: skip
        if coll.overlap_pairs():
            coll = replace(coll, dedupe=True)
    log.info(
        "%s%d tile(s), %d points (headers)", f"{label}: " if label else "", len(files),
        coll.n_points,
    )  # fmt: skip
    return coll


def region_grid(
    bounds: Tuple[np.ndarray, np.ndarray],
    tile_size_m: float,
    *,
    origin_m: Optional[Sequence[float]] = None,
    collections: Iterable[TileCollection] = (),
    grow_low_m: float = 0.0,
) -> List[Region]:
    """Regions of a regular grid of ``tile_size_m`` squares covering ``bounds``.

    The grid is aligned to multiples of ``tile_size_m`` (or to ``origin_m``); regions that
    no file of ``collections`` overlaps are left out (when collections are given), the files'
    boxes grown towards low x and y by ``grow_low_m`` (a roughness cell belongs to the tile
    of its lower corner, which may lie before its points). Regions come in a fixed order
    (ix, then iy).
    """
    t = float(tile_size_m)
    if not (math.isfinite(t) and t > 0):
        raise InvalidParameterError(f"tile_size_m must be a positive number, got {tile_size_m!r}")
    lo, hi = (np.asarray(b, dtype=np.float64) for b in bounds)
    lo = lo - float(grow_low_m)
    o = np.zeros(2) if origin_m is None else np.asarray(origin_m, dtype=np.float64)[:2]
    i0 = np.floor((lo[:2] - o) / t).astype(np.int64)
    i1 = np.floor((hi[:2] - o) / t).astype(np.int64)
    n = int((i1[0] - i0[0] + 1) * (i1[1] - i0[1] + 1))
    if n > 10_000_000:
        raise InvalidParameterError(
            f"tile_size_m = {t:g} gives {n} tiles over the data; choose larger tiles"
        )
    colls = tuple(collections)
    keep = None
    if colls:  # the grid cells each file's box meets (closed test, as TileFile.overlaps)
        keep = set()
        for c in colls:
            lo_f, hi_f, full = c._boxes()
            for a, b in zip(lo_f[full], hi_f[full]):
                j0 = np.floor((a[:2] - float(grow_low_m) - o) / t).astype(np.int64)
                j1 = np.floor((b[:2] - o) / t).astype(np.int64)
                for ix in range(int(j0[0]), int(j1[0]) + 1):
                    for iy in range(int(j0[1]), int(j1[1]) + 1):
                        keep.add((ix, iy))
    out = []
    for ix in range(int(i0[0]), int(i1[0]) + 1):
        for iy in range(int(i0[1]), int(i1[1]) + 1):
            if keep is not None and (ix, iy) not in keep:
                continue
            x0, y0 = o[0] + ix * t, o[1] + iy * t
            out.append(Region(x0, y0, o[0] + (ix + 1) * t, o[1] + (iy + 1) * t, ix, iy))
    return out
