"""The DIC engine's error budget: its displacements against the FE truth at the same material points.

The error ``e = engine - truth`` (mm, the recording's uy, uz) is summarized by region of the face
(reference coordinates):

- ``interior``: points at least ``band`` mm (one subset, by default) from every edge of the face;
- ``edge``: the band along the edges, where subsets reach past the specimen or are lost;
- ``high_gradient``: the tenth of the points where the FE field bends most (the largest second
  derivatives of uy, uz in the last frame): a subset's affine shape function cannot follow a
  curved displacement field, so DIC is biased there.

For each: the bias (mean error) and RMS per component over the loaded frames, and the observed
fraction. The error's **correlation length** is that of a squared-exponential correlation
``exp(-d^2 / (2 l^2))`` fitted (least squares) to its empirical correlogram: the errors of each
frame and component less their frame's mean, correlated over point pairs binned by distance.
"""
from __future__ import annotations

import numpy as np
from scipy.optimize import minimize_scalar
from scipy.spatial.distance import pdist


def edge_distance(yz, bounds) -> np.ndarray:
    """(P,) mm from material points (P, 2) = (y, z) to the nearest edge of the face ``bounds``."""
    (ylo, yhi), (zlo, zhi) = bounds
    return np.minimum.reduce([yz[:, 0] - ylo, yhi - yz[:, 0], yz[:, 1] - zlo, zhi - yz[:, 1]])


def _stats(e: np.ndarray) -> dict:
    """Bias and RMS per component (uy, uz) of errors (..., 2), NaN (lost) left out."""
    ok = np.isfinite(e[..., 0]) & np.isfinite(e[..., 1])
    if not ok.any():
        return {"bias_mm": [None, None], "rms_mm": [None, None], "observed": 0.0, "n": int(ok.size)}
    v = e[ok]
    return {"bias_mm": v.mean(axis=0).tolist(), "rms_mm": np.sqrt((v ** 2).mean(axis=0)).tolist(),
            "observed": float(ok.mean()), "n": int(ok.size)}


def correlogram(yz, e, bins) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The errors' correlation against distance: bin centres (B,) mm, correlation (B,), pair counts (B,).

    ``e``: (K, P, 2) errors; each frame's and component's mean is taken out, then the products of the
    pairs' errors are averaged per distance bin and divided by the variance (pooled over frames and
    components, observed pairs only)."""
    d = pdist(yz)
    num = np.zeros(len(bins) - 1)
    cnt = np.zeros(len(bins) - 1)
    var, nvar = 0.0, 0
    which = np.digitize(d, bins) - 1
    inside = (which >= 0) & (which < len(bins) - 1)
    iu = np.triu_indices(len(yz), k=1)
    for k in range(e.shape[0]):
        for c in range(2):
            v = e[k, :, c]
            ok = np.isfinite(v)
            if ok.sum() < 3:
                continue
            v = np.where(ok, v - v[ok].mean(), 0.0)
            var += float((v[ok] ** 2).sum())
            nvar += int(ok.sum())
            prod = v[iu[0]] * v[iu[1]]
            both = ok[iu[0]] & ok[iu[1]] & inside
            num += np.bincount(which[both], prod[both], minlength=len(bins) - 1)
            cnt += np.bincount(which[both], minlength=len(bins) - 1)
    centres = 0.5 * (bins[1:] + bins[:-1])
    with np.errstate(invalid="ignore", divide="ignore"):
        rho = (num / cnt) / (var / max(nvar, 1))
    return centres, rho, cnt


def correlation_length(centres, rho, counts) -> float:
    """The length l (mm) of ``exp(-d^2 / (2 l^2))`` closest (least squares, weighted by pair counts) to
    the correlogram; 0 when the errors are uncorrelated at the first bin."""
    ok = np.isfinite(rho) & (counts > 0)
    d, r, w = centres[ok], rho[ok], counts[ok]
    if not ok.any() or r[0] <= 0.05:
        return 0.0

    def loss(ell):
        return float((w * (r - np.exp(-d ** 2 / (2.0 * ell * ell))) ** 2).sum())

    return float(minimize_scalar(loss, bounds=(1e-3 * d.max(), d.max()), method="bounded").x)


def error_budget(yz, engine, truth, bounds, band: float, curvature=None, spacing: float | None = None) -> dict:
    """The engine's error budget (see the module's docstring).

    Parameters
    ----------
    yz : array (P, 2)
        The points' reference (y, z) on the face, mm.
    engine, truth : array (K, P, 2)
        The engine's (uy, uz) (NaN where lost) and the FE truth, mm; frame 0 unloaded.
    bounds : ((ylo, yhi), (zlo, zhi))
        The face, mm.
    band : float
        Width (mm) of the edge band.
    curvature : array (P,), optional
        How much the FE field bends at each point (the ``high_gradient`` region is its top tenth).
    spacing : float, optional
        The points' spacing (mm): the correlogram's bin width (default: the median nearest distance).

    Returns
    -------
    dict
        ``regions`` {interior, edge, high_gradient, all} of bias, RMS, observed fraction; ``frame0``
        (the engine's reading of the unloaded reference against itself); ``correlation_length_mm``,
        ``correlogram``; ``band_mm``.
    """
    yz, engine, truth = np.asarray(yz, float), np.asarray(engine, float), np.asarray(truth, float)
    err = engine - truth
    loaded = err[1:] if err.shape[0] > 1 else err
    dist = edge_distance(yz, bounds)
    regions = {"interior": dist >= band, "edge": dist < band}
    if curvature is not None:
        regions["high_gradient"] = np.asarray(curvature) >= np.quantile(curvature, 0.9)
    regions["all"] = np.ones(len(yz), dtype=bool)
    out = {"band_mm": float(band), "regions": {}, "points": {k: int(v.sum()) for k, v in regions.items()}}
    for name, sel in regions.items():
        out["regions"][name] = _stats(loaded[:, sel])
    out["frame0"] = _stats(err[:1])
    if spacing is None:
        from scipy.spatial import cKDTree

        spacing = float(np.median(cKDTree(yz).query(yz, k=2)[0][:, 1]))
    bins = (np.arange(11) + 0.5) * spacing  # neighbours 1..10 spacings apart
    centres, rho, counts = correlogram(yz, loaded, bins)
    out["correlation_length_mm"] = correlation_length(centres, rho, counts)
    out["correlogram"] = {"distance_mm": centres.tolist(), "correlation": np.nan_to_num(rho).tolist(),
                          "pairs": counts.astype(int).tolist()}
    return out
