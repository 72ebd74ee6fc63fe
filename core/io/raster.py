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
from .atomic import PathLike, atomic_path

__all__ = ["band_names", "raster_metadata", "read_geotiff", "write_geotiff"]

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
