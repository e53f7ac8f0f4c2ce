"""The estimators a Python user calls: :func:`calibrate` and :func:`diagnose`, each returning a result
object with the headline as text (``.summary()``), the posterior per parameter (``.posterior``), the
record as JSON (``.to_json()``) and its figures (``.plot()``).

Both are thin layers over the library: :func:`torchfra.calibration.experiment.run_calibration` on a
:class:`~torchfra.calibration.config.CalibrationConfig`, and :func:`torchfra.diagnosis.diagnose`. Given a
``run_dir``, each writes its run folder as the commands do (``summary.json`` or ``diagnosis.json``, the
PNG figures, TensorBoard events); without one it works in a temporary folder that is removed afterwards,
and the result lives in memory only.

Examples
--------
>>> import torchfra
>>> cal = torchfra.calibrate(None, members=16, resolution=1, frames=20, restart=False)  # doctest: +SKIP
>>> print(cal.summary())                                                                # doctest: +SKIP
>>> cal.posterior["C10"].mean, cal.posterior["C10"].filters["hierarchical"]["std"]      # doctest: +SKIP
"""
from __future__ import annotations

import dataclasses
import json
import math
import tempfile
import time
from pathlib import Path

import numpy as np

from torchfra.calibration.config import FILTERS, CalibrationConfig
from torchfra.observation.recording import Recording

__all__ = ["CalibrationResult", "DiagnosisResult", "ParameterPosterior", "calibrate", "diagnose"]

_CALIBRATION_KEYWORDS = {f.name for f in dataclasses.fields(CalibrationConfig)} - {
    "recording", "parameters", "fixed", "truth", "noise"}
_DIAGNOSIS_KEYWORDS = ("correlation", "candidates", "resolution", "load_steps", "alpha", "evidence_threshold",
                       "held_out_every", "max_refits", "deck", "fe_history", "mesh_error")


@dataclasses.dataclass
class ParameterPosterior:
    """The posterior of one parameter.

    Attributes
    ----------
    name, unit : str
        The parameter and its unit (MPa for C10).
    mean, std : float
        The reference posterior's mean and standard deviation, in the parameter's own units: the exact
        (grid) posterior of a calibration, the Laplace posterior of the decision's model in a diagnosis.
    source : str
        Which posterior ``mean`` and ``std`` are ("exact", "laplace (base model)", ...).
    filters : dict
        Every posterior computed, by name, each a dict with ``mean`` and ``std`` (and ``p10``, ``p90``
        for a calibration's filters; ``distance_from_exact_in_exact_stds`` and ``spread_ratio_to_exact``
        against the exact posterior on the same frames). A calibration's names are those of
        :data:`torchfra.calibration.config.FILTERS`; a diagnosis's are ``base`` and ``extended``.
    """

    name: str
    unit: str
    mean: float
    std: float
    source: str
    filters: dict

    @property
    def exact(self) -> dict | None:
        """The exact posterior's statistics (a calibration), or None (a diagnosis)."""
        return self.filters.get("exact")


def _json_ready(value):
    """``value`` as plain JSON types (NumPy scalars and arrays as numbers and lists)."""
    def default(o):
        if isinstance(o, np.generic):
            return o.item()
        if isinstance(o, np.ndarray):
            return o.tolist()
        raise TypeError(f"{type(o).__name__} is not JSON")

    return json.loads(json.dumps(value, default=default))


def _number(x: float, std: float | None = None) -> str:
    """``x`` to the digits its ``std`` leaves meaningful (4 significant digits without one)."""
    if x is None or not math.isfinite(x):
        return str(x)
    if std is None or not (std > 0 and math.isfinite(std)):
        return f"{x:.4g}"
    digits = max(0, 1 - int(math.floor(math.log10(std))))
    return f"{x:.{digits}f}" if abs(x) >= 10 ** -digits else f"{x:.2e}"


