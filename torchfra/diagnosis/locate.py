"""Step 1b of the diagnosis: where and when the recording leaves the base model.

The global chi^2 test of the whitened residual, per-frame tests with Benjamini-Hochberg control (the
onset), per-point tests grouped into clusters of neighbouring points, and the model-free hysteresis test
of path independence (loading against unloading at equal pressure)."""
from __future__ import annotations

import math

import numpy as np
import torch
from scipy import linalg, stats

from torchfra.diagnosis.model import ActuatorPhysics
from torchfra.diagnosis.noise import Whitener
from torchfra.observation.recording import Recording


def _bh(p: np.ndarray, alpha: float) -> np.ndarray:
    """Benjamini-Hochberg: True where rejected at false discovery rate alpha."""
    p = np.asarray(p, dtype=float)
    order = np.argsort(p)
    ranked = p[order] * p.size / (np.arange(p.size) + 1)
    passed = np.flatnonzero(ranked <= alpha)
    out = np.zeros(p.size, dtype=bool)
    if passed.size:
        out[order[: passed[-1] + 1]] = True
    return out


def consistency(E: np.ndarray, frames: np.ndarray, d: int, noise_dof: float | None = None) -> dict:
    """Global test of whitened residuals E (K, P, 2) over ``frames`` (d fitted parameters): chi^2 with
    n - d degrees of freedom when sigma is known; when sigma was estimated with ``noise_dof``
    effective degrees of freedom, the residual variance over sigma-hat^2 is F(n - d, noise_dof)
    (the chi^2 band would be far too narrow: sigma-hat^2 is itself uncertain by sqrt(2 / noise_dof))."""
    e = E[frames]
    e = e[np.isfinite(e)]
    n = e.size
    ss = float(e @ e)
    dof = max(n - d, 1)
    if noise_dof is None:
        p = float(stats.chi2.sf(ss, dof))
        z = (ss - dof) / math.sqrt(2 * dof)
    else:
        m = _ratio_dof(E.shape[0], frames, n, dof, noise_dof)
        p = float(stats.chi2.sf(m * ss / dof, m))
        z = (ss / dof - 1) * math.sqrt(m / 2)
    return {"statistic": ss, "dof": dof, "noise_dof": noise_dof, "nis_per_observation": ss / n,
            "rms": float(np.sqrt(ss / n)), "p_value": p, "z": z}


def _ratio_dof(K: int, frames: np.ndarray, n: int, dof: int, noise_dof: float) -> float:
    """Degrees of freedom m of the scaled chi^2 that matches the variance of RSS / (dof sigma-hat^2)
    under the noise model, sigma-hat^2 estimated from the second differences of the same recording
    (``estimate_noise``). Delta method: var = 2/dof + 2/noise_dof - 2 cov, where the whitened residuals
    and the second differences share the noise: cov(RSS, sum D2^2) = 2 sum_{k in frames} w_k o
    (w_k: frame k's weight in the second differences, o observations per frame). Independent noise
    gives var ~ 1.9/dof (chi^2 is about right); spatially correlated noise far more (sigma-hat rests
    on fewer independent samples), which chi^2 alone would turn into false alarms."""
    D = np.zeros((K - 2, K))
    for i in range(K - 2):
        D[i, i:i + 3] = (1.0, -2.0, 1.0)
    w = (D**2).sum(axis=0)
    o = n / max(len(frames), 1)
    cov = 2.0 * float(w[frames].sum()) / (6.0 * len(frames) * (K - 2) * o)
    var = max(2.0 / dof + 2.0 / noise_dof - 2.0 * cov, 0.5 * 2.0 / dof)
    return 2.0 / var


