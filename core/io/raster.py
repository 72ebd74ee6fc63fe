"""GeoTIFF rasters (GDAL): north-up writing, atomic, with band names, CRS and metadata.

GDAL (``osgeo.gdal``) is imported inside the functions: without it the rest of SlipMap works and
these functions raise :class:`~slipmap.core.errors.DependencyError`.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Mapping, Sequence, Tuple, Union

import numpy as np

from ..errors import DependencyError, InvalidParameterError, SlipMapFileError
from .atomic import PathLike, atomic_path, write_text_atomic

__all__ = [
    "RasterBlockWriter",
    "band_names",
    "band_range",
    "raster_metadata",
    "read_geotiff",
    "style_sidecar",
    "write_geotiff",
    "write_raster_style",
]

_GDAL_TYPES = {
    np.dtype(np.uint8): "Byte",
    np.dtype(np.uint16): "UInt16",
    np.dtype(np.int16): "Int16",
    np.dtype(np.uint32): "UInt32",
    np.dtype(np.int32): "Int32",
    np.dtype(np.float32): "Float32",
    np.dtype(np.float64): "Float64",
}


def _gdal():
    try:
        from osgeo import gdal
    except ImportError as exc:  # pragma: no cover - depends on the environment
        raise DependencyError(
            "writing/reading GeoTIFF needs GDAL's Python bindings (osgeo.gdal): install "
            "python3-gdal (Debian/Ubuntu) or 'gdal' from conda-forge"
        ) from exc
    gdal.UseExceptions()
    return gdal


def write_geotiff(
    path: PathLike,
    array: np.ndarray,
    *,
    origin_xy: Tuple[float, float],
    pixel_size_m: Union[float, Tuple[float, float]],
    crs_wkt: str | None = None,
    nodata: float | None = np.nan,
    band_names: Sequence[str] | None = None,
    metadata: Mapping[str, str] | None = None,
) -> Path:
    """Write a north-up GeoTIFF atomically (DEFLATE-compressed, tiled).

    Parameters
    ----------
    path : str or os.PathLike
        Output ``.tif``; replaced only once the new file is complete.
    array : numpy.ndarray, shape (rows, cols) or (bands, rows, cols)
        Row 0 is the top (north) row. dtype uint8/(u)int16/(u)int32/float32/float64 (other
        dtypes are written as float64).
    origin_xy : (float, float)
        ``(x, y)`` of the upper-left corner of the upper-left pixel, in CRS units.
    pixel_size_m : float or (float, float)
        Pixel width and height (both > 0), CRS units.
    crs_wkt : str, optional
        The CRS as WKT (e.g. ``pyproj.CRS.to_wkt()``); None writes no CRS.
    nodata : float or None, default NaN
        Nodata value of every band; None for none. NaN is only valid for float arrays.
    band_names : sequence of str, optional
        One description per band.
    metadata : mapping of str to str, optional
        Dataset metadata items (e.g. the map-plane definition of a local frame).

    Returns
    -------
    pathlib.Path
    """
    gdal = _gdal()
    a = np.asarray(array)
    if a.ndim == 2:
        a = a[None, :, :]
    if a.ndim != 3 or a.shape[1] == 0 or a.shape[2] == 0:
        raise InvalidParameterError(
            f"write_geotiff: array must be (rows, cols) or (bands, rows, cols) and non-empty, "
            f"got shape {np.asarray(array).shape}"
        )
    if a.dtype not in _GDAL_TYPES:
        a = a.astype(np.float64)
    if np.isscalar(pixel_size_m):
        dx = dy = float(pixel_size_m)  # type: ignore[arg-type]
    else:
        dx, dy = (float(v) for v in pixel_size_m)  # type: ignore[union-attr]
    if not (dx > 0 and dy > 0 and math.isfinite(dx) and math.isfinite(dy)):
        raise InvalidParameterError(f"write_geotiff: pixel_size_m must be > 0, got {pixel_size_m}")
    x0, y0 = (float(v) for v in origin_xy)
    if band_names is not None and len(band_names) != a.shape[0]:
        raise InvalidParameterError(
            f"write_geotiff: {len(band_names)} band names for {a.shape[0]} bands"
        )
    if nodata is not None and math.isnan(nodata) and a.dtype.kind != "f":
        raise InvalidParameterError("write_geotiff: NaN nodata needs a float array; give nodata")
    bands, rows, cols = a.shape
    options = ["COMPRESS=DEFLATE", "TILED=YES"]
    if a.dtype.kind == "f":
        options.append("PREDICTOR=3")
    driver = gdal.GetDriverByName("GTiff")
    with atomic_path(path) as tmp:
        try:
            ds = driver.Create(
                str(tmp), cols, rows, bands, gdal.GetDataTypeByName(_GDAL_TYPES[a.dtype]), options
            )
        except RuntimeError as exc:
            raise SlipMapFileError(f"cannot write GeoTIFF {str(path)!r}: {exc}") from exc
        try:
            ds.SetGeoTransform((x0, dx, 0.0, y0, 0.0, -dy))
            if crs_wkt:
                ds.SetProjection(crs_wkt)
            if metadata:
                ds.SetMetadata({str(k): str(v) for k, v in metadata.items()})
            for b in range(bands):
                band = ds.GetRasterBand(b + 1)
                if nodata is not None:
                    band.SetNoDataValue(float(nodata))
                if band_names is not None:
                    band.SetDescription(str(band_names[b]))
                band.WriteArray(a[b])
            ds.FlushCache()
        finally:
            ds = None  # noqa: F841 - closes the dataset
    return Path(path)


def read_geotiff(path: PathLike) -> Tuple[np.ndarray, Tuple[float, ...], str]:
    """Read a raster: ``(array, geotransform, wkt)``.

    Returns
    -------
    array : numpy.ndarray
        (rows, cols) for one band, else (bands, rows, cols).
    geotransform : tuple of 6 float
        GDAL geotransform ``(x0, dx, 0, y0, 0, -dy)`` for north-up rasters.
    wkt : str
        The CRS WKT ('' when none).
    """
    gdal = _gdal()
    p = Path(path)
    if not p.is_file():
        raise SlipMapFileError(f"raster {str(p)!r} does not exist")
    try:
        ds = gdal.Open(str(p))
    except RuntimeError as exc:
        raise SlipMapFileError(f"cannot read raster {str(p)!r}: {exc}") from exc
    try:
        arr = ds.ReadAsArray()
        gt = tuple(float(v) for v in ds.GetGeoTransform())
        wkt = ds.GetProjection() or ""
    finally:
        ds = None  # noqa: F841
    return np.asarray(arr), gt, wkt


def band_names(path: PathLike) -> list:
    """Band descriptions of a raster (for tests and reports)."""
    gdal = _gdal()
    ds = gdal.Open(str(path))
    try:
        return [ds.GetRasterBand(i + 1).GetDescription() for i in range(ds.RasterCount)]
    finally:
        ds = None  # noqa: F841


def raster_metadata(path: PathLike) -> dict:
    """Dataset metadata items of a raster."""
    gdal = _gdal()
    ds = gdal.Open(str(path))
    try:
        return dict(ds.GetMetadata() or {})
    finally:
        ds = None  # noqa: F841


def style_sidecar(path: PathLike) -> Path:
    """The style file QGIS reads as a raster's default style: ``<name>.qml`` beside it
    (``windows.tif`` -> ``windows.qml``)."""
    return Path(path).with_suffix(".qml")


def write_raster_style(path: PathLike, qml: str) -> Path:
    """Write ``qml`` (QGIS's style format) as the default style of the raster ``path``.

    QGIS opens a raster with the ``.qml`` beside it (:func:`style_sidecar`) as its style, by
    drag and drop, from the browser or as ``QgsRasterLayer(path)``. The file is written
    atomically; the raster itself is not touched (it need not exist yet).

    Returns
    -------
    pathlib.Path
        The sidecar's path.
    """
    return write_text_atomic(style_sidecar(path), str(qml))


def band_range(path: PathLike, band: int = 1) -> Tuple[float, float]:
    """``(min, max)`` of the finite values of ``band`` (1-based) of a raster, read block by
    block (NaN, NaN when it has none)."""
    gdal = _gdal()
    ds = gdal.Open(str(path))
    try:
        b = ds.GetRasterBand(int(band))
        nodata = b.GetNoDataValue()
        bx, by = b.GetBlockSize()
        lo, hi = math.inf, -math.inf
        for r0 in range(0, ds.RasterYSize, max(by, 256)):
            rows = min(max(by, 256), ds.RasterYSize - r0)
            a = np.asarray(b.ReadAsArray(0, r0, ds.RasterXSize, rows), dtype=np.float64)
            ok = np.isfinite(a)
            if nodata is not None and math.isfinite(nodata):
                ok &= a != nodata
            if ok.any():
                lo, hi = min(lo, float(a[ok].min())), max(hi, float(a[ok].max()))
    finally:
        ds = None  # noqa: F841
    return (lo, hi) if lo <= hi else (math.nan, math.nan)


class RasterBlockWriter:
    """A float64 raster written block by block and closed as a Cloud-Optimized GeoTIFF.

    For rasters too large to hold in memory (the DEMs of a tiled run): blocks are written into
    a tiled, DEFLATE-compressed BigTIFF-if-needed scratch file beside ``path``; :meth:`close`
    translates it into a COG (GDAL's COG driver: internal tiles and overviews, readable by
    range requests) at a temporary name and moves it onto ``path``. Until then ``path`` is not
    touched; an error or a missing :meth:`close` (use it as a context manager) leaves nothing.

    Parameters
    ----------
    path : str or os.PathLike
        Final ``.tif``.
    shape : (bands, rows, cols)
    origin_xy, pixel_size_m, crs_wkt, band_names, metadata
        As :func:`write_geotiff` (NaN is the nodata value).
    """

    def __init__(
        self,
        path: PathLike,
        shape: Tuple[int, int, int],
        *,
        origin_xy: Tuple[float, float],
        pixel_size_m: float,
        crs_wkt: str | None = None,
        band_names: Sequence[str] | None = None,
        metadata: Mapping[str, str] | None = None,
    ):
        import tempfile

        gdal = _gdal()
        self.path = Path(path)
        bands, rows, cols = (int(v) for v in shape)
        if min(bands, rows, cols) < 1:
            raise InvalidParameterError(f"RasterBlockWriter: empty shape {shape}")
        if band_names is not None and len(band_names) != bands:
            raise InvalidParameterError(
                f"RasterBlockWriter: {len(band_names)} band names for {bands} bands"
            )
        directory = self.path.parent if str(self.path.parent) else Path(".")
        fd, name = tempfile.mkstemp(prefix=f".{self.path.stem}.", suffix=".part.tif", dir=directory)
        import os

        os.close(fd)
        self._scratch = Path(name)
        options = [
            "TILED=YES",
            "BLOCKXSIZE=256",
            "BLOCKYSIZE=256",
            "COMPRESS=DEFLATE",
            "PREDICTOR=3",
            "BIGTIFF=IF_SAFER",
            "SPARSE_OK=TRUE",
        ]
        try:
            ds = gdal.GetDriverByName("GTiff").Create(
                str(self._scratch), cols, rows, bands, gdal.GDT_Float64, options
            )
        except RuntimeError as exc:
            self._scratch.unlink(missing_ok=True)
            raise SlipMapFileError(f"cannot write GeoTIFF {str(path)!r}: {exc}") from exc
        dx = float(pixel_size_m)
        ds.SetGeoTransform((float(origin_xy[0]), dx, 0.0, float(origin_xy[1]), 0.0, -dx))
        if crs_wkt:
            ds.SetProjection(crs_wkt)
        if metadata:
            ds.SetMetadata({str(k): str(v) for k, v in metadata.items()})
        for b in range(bands):
            band = ds.GetRasterBand(b + 1)
            band.SetNoDataValue(float("nan"))
            if band_names is not None:
                band.SetDescription(str(band_names[b]))
        self._ds = ds
        self.shape = (bands, rows, cols)

    def write(self, block: np.ndarray, row0: int, col0: int) -> None:
        """Write ``block`` ``(bands, r, c)`` (or ``(r, c)`` for one band) at ``(row0, col0)``;
        the part outside the raster is dropped."""
        a = np.asarray(block, dtype=np.float64)
        if a.ndim == 2:
            a = a[None]
        bands, rows, cols = self.shape
        r0, c0 = int(row0), int(col0)
        r_lo, c_lo = max(0, -r0), max(0, -c0)
        r_hi = min(a.shape[1], rows - r0)
        c_hi = min(a.shape[2], cols - c0)
        if r_hi <= r_lo or c_hi <= c_lo:
            return
        for b in range(min(bands, a.shape[0])):
            self._ds.GetRasterBand(b + 1).WriteArray(
                np.ascontiguousarray(a[b, r_lo:r_hi, c_lo:c_hi]), c0 + c_lo, r0 + r_lo
            )

    def close(self) -> Path:
        """Finish: the COG replaces ``path`` (atomic)."""
        gdal = _gdal()
        ds, self._ds = self._ds, None
        try:
            ds.FlushCache()
            ds = None  # noqa: F841 - closes the scratch file
            with atomic_path(self.path) as tmp:
                out = gdal.Translate(
                    str(tmp),
                    str(self._scratch),
                    format="COG",
                    creationOptions=["COMPRESS=DEFLATE", "PREDICTOR=YES", "BIGTIFF=IF_SAFER"],
                )
                if out is None:
                    raise SlipMapFileError(f"cannot write GeoTIFF {str(self.path)!r}")
                out = None  # noqa: F841
        finally:
            self._scratch.unlink(missing_ok=True)
        return self.path

    def abort(self) -> None:
        """Drop everything written (``path`` untouched)."""
        self._ds = None
        self._scratch.unlink(missing_ok=True)

    def __enter__(self):
        return self

    def __exit__(self, exc_type, exc, tb):
        if exc_type is None:
            self.close()
        else:
            self.abort()
        return False