class CalibrationResult:
    """What :func:`calibrate` found: the four posteriors of every uncertain parameter.

    Attributes
    ----------
    run_dir : Path or None
        The run folder written (None: nothing was kept on disk).
    posterior : dict of str to ParameterPosterior
        Per parameter: the exact posterior's mean and std, and every filter's in ``.filters``.
    noise : float
        The observation noise's standard deviation used (mm); ``noise_source`` says where it came from
        ("given", "estimated from the frames", "synthetic").
    """

    def __init__(self, summary: dict, out: dict, run_dir: Path | None, noise_source: str):
        self._summary = summary
        self._out = out
        self.run_dir = run_dir
        self.noise = float(summary["noise_std_mm"])
        self.noise_source = noise_source
        self.posterior = {}
        for p in summary["parameters"]:
            unit = summary["prior"][p].get("unit", "")
            filters = {}
            for name, row in summary["filters"].items():
                stats = dict(row[p])
                comp = summary["comparison"][name]
                comp = comp.get(p, comp) if len(summary["parameters"]) > 1 else comp
                stats["distance_from_exact_in_exact_stds"] = comp["distance_from_exact_mean_in_exact_stds"]
                stats["spread_ratio_to_exact"] = comp["spread_ratio_to_exact"]
                filters[name] = stats
            ex = filters["exact"]
            self.posterior[p] = ParameterPosterior(p, unit, float(ex["mean"]), float(ex["std"]), "exact", filters)

    def summary(self) -> str:
        """The headline as text: every parameter's exact posterior, each filter against it, the truth when
        the recording is synthetic, and whether the data fit the model at all.

        Returns
        -------
        str
            A few lines, one per parameter and filter.
        """
        s = self._summary
        lines = []
        headline = s.get("headline")
        if isinstance(headline, str):
            lines.append(headline)
        fit = s.get("data_fit", {"ok": True})
        if not fit.get("ok", True):
            lines.append("the data do not fit the model/prior; no calibration result: " + "; ".join(fit["reasons"]))
        for p, post in self.posterior.items():
            unit = f" {post.unit}" if post.unit else ""
            truth = s["truth"][p] if s.get("truth") else None
            lines.append(f"{p} = {_number(post.mean, post.std)} +- {post.std:.2g}{unit} (exact posterior"
                         + (f"; truth {truth:g}{unit})" if truth is not None else ")"))
            for name in FILTERS:
                if name == "exact" or name not in post.filters:
                    continue
                f = post.filters[name]
                lines.append(f"  {name}: {_number(f['mean'], f['std'])} +- {f['std']:.2g}{unit}, "
                             f"{f['distance_from_exact_in_exact_stds']:+.2f} exact stds from the exact mean, "
                             f"spread {f['spread_ratio_to_exact']:.2f}x the exact one")
        lines.append(f"{s['members']} members, {s['frames']} frames, noise {self.noise:g} mm ({self.noise_source})"
                     + (f"; run folder {self.run_dir}" if self.run_dir else ""))
        return "\n".join(lines)

    def to_json(self) -> dict:
        """The run's record, as ``summary.json`` holds it (plain JSON types).

        Returns
        -------
        dict
        """
        return _json_ready({**self._summary, "noise_source": self.noise_source})

    def plot(self) -> dict:
        """The run's figures, built anew (matplotlib ``Figure`` objects; save one with ``fig.savefig(path)``).

        Returns
        -------
        dict of str to matplotlib.figure.Figure
            ``bands`` (the tracked point and every parameter over time, each filter's 10-90 % band),
            ``pdfs`` (prior and posterior densities), and ``pairs`` for several parameters.
        """
        from torchfra.report.calibration import bands_figure, pairs_figure, pdf_figure

        figs = {"bands": bands_figure(self._out), "pdfs": pdf_figure(self._out)}
        if len(self.posterior) > 1:
            figs["pairs"] = pairs_figure(self._out)
        return figs

    def __repr__(self) -> str:
        return f"CalibrationResult({', '.join(f'{p}={v.mean:.5g}+-{v.std:.2g}' for p, v in self.posterior.items())})"


def _specs(value, what: str) -> list[str]:
    """Prior or fixed-value specs as ``NAME=...`` strings from a list of them or a dict."""
    if value is None:
        return []
    if isinstance(value, str):
        return [value]
    if isinstance(value, dict):
        return [f"{k}={v}" for k, v in value.items()]
    try:
        return [str(v) for v in value]
    except TypeError:
        raise TypeError(f"{what}: give a list of 'NAME=...' strings or a dict, got {type(value).__name__}") from None


