"""Figures (matplotlib, Agg backend, no pyplot state): roughness maps, histograms, semivariograms.

Every function takes plain arrays, writes one PNG atomically and returns its path. matplotlib is
imported inside the functions; without it they raise
:class:`~slipmap.core.errors.DependencyError`.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Mapping, Sequence, Tuple

import numpy as np

from ..core.errors import DependencyError, InvalidParameterError
from ..core.io.atomic import PathLike, atomic_path

__all__ = [
    "plot_normals_polar",
    "hillshade",
    "plot_plane_residual_polar",
    "plot_raster_panels",
    "plot_vector_field",
    "plot_residual_histograms",
    "plot_roughness_histograms",
    "plot_roughness_map",
    "plot_semivariograms",
    "plot_strip_profile",
    "write_html_report",
]

#: marker per series, in the order given (the study's Fig. 4: ODR circles, OLS triangles,
#: E_OLS plus signs)
_MARKERS = ("o", "^", "+", "s", "x", "D")


def _figure(width_in: float, height_in: float):
    try:
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure
    except ImportError as exc:  # pragma: no cover - depends on the environment
        raise DependencyError(
            "figures need matplotlib: pip install matplotlib (or apt install python3-matplotlib)"
        ) from exc
    fig = Figure(figsize=(width_in, height_in), layout="constrained")
    FigureCanvasAgg(fig)
    return fig


def _save(fig, path: PathLike, dpi: int, metadata: Mapping[str, str] | None = None) -> Path:
    """Write the PNG atomically; ``metadata``: PNG text chunks (e.g. ``Description``)."""
    with atomic_path(path) as tmp:
        fig.savefig(str(tmp), format="png", dpi=dpi, metadata=dict(metadata or {}) or None)
    return Path(path)


def plot_roughness_map(
    path: PathLike,
    panels: Mapping[str, np.ndarray],
    *,
    extent: Tuple[float, float, float, float],
    cutoff: float | None = None,
    axis_labels: Tuple[str, str] = ("x (m)", "y (m)"),
    title: str | None = None,
    colorbar_label: str = "roughness (m)",
    dpi: int = 150,
) -> Path:
    """Maps of roughness, one panel per entry (the study's Fig. 2 when ``cutoff`` is given).

    Parameters
    ----------
    path : str or os.PathLike
        Output PNG.
    panels : mapping of str to numpy.ndarray, shape (rows, cols)
        Panel title -> raster (row 0 at the top); NaN is drawn white.
    extent : (left, right, bottom, top)
        Map coordinates of the raster edges.
    cutoff : float, optional
        Binary transform: values >= cutoff black, below light grey (values are usually the
        normalised roughness). None: a continuous colour scale per panel.
    axis_labels : (str, str)
    title : str, optional
    colorbar_label : str
    dpi : int

    Returns
    -------
    pathlib.Path
    """
    if not panels:
        raise InvalidParameterError("plot_roughness_map: give at least one panel")
    from matplotlib.colors import ListedColormap

    left, right, bottom, top = extent
    width, height = max(right - left, 1e-9), max(top - bottom, 1e-9)
    n = len(panels)
    stacked = width / height > 2.0
    if stacked:
        fig = _figure(9.0, min(12.0, 0.8 + n * (9.0 * height / width + 0.7)))
        axes = [fig.add_subplot(n, 1, i + 1) for i in range(n)]
    else:
        fig = _figure(min(16.0, 1.0 + n * 5.0), 5.0)
        axes = [fig.add_subplot(1, n, i + 1) for i in range(n)]
    for ax, (name, raster) in zip(axes, panels.items()):
        data = np.ma.masked_invalid(np.asarray(raster, dtype=np.float64))
        if cutoff is not None:
            binary = np.ma.where(data >= cutoff, 1.0, 0.0)
            cmap = ListedColormap(["0.75", "black"])
            cmap.set_bad("white")
            ax.imshow(binary, extent=extent, cmap=cmap, vmin=0, vmax=1, interpolation="nearest")
            frac = float(np.ma.mean(binary)) if binary.count() else float("nan")
            ax.set_title(f"{name}: {100 * frac:.1f} % of pixels >= {cutoff:g}", fontsize=10)
        else:
            im = ax.imshow(data, extent=extent, cmap="viridis", interpolation="nearest")
            fig.colorbar(im, ax=ax, label=colorbar_label, shrink=0.8)
            ax.set_title(name, fontsize=10)
        ax.set_xlabel(axis_labels[0])
        ax.set_ylabel(axis_labels[1])
        ax.set_aspect("equal")
    if title:
        fig.suptitle(title)
    return _save(fig, path, dpi)


def plot_roughness_histograms(
    path: PathLike,
    panels: Mapping[str, np.ndarray],
    *,
    bin_width: float = 0.05,
    title: str | None = None,
    dpi: int = 150,
) -> Path:
    """Histograms of normalised roughness on [0, 1] (the study's Fig. 3), one panel per entry.

    Parameters
    ----------
    path : str or os.PathLike
    panels : mapping of str to numpy.ndarray
        Panel title -> normalised values (NaN ignored).
    bin_width : float, default 0.05
    title : str, optional
    dpi : int

    Returns
    -------
    pathlib.Path
    """
    if not panels:
        raise InvalidParameterError("plot_roughness_histograms: give at least one panel")
    k = int(round(1.0 / bin_width))
    edges = np.linspace(0.0, 1.0, k + 1)
    n = len(panels)
    fig = _figure(min(16.0, 1.0 + 4.5 * n), 3.8)
    for i, (name, values) in enumerate(panels.items()):
        ax = fig.add_subplot(1, n, i + 1)
        v = np.asarray(values, dtype=np.float64).ravel()
        v = v[np.isfinite(v)]
        counts, _ = np.histogram(v, bins=edges)
        pct = 100.0 * counts / max(1, v.size)
        ax.bar(edges[:-1], pct, width=bin_width, align="edge", color="0.35", edgecolor="black")
        ax.set_xlim(0, 1)
        ax.set_xlabel("normalised roughness")
        ax.set_ylabel("cells (%)")
        ax.set_title(f"{chr(65 + i)}: {name} ({pct[0]:.0f} % in the first bin)", fontsize=10)
    if title:
        fig.suptitle(title)
    return _save(fig, path, dpi)


def plot_semivariograms(
    path: PathLike,
    panels: Sequence[Tuple[str, Mapping[str, Tuple[np.ndarray, np.ndarray]]]],
    *,
    ylabel: str = "normalised semivariance  γ(h) / σ²",
    xlabel: str = "lag h (m)",
    title: str | None = None,
    dpi: int = 150,
) -> Path:
    """Experimental semivariograms, one panel per entry (the study's Fig. 4).

    Parameters
    ----------
    path : str or os.PathLike
    panels : sequence of (str, mapping of str to (lag, gamma))
        Panel title and its series: name -> (lag (K,), gamma (K,)). Series are drawn with
        circles, triangles, plus signs, ... in the order given.
    ylabel, xlabel, title : str
    dpi : int

    Returns
    -------
    pathlib.Path
    """
    if not panels:
        raise InvalidParameterError("plot_semivariograms: give at least one panel")
    n = len(panels)
    ncols = min(n, 2)
    nrows = (n + ncols - 1) // ncols
    fig = _figure(5.0 * ncols + 0.5, 3.8 * nrows + 0.3)
    for i, (name, series) in enumerate(panels):
        ax = fig.add_subplot(nrows, ncols, i + 1)
        for j, (label, (lag, gamma)) in enumerate(series.items()):
            marker = _MARKERS[j % len(_MARKERS)]
            face = "none" if marker in ("o", "^", "s", "D") else None
            ax.plot(
                np.asarray(lag),
                np.asarray(gamma),
                linestyle="none",
                marker=marker,
                markerfacecolor=face,
                color="black" if j == 0 else f"C{j}",
                label=label,
            )
        ax.axhline(1.0, color="0.6", linewidth=0.8, linestyle="--")
        ax.set_xlabel(xlabel)
        ax.set_ylabel(ylabel)
        ax.set_title(f"{chr(65 + i)}: {name}", fontsize=10)
        ax.set_ylim(bottom=0)
        ax.legend(fontsize=8)
    if title:
        fig.suptitle(title)
    return _save(fig, path, dpi)


def plot_residual_histograms(
    path: PathLike, residuals: Mapping[str, np.ndarray], *, title: str | None = None, dpi: int = 150
) -> Path:
    """Histograms of point-to-plane residuals with a Gaussian fit, one panel per entry
    (the study's Fig. 6 / Fig. 10). Residuals in metres, shown in millimetres."""
    if not residuals:
        raise InvalidParameterError("residuals: give at least one series")
    fig = _figure(4.2 * len(residuals), 3.4)
    axes = fig.subplots(1, len(residuals), squeeze=False)[0]
    for ax, (name, r) in zip(axes, residuals.items()):
        mm = 1000.0 * np.asarray(r, dtype=np.float64)
        mm = mm[np.isfinite(mm)]
        if mm.size == 0:
            ax.set_title(f"{name}: no residuals")
            continue
        mu, sd = float(mm.mean()), float(mm.std())
        lim = max(4 * sd, 1e-6)
        ax.hist(mm, bins=80, range=(mu - lim, mu + lim), density=True, color="0.7")
        x = np.linspace(mu - lim, mu + lim, 200)
        if sd > 0:
            ax.plot(x, np.exp(-0.5 * ((x - mu) / sd) ** 2) / (sd * np.sqrt(2 * np.pi)), "k-")
        ax.set_title(f"{name}: mean {mu:.2f} mm, sd {sd:.2f} mm")
        ax.set_xlabel("residual along the plane normal (mm)")
        ax.set_ylabel("density")
    if title:
        fig.suptitle(title)
    return _save(fig, path, dpi)


def plot_normals_polar(
    path: PathLike, normals: Mapping[str, np.ndarray], *, title: str | None = None, dpi: int = 150
) -> Path:
    """Polar plot of plane-normal azimuth (clockwise from north) against elevation (the
    study's Fig. 4): which directions the matched planes constrain."""
    fig = _figure(4.2 * max(1, len(normals)), 4.2)
    for k, (name, n) in enumerate(normals.items()):
        ax = fig.add_subplot(1, max(1, len(normals)), k + 1, projection="polar")
        n = np.asarray(n, dtype=np.float64).reshape(-1, 3)
        az = np.arctan2(n[:, 0], n[:, 1])
        elev = np.degrees(np.arcsin(np.clip(np.abs(n[:, 2]), 0, 1)))
        ax.set_theta_zero_location("N")
        ax.set_theta_direction(-1)
        ax.scatter(az, 90 - elev, s=10, c="k")
        ax.set_rlim(0, 90)
        ax.set_title(f"{name}: {n.shape[0]} planes (radius = 90° − elevation)")
    if title:
        fig.suptitle(title)
    return _save(fig, path, dpi)


def readable_number(value: float, digits: int = 4) -> str:
    """``value`` for a reader: ``digits`` significant digits in fixed point when
    0.001 <= |value| < 10⁶ (trailing zeros dropped: 0.01787, 17.87, 215334), otherwise three
    significant digits with an exponent (1.6e-05); NaN and infinities as ``nan``, ``inf``."""
    import math

    v = float(value)
    if not math.isfinite(v):
        return str(v)
    a = abs(v)
    if a == 0:
        return "0"
    if 1e-3 <= a < 1e6:
        decimals = max(0, digits - 1 - int(math.floor(math.log10(a))))
        text = f"{v:.{decimals}f}"
        return text.rstrip("0").rstrip(".") if "." in text else text
    return f"{v:.2e}".replace("e-0", "e-").replace("e+0", "e+")


def write_html_report(
    path: PathLike,
    title: str,
    tables: Mapping[str, object],
    images: Sequence[str],
    *,
    lead: str = "",
) -> Path:
    """A self-contained HTML summary: ``lead`` (the result in one sentence) under the title,
    one table per entry of ``tables`` and the given image files (relative paths beside the
    report).

    A table is either a mapping (one ``key | value`` row per item) or a sequence of mappings
    (rows of a table whose columns are the keys, in order of first appearance). Floats are
    shown for reading (:func:`readable_number`: 4 significant digits, no exponent between
    0.001 and 10⁶), None as an empty cell."""
    import html

    def cell(value) -> str:
        if value is None:
            return ""
        if isinstance(value, (float, np.floating)):
            return readable_number(float(value))
        if isinstance(value, (list, tuple)):
            # numpy scalars as Python numbers: under numpy 2 their repr is "np.float64(...)"
            plain = [v.item() if isinstance(v, np.generic) else v for v in value]
            value = plain if isinstance(value, list) else tuple(plain)
        return str(value)

    parts = [
        "<!DOCTYPE html><html><head><meta charset='utf-8'>",
        f"<title>{html.escape(title)}</title>",
        "<style>body{font-family:sans-serif;margin:2em}table{border-collapse:collapse;"
        "margin-bottom:1.5em}td,th{border:1px solid #bbb;padding:3px 8px;text-align:right}"
        "th{background:#eee}td.text{text-align:left}img{max-width:100%;margin:1em 0}"
        "</style></head><body>",
        f"<h1>{html.escape(title)}</h1>",
    ]
    if lead:
        parts.append(f"<p style='font-size:1.3em'><b>{html.escape(lead)}</b></p>")
    for name, rows in tables.items():
        parts.append(f"<h2>{html.escape(name)}</h2><table>")
        if isinstance(rows, Mapping):
            for key, value in rows.items():
                parts.append(
                    f"<tr><th>{html.escape(str(key))}</th><td>{html.escape(cell(value))}</td></tr>"
                )
        else:
            rows = list(rows)
            columns: list = []
            for row in rows:
                columns += [k for k in row if k not in columns]
            parts.append("<tr>" + "".join(f"<th>{html.escape(str(c))}</th>" for c in columns))
            for row in rows:
                tds = []
                for c in columns:
                    v = row.get(c)
                    cls = " class='text'" if isinstance(v, str) else ""
                    tds.append(f"<td{cls}>{html.escape(cell(v))}</td>")
                parts.append("<tr>" + "".join(tds) + "</tr>")
        parts.append("</table>")
    for img in images:
        parts.append(f"<div><img src='{html.escape(img)}' alt='{html.escape(img)}'></div>")
    parts.append("</body></html>")
    with atomic_path(path) as tmp:
        tmp.write_text("\n".join(parts), encoding="utf-8")
    return Path(path)


def plot_strip_profile(
    path: PathLike,
    along_m: np.ndarray,
    value_m: np.ndarray,
    sigma_m: np.ndarray,
    side: Sequence[str],
    *,
    side_names: Mapping[str, str] | None = None,
    title: str = "Right-lateral motion along strike: each side's strips and their sum",
    dpi: int = 150,
) -> Path:
    """Strip profile (the study's Fig. 5) in the sign convention (docs/methods.md, "Sign
    convention"): each side's right-lateral motion ± 1σ (+ = dextral on either side) against
    along-strike distance, and where both sides have a strip at one chainage their sum, the
    local right-lateral slip (σ of the two added in quadrature).

    Parameters
    ----------
    along_m, value_m, sigma_m : (K,) float64
        Strip centre chainage (m), right-lateral motion and its 1σ (m).
    side : (K,) str
        "left" or "right".
    side_names : mapping, optional
        Compass name of each side (``{"left": "west", "right": "east"}``) for the legend.

    The PNG's ``Description`` text chunk holds the axis label and the plotted series (JSON,
    mm) so that the figure can be checked without reading pixels.
    """
    import json

    names = dict(side_names or {})
    fig = _figure(7.0, 3.6)
    ax = fig.subplots()
    along, value, sigma = (np.asarray(a, dtype=np.float64) for a in (along_m, value_m, sigma_m))
    sides = np.asarray(side)
    series = {}
    for name, marker in (("left", "o"), ("right", "s")):
        k = (sides == name) & np.isfinite(value)
        label = f"{name} ({names[name]}) side" if names.get(name) else f"{name} side"
        if k.any():
            ax.errorbar(
                along[k], 1000 * value[k], yerr=1000 * sigma[k], fmt=marker, capsize=3, label=label
            )
            series[label] = [[float(a), float(1000 * v)] for a, v in zip(along[k], value[k])]
    pairs = []
    for a in np.unique(along):
        lv = (sides == "left") & (along == a) & np.isfinite(value)
        rv = (sides == "right") & (along == a) & np.isfinite(value)
        if lv.any() and rv.any():
            i, j = np.flatnonzero(lv)[0], np.flatnonzero(rv)[0]
            pairs.append((a, value[i] + value[j], math.hypot(sigma[i], sigma[j])))
    if pairs:
        a, v, s = (np.array(x) for x in zip(*pairs))
        label = "sum: local right-lateral slip"
        ax.errorbar(a, 1000 * v, yerr=1000 * s, fmt="D", color="k", capsize=3, label=label)
        series[label] = [[float(x), float(1000 * y)] for x, y in zip(a, v)]
    ylabel = "right-lateral motion (mm, + = dextral)"
    ax.axhline(0, color="0.6", lw=0.8)
    ax.set_xlabel("along-strike distance (m)")
    ax.set_ylabel(ylabel)
    ax.set_title(title, fontsize=9)
    ax.legend(fontsize=8)
    description = json.dumps({"ylabel": ylabel, "series_mm": series})
    return _save(fig, path, dpi, metadata={"Title": title, "Description": description})


def plot_plane_residual_polar(
    path: PathLike,
    series: Mapping[str, Tuple[np.ndarray, np.ndarray]],
    *,
    title: str = "Mean residual of each matched plane against its normal azimuth",
    dpi: int = 150,
) -> Path:
    """Per-plane mean residual (mm, radius) against the normal's azimuth (clockwise from
    north), one panel per side (the study's Fig. 10 polar plots). ``series[name]`` is
    ``(normals (K, 3), mean_residual_m (K,))``; planes with |nz| > 0.9 (roofs facing up) are
    drawn at their azimuth all the same, in grey."""
    fig = _figure(4.2 * max(1, len(series)), 4.4)
    for k, (name, (normals, res)) in enumerate(series.items()):
        ax = fig.add_subplot(1, max(1, len(series)), k + 1, projection="polar")
        n = np.asarray(normals, dtype=np.float64).reshape(-1, 3)
        r = 1000.0 * np.asarray(res, dtype=np.float64)
        ok = np.isfinite(r)
        az = np.arctan2(n[:, 0], n[:, 1])
        flat = np.abs(n[:, 2]) > 0.9
        ax.set_theta_zero_location("N")
        ax.set_theta_direction(-1)
        ax.scatter(
            az[ok & ~flat],
            np.abs(r[ok & ~flat]),
            c=np.sign(r[ok & ~flat]),
            cmap="coolwarm",
            vmin=-1,
            vmax=1,
            s=14,
        )
        ax.scatter(az[ok & flat], np.abs(r[ok & flat]), c="0.6", s=14)
        ax.set_title(f"{name}: |mean residual| (mm); red > 0, blue < 0", fontsize=8)
    fig.suptitle(title, fontsize=9)
    return _save(fig, path, dpi)


def hillshade(
    z: np.ndarray, *, cell_m: float, azimuth_deg: float = 315.0, altitude_deg: float = 45.0
):
    """Hillshade in [0, 1] of a north-up elevation grid (row 0 = north); NaN stays NaN.

    Parameters
    ----------
    z : (rows, cols) float64
        Elevations, metres.
    cell_m : float
        Cell size, metres.
    azimuth_deg, altitude_deg : float
        Sun azimuth (clockwise from north) and altitude, degrees.
    """
    z = np.asarray(z, dtype=np.float64)
    if z.ndim != 2 or min(z.shape) < 2:
        return np.full(z.shape, np.nan)
    dzdy_rows, dzdx = np.gradient(z, cell_m)
    dzdy = -dzdy_rows  # rows run south
    az, alt = np.radians(azimuth_deg), np.radians(altitude_deg)
    # surface normal (-dz/dx, -dz/dy, 1) against the sun direction (east, north, up)
    sun = np.array([np.sin(az) * np.cos(alt), np.cos(az) * np.cos(alt), np.sin(alt)])
    norm = np.sqrt(dzdx**2 + dzdy**2 + 1.0)
    return np.clip((-dzdx * sun[0] - dzdy * sun[1] + sun[2]) / norm, 0.0, 1.0)


def plot_vector_field(
    path: PathLike,
    *,
    x: np.ndarray,
    y: np.ndarray,
    dx: np.ndarray,
    dy: np.ndarray,
    valid: np.ndarray | None = None,
    background: np.ndarray | None = None,
    extent: Tuple[float, float, float, float] | None = None,
    colour: np.ndarray | None = None,
    colour_label: str = "dz (m)",
    title: str | None = None,
    dpi: int = 150,
) -> Path:
    """Quiver plot of horizontal displacements over a grey background (e.g. a hillshade).

    Parameters
    ----------
    path : str or os.PathLike
        Output PNG.
    x, y, dx, dy : (M,) float64
        Vector positions and components (metres, map coordinates); NaN vectors are skipped.
    valid : (M,) bool, optional
        False vectors (replaced / interpolated) are drawn in orange.
    background : (rows, cols) float64, optional
        Raster drawn in grey under the vectors (row 0 at the top), with ``extent``.
    extent : (left, right, bottom, top), optional
    colour : (M,) float64, optional
        Colours valid vectors by this value (e.g. dz) with a diverging ramp.
    """
    x, y, dx, dy = (np.asarray(a, dtype=np.float64).ravel() for a in (x, y, dx, dy))
    ok = np.isfinite(dx) & np.isfinite(dy) & np.isfinite(x) & np.isfinite(y)
    v = np.ones_like(ok) if valid is None else np.asarray(valid, dtype=bool).ravel()
    fig = _figure(8.0, 7.0)
    ax = fig.add_subplot(1, 1, 1)
    if background is not None and extent is not None:
        ax.imshow(np.ma.masked_invalid(background), extent=extent, cmap="gray", vmin=0, vmax=1)
    mag = np.hypot(dx[ok], dy[ok])
    scale = None
    if mag.size and np.nanmax(mag) > 0:
        # the longest arrow spans about two vector spacings
        span = max(np.ptp(x[ok]) if ok.any() else 1.0, np.ptp(y[ok]) if ok.any() else 1.0, 1e-9)
        spacing = span / max(np.sqrt(ok.sum()), 1.0)
        scale = float(np.nanpercentile(mag, 99)) / (2.0 * spacing) or None
    good, bad = ok & v, ok & ~v
    kw = dict(angles="xy", scale_units="xy", scale=scale, width=0.003)
    if colour is not None and good.any():
        c = np.asarray(colour, dtype=np.float64).ravel()[good]
        lim = float(np.nanmax(np.abs(c))) if np.isfinite(c).any() else 1.0
        q = ax.quiver(
            x[good], y[good], dx[good], dy[good], c, cmap="RdBu_r", clim=(-lim, lim), **kw
        )
        fig.colorbar(q, ax=ax, label=colour_label, shrink=0.8)
    elif good.any():
        ax.quiver(x[good], y[good], dx[good], dy[good], color="tab:blue", **kw)
    if bad.any():
        thin = dict(kw, width=0.002)
        ax.quiver(
            x[bad],
            y[bad],
            dx[bad],
            dy[bad],
            color="tab:orange",
            alpha=0.6,
            label="replaced",
            **thin,
        )
        ax.legend(loc="upper right", fontsize=8)
    if mag.size:
        ax.set_xlabel(f"x (m) - median |d| {np.median(mag):.3f} m, max {np.max(mag):.3f} m")
    else:
        ax.set_xlabel("x (m) - no vectors")
    ax.set_ylabel("y (m)")
    ax.set_aspect("equal")
    ax.ticklabel_format(useOffset=False, style="plain")
    if title:
        ax.set_title(title)
    return _save(fig, path, dpi)


def plot_raster_panels(
    path: PathLike,
    panels: Mapping[str, np.ndarray],
    *,
    extent: Tuple[float, float, float, float],
    diverging: Sequence[str] = (),
    cyclic: Sequence[str] = (),
    title: str | None = None,
    columns: int = 3,
    dpi: int = 130,
) -> Path:
    """A grid of raster maps (e.g. strain bands); ``diverging`` panels use a symmetric
    blue-red ramp centred on 0, ``cyclic`` panels (axial directions in [0°, 180°)) a cyclic
    ramp, the others viridis. NaN is drawn white."""
    if not panels:
        raise InvalidParameterError("plot_raster_panels: give at least one panel")
    n = len(panels)
    cols = min(columns, n)
    rows = int(np.ceil(n / cols))
    fig = _figure(4.2 * cols, 3.8 * rows)
    for i, (name, raster) in enumerate(panels.items()):
        ax = fig.add_subplot(rows, cols, i + 1)
        data = np.ma.masked_invalid(np.asarray(raster, dtype=np.float64))
        if name in diverging:
            lim = float(np.ma.max(np.abs(data))) if data.count() else 1.0
            im = ax.imshow(data, extent=extent, cmap="RdBu_r", vmin=-lim, vmax=lim)
        elif name in cyclic:
            im = ax.imshow(data, extent=extent, cmap="twilight", vmin=0.0, vmax=180.0)
        else:
            im = ax.imshow(data, extent=extent, cmap="viridis")
        fig.colorbar(im, ax=ax, shrink=0.8)
        ax.set_title(name, fontsize=10)
        ax.set_aspect("equal")
        ax.ticklabel_format(useOffset=False, style="plain")
        ax.tick_params(labelsize=7)
    if title:
        fig.suptitle(title)
    return _save(fig, path, dpi)