def locate(E: np.ndarray, rec: Recording, frames: np.ndarray, d: int, alpha: float, raw: np.ndarray,
           sigma: float, noise_dof: float | None = None) -> dict:
    """Global test, onset in time and spatial clusters of the whitened residuals E (K, P, 2);
    ``raw`` residuals (mm) give the map in noise units."""
    glob = consistency(E, frames, d, noise_dof)
    # per frame
    Ek = E[frames]
    ss_k = np.nansum(Ek**2, axis=(1, 2))
    n_k = np.isfinite(Ek).sum(axis=(1, 2))
    p_k = np.where(n_k > 0, stats.chi2.sf(ss_k, np.maximum(n_k, 1)), 1.0)
    sig_k = _bh(p_k, alpha)
    onset = None
    for j in range(len(frames)):
        if sig_k[j] and sig_k[j:].mean() > 0.5:
            onset = j
            break
    # per point (marginal: standardized, not whitened, so that a point is a point)
    std = raw[frames] / sigma
    ss_p = np.nansum(std**2, axis=(0, 2))
    n_p = np.isfinite(std).sum(axis=(0, 2))
    p_p = np.where(n_p > 0, stats.chi2.sf(ss_p, np.maximum(n_p, 1)), 1.0)
    sig_p = _bh(p_p, alpha)
    rms_p = np.sqrt(ss_p / np.maximum(n_p, 1))
    clusters = _clusters(rec.X, sig_p, rms_p, rec.point_ids)
    return {
        "global": glob,
        "detected": bool(glob["p_value"] < alpha),
        "onset": None if onset is None else {"frame": int(rec.frames[frames[onset]]),
                                              "pressure": float(rec.pressure[frames[onset]]),
                                              "time": float(rec.times[frames[onset]])},
        "frames_significant": int(sig_k.sum()),
        "points_significant": int(sig_p.sum()),
        "clusters": clusters,
        "point_rms": rms_p,
        "frame_statistic": ss_k / np.maximum(n_k, 1),
    }


def _clusters(X: np.ndarray, sig: np.ndarray, rms: np.ndarray, ids: np.ndarray) -> list[dict]:
    idx = np.flatnonzero(sig)
    if idx.size == 0:
        return []
    d = np.sqrt(((X[:, None, :] - X[None, :, :]) ** 2).sum(-1))
    np.fill_diagonal(d, np.inf)
    link = 1.5 * float(np.median(d.min(axis=1)))
    label = -np.ones(len(X), dtype=int)
    out = []
    for seed in idx:
        if label[seed] >= 0:
            continue
        stack, members = [seed], []
        label[seed] = len(out)
        while stack:
            i = stack.pop()
            members.append(i)
            for j in idx[(d[i, idx] <= link) & (label[idx] < 0)]:
                label[j] = len(out)
                stack.append(j)
        members = np.array(members)
        out.append({"points": int(members.size), "centre_mm": X[members].mean(axis=0).round(3).tolist(),
                    "z_range_mm": [float(X[members, 2].min()), float(X[members, 2].max())],
                    "rms_noise_units": float(np.sqrt(np.mean(rms[members] ** 2))),
                    "worst_point": int(ids[members[np.argmax(rms[members])]])})
    return sorted(out, key=lambda c: -c["points"] * c["rms_noise_units"] ** 2)


HISTORY_DEPENDENT = ("viscoelasticity", "a time lag of the pressure sensor", "Mullins-type damage on first loading",
                     "friction", "a drift of the camera or the specimen in time")


# the sense of the loop sorts the causes: a passive body that dissipates (creep, damage, friction)
# takes more work on loading than it returns, so at equal pressure it unloads through larger
# displacements (it lags its load); a loop the other way round would return more work than it took,
# which only a clock (a lagging pressure sensor, a camera out of step) or a drift can make. A cavity
# whose pressure lags its sensor (a pneumatic line) makes a loop of the first sense, like a creeping body
CAUSES = {"lags": ("viscoelasticity", "the cavity's pressure lagging its sensor (a pneumatic line between them)",
                   "Mullins-type damage on first loading", "friction", "a drift of the camera or the specimen in time"),
          "leads": ("a time lag of the pressure sensor, or the camera's clock out of step with it",
                    "a drift of the camera or the specimen in time")}