def _recording_file(recording, folder: Path) -> tuple[str | None, Recording | None]:
    """A recording argument as a file the calibration reads (a Recording is written into ``folder``)."""
    from torchfra.io.recordings import read_recording, write_recording

    if recording is None:
        return None, None
    if isinstance(recording, Recording):
        path = folder / "recording_given.csv"
        write_recording(path, recording)
        return str(path), recording
    if isinstance(recording, (str, Path)):
        return str(recording), read_recording(recording)
    raise TypeError(f"recording: give a path to a CSV/NPZ recording, a torchfra Recording or None (synthetic), "
                    f"got {type(recording).__name__}")


def calibrate(recording=None, params=None, noise: float | None = None, run_dir=None, *, fixed=None, truth=None,
              progress: bool = True, **settings) -> CalibrationResult:
    """Calibrate the actuator's parameters from a recording with the four posteriors side by side.

    The hierarchical EnKF of the paper (linear slave), the same with a polynomial slave, the restart
    EnKF (FE re-solves) and the exact posterior, all on one forward ensemble of the prior
    (:func:`torchfra.calibration.experiment.run_calibration`).

    Parameters
    ----------
    recording : str, Path, Recording or None
        A CSV/NPZ recording (``frame,time,pressure,point_id,X,Y,Z,uy,uz``, mm and MPa), a
        :class:`~torchfra.observation.recording.Recording`, or None for a synthetic recording made by
        the model at ``truth`` (the paper's experiment).
    params : list of str or dict, optional
        The uncertain parameters and their priors, ``["C10=lognormal:0.0062,0.0011", ...]`` or
        ``{"C10": "lognormal:0.0062,0.0011"}`` (kinds ``lognormal``, ``normal``, ``uniform``). None: the
        paper's prior of C10.
    noise : float, optional
        The observation noise's standard deviation (mm). None: estimated from the recording's frames
        (frame-to-frame differences, :func:`torchfra.diagnosis.estimate_noise`); for a synthetic
        recording, the noise it is made with (1 mm).
    run_dir : str or Path, optional
        The run folder: ``summary.json``, ``bands.png``, ``pdfs.png`` (``pairs.png``), TensorBoard
        events; the forward ensemble is cached beside it in ``forward_cache/``. None: nothing is kept.
    fixed : list of str or dict, optional
        Parameters held at a value, ``["E_fiber=31000"]`` or ``{"E_fiber": 31000}``.
    truth : float or dict, optional
        The synthetic recording's values: C10 (MPa) or ``{name: value}`` per uncertain parameter.
    progress : bool
        Progress bars on stderr.
    **settings
        Any other field of :class:`~torchfra.calibration.config.CalibrationConfig`: ``members`` (100),
        ``resolution`` (1), ``frames`` (100, synthetic), ``pressure`` (MPa, the forward ensemble's
        largest), ``load_steps``, ``restart`` (True), ``restart_every``, ``coverage_seeds``, ``grid``,
        ``degree``, ``inp`` (your own deck), ...

    Returns
    -------
    CalibrationResult

    Raises
    ------
    TypeError
        An unknown keyword (named, with the valid ones).
    ValueError
        A bad prior, truth or recording (``PriorError``, ``RecordingError``: the message names it).
    """
    import torch

    from torchfra.calibration.experiment import run_calibration
    from torchfra.calibration.frames import validate_recording
    from torchfra.calibration.priors import ParameterSet
    from torchfra.report.calibration import write_calibration_outputs

    unknown = sorted(set(settings) - _CALIBRATION_KEYWORDS)
    if unknown:
        raise TypeError(f"calibrate() got an unknown keyword {unknown[0]!r}; valid: "
                        f"{', '.join(sorted(_CALIBRATION_KEYWORDS | {'fixed', 'truth', 'progress'}))}")
    parameters, fixed_specs = _specs(params, "params"), _specs(fixed, "fixed")
    if fixed_specs and not parameters:
        raise ValueError("fixed: name the uncertain parameters with params as well (the paper's prior fixes "
                         "E_fiber itself)")
    if parameters:
        ParameterSet.parse(parameters, fixed_specs)  # every bad entry named before any work
    torch.set_default_dtype(torch.float64)
    with tempfile.TemporaryDirectory(prefix="torchfra_calibrate_") as tmp:
        folder = Path(run_dir) if run_dir is not None else Path(tmp) / "run"
        folder.mkdir(parents=True, exist_ok=True)
        path, rec = _recording_file(recording, folder)
        if rec is not None and noise is None:
            from torchfra.diagnosis.noise import estimate_noise

            noise, source = float(estimate_noise(rec).sigma), "estimated from the frames"
        else:
            source = "given" if noise is not None else "synthetic"
        values = dict(truth) if isinstance(truth, dict) else ({"C10": truth} if truth is not None else {})
        if values and path is not None:
            raise ValueError("truth sets a synthetic recording's values; a recording has its own (give recording=None)")
        config = CalibrationConfig(recording=path, parameters=parameters, fixed=fixed_specs,
                                   **({"noise": float(noise)} if noise is not None else {}), **settings)
        if "C10" in values:
            config = dataclasses.replace(config, truth_c10=float(values.pop("C10")))
        if values:
            config = dataclasses.replace(config, truth={k: float(v) for k, v in values.items()})
        if config.parameters and path is None:
            from torchfra.calibration.forward import truth_values

            truth_values(config)  # each value checked against its prior before any FE work
        validate_recording(config)
        t0 = time.perf_counter()
        out = run_calibration(config, folder, progress=progress)
        summary = write_calibration_outputs(out, folder, time.perf_counter() - t0)
        summary = _json_ready(summary)
        return CalibrationResult(summary, out, Path(run_dir) if run_dir is not None else None, source)


class DiagnosisResult:
    """What :func:`diagnose` found: the decision, the ranking of the candidates, the fits before and after.

    Attributes
    ----------
    decision : str
        ``"none"`` (no mismatch), ``"unexplained"``, a candidate, or candidates the data cannot tell
        apart joined by ``"|"``.
    run_dir : Path or None
        The run folder written (None: nothing was kept on disk).
    posterior : dict of str to ParameterPosterior
        Per parameter of the decision's model: its Laplace posterior (mean, std in the parameter's
        units); ``.filters`` holds the ``base`` and ``extended`` fits' where each has the parameter.
    """

    def __init__(self, out: dict, recording: Recording, residuals: dict, run_dir: Path | None):
        self._out = _json_ready(out)
        self._rec = recording
        self._residuals = residuals
        self.run_dir = run_dir
        self.decision = self._out["decision"]
        base, ext = self._out["parameters"]["base"], self._out["parameters"]["extended"]
        chosen = ext if ext is not None else base
        self.posterior = {}
        for p, row in chosen.items():
            fits = {k: {"mean": v[p]["mean"], "std": v[p]["std"]} for k, v in (("base", base), ("extended", ext))
                    if v is not None and p in v}
            source = f"laplace ({'extended' if ext is not None else 'base'} model)"
            self.posterior[p] = ParameterPosterior(p, row.get("unit", ""), float(row["mean"]), float(row["std"]),
                                                   source, fits)

    def summary(self) -> str:
        """The headline as text: the decision, the fit before and after, the ranking's significant
        candidates and those the recording could not test.

        Returns
        -------
        str
        """
        o = self._out
        mp = o["missing_physics"]
        what = {"none": "no mismatch with the base model", "unexplained": "a mismatch no candidate explains"}
        named = what.get(o["decision"], f"missing physics: {mp.get('name', mp.get('kind'))}")
        lines = [f"decision: {o['decision']} ({named})",
                 f"fit: whitened RMS {o['fit_before']['rms']:.3g} before, {o['fit_after']['rms']:.3g} after "
                 f"(1 is the noise level, sigma {o['noise']['sigma']:.3g} mm)"]
        for p, post in self.posterior.items():
            lines.append(f"  {p} = {_number(post.mean, post.std)} +- {post.std:.2g} {post.unit} ({post.source})")
        sig = [r for r in o["ranking"] if r["significant"]]
        lines.append("significant candidates: "
                     + (", ".join(f"{r['name']} (score {r['score']:.3g}, p = {r['p_value']:.2g})" for r in sig)
                        or "none"))
        skipped = {**o["not_testable"], **o["not_available"]}
        if skipped:
            lines.append("not tested: " + "; ".join(f"{k}: {v}" for k, v in skipped.items()))
        lines.append(f"{o['frames']} frames, {o['points']} points, {o['cost']['solves']} FE solves"
                     + (f"; run folder {self.run_dir}" if self.run_dir else ""))
        return "\n".join(lines)

    def to_json(self) -> dict:
        """The diagnosis as ``diagnosis.json`` holds it (:class:`torchfra.diagnosis.Diagnosis`'s fields).

        Returns
        -------
        dict
        """
        return json.loads(json.dumps(self._out))

    def plot(self) -> dict:
        """The diagnosis's main figures, built anew (matplotlib ``Figure`` objects).

        Returns
        -------
        dict of str to matplotlib.figure.Figure
            ``ranking`` (the candidates' score statistics against the test level), ``residual_map`` (the
            RMS residual on the face before and after), ``observed_vs_models`` (the worst point).
        """
        from torchfra.report.diagnosis import observed_vs_models_figure, ranking_figure, residual_map_figure

        r, rec, sigma = self._residuals, self._rec, self._out["noise"]["sigma"]
        Z = rec.Z - r["mesh_error_taken_out"]
        accepted = self._out["parameters"]["extended"] is not None
        rms_b = np.sqrt(np.nanmean((r["before"] / sigma) ** 2, axis=(0, 2)))
        rms_a = np.sqrt(np.nanmean((r["after"] / sigma) ** 2, axis=(0, 2))) if accepted else None
        return {"ranking": ranking_figure(self._out),
                "residual_map": residual_map_figure(rec, rms_b, rms_a, self.decision),
                "observed_vs_models": observed_vs_models_figure(rec, Z, Z - r["before"],
                                                                Z - r["after"] if accepted else None,
                                                                int(np.argmax(rms_b)), self.decision)}

    def __repr__(self) -> str:
        return f"DiagnosisResult(decision={self.decision!r})"