def _pressure_direction(phys: ActuatorPhysics, z: dict[str, float]) -> np.ndarray | None:
    """The model's dY/dlambda at every frame's load factor (K, P, 2), by linear interpolation between
    its load steps; None if its solve failed."""
    steps = phys.at_steps(z)
    if steps is None:
        return None
    s, _, dYs = steps
    zt = {k: torch.tensor([v], dtype=torch.float64) for k, v in z.items()}
    lam = np.clip(phys.frame_loads(zt).numpy(), 0.0, 1.0)
    i = np.clip(np.searchsorted(s, lam, side="right") - 1, 0, s.size - 2)
    t = ((lam - s[i]) / (s[i + 1] - s[i]))[:, None, None]
    return (1 - t) * dYs[i] + t * dYs[i + 1]


def hysteresis(rec: Recording, white: Whitener, alpha: float, direction: np.ndarray | None = None) -> dict:
    """Does the recording pass through the same state at the same pressure on loading and unloading?

    Every term of the model library is hyperelastic and quasi-static, so its observations are a
    function of the pressure alone: a recording that goes up and comes back down must show the same
    displacements at the same pressure. The loading branch (the frames up to the largest pressure,
    pressure rising) is interpolated at each unloading frame's pressure by a cubic spline (linear
    below 4 frames), which is linear in the data: ``d_k = Z_k - sum_j W_kj Z_j``. Under path
    independence ``d`` is noise only, with covariance ``(I + W W^T)`` in time times the spatial noise
    covariance (frames independent), so after spatial whitening and temporal decorrelation

    - omnibus: ``sum d^2`` is chi^2 with (unloading frames x observations per frame) dof;
    - directional: the projections of each ``d_k`` on ``direction[k]`` ((K, P, 2) for every frame;
      e.g. the calibrated model's
      ``dY/dpressure`` there: what a lagging or creeping pressure response moves) are jointly
      Gaussian with covariance ``(I + W W^T) o (cosines between the directions)``, chi^2 with one dof
      per unloading frame. Any fixed direction keeps the test valid; the model's makes it powerful.

    Each statistic takes half of ``alpha``. Points and components must be observed in every frame
    compared (others are left out). Returns a dict with ``applicable`` (False with a ``reason`` when
    the recording has no unloading frame within its loading range), ``detected``, both statistics,
    their dof and p-values, the frames compared, the loop per unloading frame (z-scores of the
    directional projections) and per point (RMS in noise units), and the largest loop in mm."""
    p = np.asarray(rec.pressure, dtype=np.float64)
    K = p.size
    top = int(np.argmax(p))
    start = top
    while start > 0 and p[start - 1] < p[start]:
        start -= 1
    load = np.arange(start, top + 1)
    after = np.arange(top + 1, K)
    if load.size < 2 or after.size == 0:
        return {"applicable": False, "detected": False,
                "reason": "the recording does not come back down from its largest pressure (no unloading frames)"
                if after.size == 0 else "fewer than 2 loading frames before the largest pressure"}
    p_l = p[load]
    unl = after[(p[after] >= p_l.min()) & (p[after] <= p_l.max())]
    if unl.size == 0:
        return {"applicable": False, "detected": False,
                "reason": "no unloading frame lies within the pressures of the loading branch"}
    if load.size >= 4:
        from scipy.interpolate import CubicSpline

        W = CubicSpline(p_l, np.eye(load.size))(p[unl])
    else:
        W = np.stack([np.interp(p[unl], p_l, e) for e in np.eye(load.size)], axis=1)
    frames = np.concatenate([load, unl])
    common = rec.mask[frames].all(axis=0)  # (P, 2)
    if not common.any():
        return {"applicable": False, "detected": False, "reason": "no point is observed in every frame compared"}
    Z = np.where(common[None], rec.Z, 0.0)
    D = Z[unl] - np.einsum("uj,jpc->upc", W, Z[load])  # (U, P, 2) mm
    mask = np.broadcast_to(common, D.shape)
    Dw = white(D, mask)
    A = np.eye(unl.size) + W @ W.T
    L = np.linalg.cholesky(A)
    flat = np.nan_to_num(Dw.reshape(unl.size, -1))
    n_obs = int(np.isfinite(Dw[0]).sum())
    X = linalg.solve_triangular(L, flat, lower=True)
    T1 = float(np.sum(X**2))
    dof1 = unl.size * n_obs
    out = {"applicable": True, "frames_loading": [int(rec.frames[k]) for k in load],
           "frames_unloading": [int(rec.frames[k]) for k in unl], "alpha": alpha,
           "omnibus": {"statistic": T1, "dof": dof1, "p_value": float(stats.chi2.sf(T1, dof1))}}
    z_frames = None
    if direction is not None:
        G = np.nan_to_num(white(np.where(mask, np.asarray(direction)[unl], 0.0), mask).reshape(unl.size, -1))
        norms = np.linalg.norm(G, axis=1)
        if np.all(norms > 0):
            Gh = G / norms[:, None]
            s_k = np.sum(Gh * flat, axis=1)
            C = A * (Gh @ Gh.T)
            T2 = float(s_k @ np.linalg.solve(C, s_k))
            out["directional"] = {"statistic": T2, "dof": int(unl.size), "p_value": float(stats.chi2.sf(T2, unl.size))}
            z_frames = s_k / np.sqrt(np.diag(C))
            # along dY/dpressure: > 0 when unloading passes through larger displacements than loading
            out["sense"] = "lags" if float(np.sum(s_k)) > 0 else "leads"
    tests = [out["omnibus"]] + ([out["directional"]] if "directional" in out else [])
    out["detected"] = bool(any(t["p_value"] < alpha / len(tests) for t in tests))
    scale = np.sqrt(np.diag(A))[:, None, None]
    loop = np.where(mask, D, np.nan) / white.noise.sigma / scale  # noise units per frame, per observation
    point_rms = np.sqrt(np.nanmean(loop**2, axis=(0, 2)))
    worst = np.argsort(-np.nan_to_num(point_rms))[:5]
    out["per_frame"] = [{"frame": int(rec.frames[k]), "pressure": float(p[k]),
                         "rms_noise_units": float(np.sqrt(np.nanmean(loop[i] ** 2))),
                         **({"directional_z": float(z_frames[i])} if z_frames is not None else {})}
                        for i, k in enumerate(unl)]
    out["worst_points"] = [{"point": int(rec.point_ids[j]), "X": rec.X[j].tolist(),
                            "rms_noise_units": float(point_rms[j])} for j in worst]
    out["largest_loop_mm"] = float(np.nanmax(np.abs(np.where(mask, D, np.nan))))
    if out["detected"]:
        sense = out.get("sense")
        out["physics"] = {"kind": "history-dependent",
                          "meaning": "the recording is not a function of the pressure alone: no hyperelastic, "
                                     "quasi-static term can explain it"
                                     + {"lags": "; the body lags its load, as a dissipating body does",
                                        "leads": "; the body leads the recorded pressure, which no passive body "
                                                 "does: a clock or a drift",
                                        None: ""}[sense],
                          "possible_causes": list(CAUSES.get(sense, HISTORY_DEPENDENT))}
    return out


def history_identifiable(rec: Recording, hold_fraction: float = 0.1) -> bool:
    """Whether a recording can show history-dependent physics apart from a load-axis warp: it comes
    back down from a pressure (a drop of more than 1 % of the largest), or holds a pressure above
    ``hold_fraction`` of the largest over two frames or more (a change below 0.1 % of it)."""
    p = np.asarray(rec.pressure, dtype=np.float64)
    top = float(np.max(np.abs(p))) if p.size else 0.0
    if top <= 0 or p.size < 3:
        return False
    drops = np.maximum.accumulate(p) - p > 0.01 * top
    hold = (np.abs(np.diff(p)) < 1e-3 * top) & (p[1:] > hold_fraction * top)
    return bool(drops.any() or hold.any())