def diagnose(recording, noise: float | None = None, run_dir=None, *, progress: bool = True,
             **options) -> DiagnosisResult:
    """Diagnose the physics a recording shows the model lacks: locate the mismatch, rank the candidate
    terms by score tests, refit, decide (:func:`torchfra.diagnosis.diagnose`).

    Parameters
    ----------
    recording : str, Path or Recording
        A CSV/NPZ recording or a :class:`~torchfra.observation.recording.Recording` whose points are
        followed through the frames.
    noise : float, optional
        The noise's standard deviation (mm); estimated from the frames when None.
    run_dir : str or Path, optional
        The run folder: ``diagnosis.json``, ``residuals.npz``, the figures, TensorBoard events and every
        FE solve (a rerun reuses them). None: nothing is kept.
    progress : bool
        Progress on stderr.
    **options
        ``correlation`` (mm), ``candidates`` ("all" or a list of names,
        :data:`torchfra.diagnosis.ALL_CANDIDATES`), ``resolution`` (1), ``load_steps`` (10), ``alpha``
        (0.01), ``evidence_threshold`` (5), ``held_out_every`` (5), ``max_refits``, ``deck`` (a
        :class:`torchfra.actuator.deck.DeckModel`), ``fe_history``, ``mesh_error``.

    Returns
    -------
    DiagnosisResult

    Raises
    ------
    TypeError
        An unknown keyword (named, with the valid ones).
    torchfra.diagnosis.DiagnosisError, torchfra.observation.recording.RecordingError
        A recording the diagnosis cannot use (the message names what and what to do).
    """
    import torch

    from torchfra.diagnosis import diagnose as run_diagnosis
    from torchfra.io.recordings import read_recording

    unknown = sorted(set(options) - set(_DIAGNOSIS_KEYWORDS))
    if unknown:
        raise TypeError(f"diagnose() got an unknown keyword {unknown[0]!r}; valid: "
                        f"{', '.join(sorted((*_DIAGNOSIS_KEYWORDS, 'progress')))}")
    if isinstance(recording, (str, Path)):
        rec = read_recording(recording)
    elif isinstance(recording, Recording):
        rec = recording
    else:
        raise TypeError(f"recording: give a path to a CSV/NPZ recording or a torchfra Recording, "
                        f"got {type(recording).__name__}")
    torch.set_default_dtype(torch.float64)
    with tempfile.TemporaryDirectory(prefix="torchfra_diagnose_") as tmp:
        folder = Path(run_dir) if run_dir is not None else Path(tmp) / "run"
        out = run_diagnosis(rec, noise=noise, run_dir=folder, progress=progress, **options)
        with np.load(folder / "residuals.npz", allow_pickle=False) as z:
            residuals = {k: z[k] for k in ("before", "after", "mesh_error_taken_out")}
    return DiagnosisResult(out, rec, residuals, Path(run_dir) if run_dir is not None else None)
