"""Uncertain parameters as data: priors, fixed values, and the coordinates the filters work in.

A parameter set says which of the actuator model's parameters are uncertain (each with a prior on
the parameter itself) and which take fixed values; every other parameter keeps its base-model value
(``D1 = 1 / (bulk_ratio C10)``, ``E_fiber = 31000`` MPa, candidates at their null). Names, units and
admissible ranges come from the registry :data:`torchfra.actuator.candidates.COORDINATES`; no name is hard-wired
elsewhere.

Priors, written ``NAME=KIND:A,B`` on the command line or in a TOML file:

==========  ==========================  ===================================  =======================
kind        A, B                        filter coordinate q                  q's prior
==========  ==========================  ===================================  =======================
lognormal   mean, std of the parameter  log x                                N(mu, s^2) (lognormal)
normal      mean, std                   x                                    N(A, B^2)
uniform     lower, upper bound          Phi^-1((x - A) / (B - A)) (probit)   N(0, 1)
==========  ==========================  ===================================  =======================

Every prior is Gaussian in its coordinate q (the ensemble Kalman filters' assumption, paper §3.4),
and q maps back to an admissible value for any real q (exp keeps a scale positive, the probit keeps a
uniform parameter inside its bounds). The paper's experiment is ``C10=lognormal:0.0061765,0.001123``.
"""
from __future__ import annotations

import hashlib
import json
import math
import re
from dataclasses import dataclass
from pathlib import Path

import torch

from torchfra.actuator.candidates import (
    ADDED_MODEL_PARAMETERS,
    BULK_RATIO,
    COORDINATES,
    E_FIBER,
    SENSOR_PARAMETERS,
    actuator_model,
    candidates_of,
)
from torchfra.io.files import read_text

KINDS = ("lognormal", "normal", "uniform")
# parameters that act on the frames' load factors, not on the FE solve (the candidate that carries them)
SENSOR = SENSOR_PARAMETERS
MAX_PARAMETER_FILE_BYTES = 1 << 20  # a parameter file is a few lines; a bigger one is the wrong file
_NAME = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")  # a parameter name as a file or flag writes it
TAIL = 4.0  # a normal prior's mean +- TAIL stds (and a lognormal's matching quantiles) must be admissible


class PriorError(ValueError):
    """A parameter set that cannot be used; the message names the parameter and what to do."""


def _known() -> str:
    return ", ".join(sorted(COORDINATES))


def _info(name: str, where: str):
    reg = COORDINATES
    if name not in reg:
        raise PriorError(f"{where}: unknown parameter '{name}'; the model's parameters are {_known()}")
    return reg[name]


def lognormal_parameters(mean: float, std: float) -> tuple[float, float]:
    """(mu, sigma) of log X for a lognormal X with the given mean and standard deviation."""
    if not (mean > 0 and std > 0):
        raise ValueError(f"a lognormal prior needs mean > 0 and std > 0, got mean={mean}, std={std}")
    sigma2 = math.log1p((std / mean) ** 2)
    return math.log(mean) - 0.5 * sigma2, math.sqrt(sigma2)


@dataclass(frozen=True)
class Prior:
    """Prior of one uncertain parameter: ``kind`` with ``a``, ``b`` (mean and std for lognormal and
    normal, bounds for uniform), given for the parameter itself in its unit."""

    name: str
    kind: str
    a: float
    b: float

    @property
    def unit(self) -> str:
        return COORDINATES[self.name].unit

    @property
    def gaussian(self) -> tuple[float, float]:
        """(mean, std) of the coordinate q, which is normal under this prior."""
        if self.kind == "lognormal":
            return lognormal_parameters(self.a, self.b)
        if self.kind == "normal":
            return self.a, self.b
        return 0.0, 1.0

    def natural(self, q: torch.Tensor) -> torch.Tensor:
        """Parameter values of coordinates q (any real q gives an admissible value)."""
        if self.kind == "lognormal":
            return torch.exp(q)
        if self.kind == "normal":
            return q
        return self.a + (self.b - self.a) * torch.special.ndtr(q)

    def coordinate(self, x) -> torch.Tensor:
        x = torch.as_tensor(x, dtype=torch.float64)
        if self.kind == "lognormal":
            return torch.log(x)
        if self.kind == "normal":
            return x.clone()
        return torch.special.ndtri((x - self.a) / (self.b - self.a))

    @property
    def transform(self) -> str:
        return {"lognormal": "log", "normal": "linear", "uniform": "probit"}[self.kind]

    @property
    def mean(self) -> float:
        return 0.5 * (self.a + self.b) if self.kind == "uniform" else self.a

    def spec(self) -> str:
        return f"{self.name}={self.kind}:{self.a!r},{self.b!r}"

    def describe(self) -> str:
        if self.kind == "uniform":
            return f"{self.name} ~ uniform [{self.a:g}, {self.b:g}] {self.unit}"
        return f"{self.name} ~ {self.kind} (mean {self.a:g}, std {self.b:g}) {self.unit}"


def _number(text: str, what: str) -> float:
    try:
        v = float(text)
    except ValueError:
        raise PriorError(f"{what}: '{text}' is not a number") from None
    if not math.isfinite(v):
        raise PriorError(f"{what}: {text} is not a finite number")
    return v


def parse_prior(text: str) -> Prior:
    """``NAME=KIND:A,B`` -> :class:`Prior`, checked against the parameter's admissible range."""
    where = f"--param {text!r}"
    if "=" not in text or ":" not in text.split("=", 1)[1]:
        raise PriorError(f"{where}: write NAME=KIND:A,B, e.g. C10=lognormal:0.0062,0.0011 or C01=uniform:0,0.002 "
                         f"(kinds: {', '.join(KINDS)})")
    name, rest = (s.strip() for s in text.split("=", 1))
    kind, args = (s.strip() for s in rest.split(":", 1))
    info = _info(name, where)
    if kind not in KINDS:
        raise PriorError(f"{where}: unknown prior kind '{kind}'; use one of {', '.join(KINDS)}")
    parts = [s for s in args.split(",")]
    if len(parts) != 2:
        raise PriorError(f"{where}: a {kind} prior takes two numbers "
                         f"({'lower,upper bound' if kind == 'uniform' else 'mean,std of the parameter'})")
    a, b = (_number(s.strip(), where) for s in parts)
    prior = Prior(name, kind, a, b)
    rng = f"[{info.low:g}, {info.high:g}] {info.unit}"
    if kind == "uniform":
        if not a < b:
            raise PriorError(f"{where}: a uniform prior needs lower < upper, got {a:g}, {b:g}")
        lo, hi = a, b
    else:
        if not b > 0:
            raise PriorError(f"{where}: the prior's std must be > 0, got {b:g}")
        if kind == "lognormal":
            if not a > 0:
                raise PriorError(f"{where}: a lognormal prior needs mean > 0, got {a:g}")
            mu, s = prior.gaussian
            lo, hi = math.exp(mu - TAIL * s), math.exp(mu + TAIL * s)
            if info.low > lo:
                raise PriorError(f"{where}: {name} must lie in {rng}, but a lognormal prior reaches "
                                 f"{lo:.3g}; use a uniform prior within the range")
        else:
            lo, hi = a - TAIL * b, a + TAIL * b
    if lo < info.low or hi > info.high:
        raise PriorError(f"{where}: {name} must lie in {rng}, but this prior reaches [{lo:.4g}, {hi:.4g}] "
                         f"({'its bounds' if kind == 'uniform' else f'mean +- {TAIL:g} stds'}); narrow it or "
                         "choose a prior that stays in the range (lognormal for a positive scale, uniform for a bounded one)")
    if name in SENSOR:
        raise PriorError(f"{where}: {name} acts on the recorded pressure (the frames' load factors), not on the FE "
                         f"solve of a forward ensemble; it is estimated by scripts/diagnose.py (candidate {SENSOR[name]})")
    return prior


def parse_fixed(text: str, flag: str = "--fixed") -> tuple[str, float]:
    """``NAME=VALUE`` -> (name, value), checked against the admissible range."""
    where = f"{flag} {text!r}"
    if "=" not in text:
        raise PriorError(f"{where}: write NAME=VALUE, e.g. E_fiber=31000")
    name, value = (s.strip() for s in text.split("=", 1))
    info = _info(name, where)
    v = _number(value, where)
    if not info.low <= v <= info.high or (info.transform == "log" and v <= 0):
        raise PriorError(f"{where}: {name} must lie in [{info.low:g}, {info.high:g}] {info.unit}")
    if name in SENSOR:
        raise PriorError(f"{where}: {name} acts on the recorded pressure (the frames' load factors), not on the FE "
                         f"solve; see scripts/diagnose.py (candidate {SENSOR[name]})")
    return name, v


@dataclass(frozen=True)
class ParameterSet:
    """Uncertain parameters (``priors``, in order: the columns of every ensemble) and ``fixed`` ones."""

    priors: tuple[Prior, ...]
    fixed: tuple[tuple[str, float], ...] = ()

    def __post_init__(self):
        names = [p.name for p in self.priors] + [n for n, _ in self.fixed]
        dup = sorted({n for n in names if names.count(n) > 1})
        if dup:
            raise PriorError(f"parameters {dup} are given more than once (as a prior and/or a fixed value); give each once")
        if not self.priors:
            raise PriorError("no uncertain parameter: give at least one prior, e.g. --param C10=lognormal:0.0062,0.0011")
        if "C10" not in names:
            raise PriorError("C10 needs a prior (--param C10=lognormal:MEAN,STD) or a value (--fixed C10=VALUE)")
        if ("c_n" in names) != ("c_t" in names):
            raise PriorError("a compliant base has two compliances: give both c_n and c_t (a prior or a fixed value each)")

    @classmethod
    def parse(cls, params=(), fixed=()) -> "ParameterSet":
        return cls(tuple(parse_prior(t) for t in params), tuple(parse_fixed(t) for t in fixed))

    @classmethod
    def from_file(cls, path) -> "ParameterSet":
        """The parameter set of a TOML file (see :func:`read_parameter_file`)."""
        f = read_parameter_file(path)
        return cls.parse(f["parameters"], f["fixed"])

    # -- names and coordinates -----------------------------------------------------------------------
    @property
    def names(self) -> list[str]:
        return [p.name for p in self.priors]

    @property
    def d(self) -> int:
        return len(self.priors)

    def specs(self) -> tuple[list[str], list[str]]:
        return [p.spec() for p in self.priors], [f"{n}={v!r}" for n, v in self.fixed]

    def key(self) -> str:
        """Short fingerprint of the whole set (the forward cache's folder name carries it)."""
        return hashlib.sha256(json.dumps(self.specs()).encode()).hexdigest()[:10]

    def gaussian(self) -> tuple[torch.Tensor, torch.Tensor]:
        """(means, stds) of the coordinates' independent normal priors, (d,) each."""
        m, s = zip(*(p.gaussian for p in self.priors))
        return torch.tensor(m, dtype=torch.float64), torch.tensor(s, dtype=torch.float64)

    def sample(self, n: int, generator: torch.Generator) -> torch.Tensor:
        """Prior draws of the coordinates, (n, d): independent across parameters."""
        m, s = self.gaussian()
        z = torch.randn(n, self.d, generator=generator, dtype=torch.float64)
        return m + s * z

    def natural(self, Q: torch.Tensor) -> dict[str, torch.Tensor]:
        """Parameter values name -> (N,) of coordinates Q (N, d)."""
        return {p.name: p.natural(Q[:, j]) for j, p in enumerate(self.priors)}

    def coordinates(self, values: dict) -> torch.Tensor:
        """Coordinates (N, d) of parameter values name -> (N,)."""
        return torch.stack([p.coordinate(values[p.name]).reshape(-1) for p in self.priors], dim=1)

    # -- the FE model -------------------------------------------------------------------------------
    def candidates(self) -> tuple[str, ...]:
        """Candidate physics the model must switch on to carry these parameters."""
        return candidates_of(set(self.names) | {n for n, _ in self.fixed})

    def build_model(self, resolution: int, integration: str = "full"):
        """The actuator model with the candidates these parameters need, and its info."""
        return actuator_model(self.candidates(), resolution, integration)

    def model_parameters(self, Q: torch.Tensor, pressure: float, bulk_ratio: float = BULK_RATIO,
                         E_fiber: float = E_FIBER, base: dict | None = None) -> dict[str, torch.Tensor]:
        """Every FE model parameter, name -> (N,), of coordinates Q (N, d): uncertain ones from Q, fixed
        ones as given, the rest at the base model's values (D1 tied to C10 by ``bulk_ratio``).

        ``base``: the values of every parameter of a model read from a deck (``read_inp``): the rest
        then keep the deck's values (D1 included: no tie to C10) and ``P`` is ``pressure``; a
        parameter the deck's model does not have is refused by name."""
        N = Q.shape[0]
        values = self.natural(Q)
        for n, v in self.fixed:
            values[n] = torch.full((N,), float(v), dtype=torch.float64)
        if base is not None:
            unknown = sorted(set(values) - set(base))
            if unknown:
                raise PriorError(f"the deck's model has no parameter {', '.join(unknown)} (its parameters: "
                                 f"{', '.join(sorted(base))}); give priors or values of those only")
            p = {k: torch.full((N,), float(v), dtype=torch.float64) for k, v in base.items()}
            p.update(values)
            if "P" in p:
                p["P"] = torch.full((N,), float(pressure), dtype=torch.float64)
            return p
        c10 = values["C10"]
        p = {"C10": c10, "D1": values["D1"] if "D1" in values else 1.0 / (bulk_ratio * c10),
             "E_fiber": values.get("E_fiber", torch.full((N,), E_fiber, dtype=torch.float64)),
             "P": torch.full((N,), pressure, dtype=torch.float64)}
        for n in ADDED_MODEL_PARAMETERS:
            if n in values:
                p[n] = values[n]
        return p

    def values(self, truth: dict, where: str = "truth") -> torch.Tensor:
        """Coordinates (1, d) of parameter values given by name; a missing one takes its null value."""
        reg = COORDINATES
        row = {}
        for p in self.priors:
            if p.name in truth:
                row[p.name] = torch.tensor([float(truth[p.name])], dtype=torch.float64)
            elif reg[p.name].null is not None:
                row[p.name] = torch.tensor([float(reg[p.name].null)], dtype=torch.float64)
            else:
                raise PriorError(f"{where}: {p.name} has no value (give {p.name}=VALUE)")
        unknown = sorted(set(truth) - set(self.names))
        if unknown:
            raise PriorError(f"{where}: {unknown} are not uncertain parameters of this set ({self.names})")
        Q = self.coordinates(row)
        if not torch.isfinite(Q).all():
            bad = [p.name for j, p in enumerate(self.priors) if not torch.isfinite(Q[0, j])]
            raise PriorError(f"{where}: {bad} lie outside their prior's support; choose values inside the prior")
        return Q

    def check_truth(self, truth: dict, where: str = "truth") -> torch.Tensor:
        """:meth:`values` of a truth (a synthetic recording's values), each also inside its prior's
        reach: a normal or lognormal prior's mean +- ``TAIL`` stds in its coordinate (the reach its
        admissible range is checked over), a uniform prior's bounds.

        Parameters
        ----------
        truth : dict
            ``{name: value}`` of uncertain parameters; a missing one takes its null value.
        where : str
            Where the values come from, for the messages.

        Returns
        -------
        torch.Tensor
            The coordinates (1, d).

        Raises
        ------
        PriorError
            Naming the parameter, its value and its prior's reach, for a value outside it.
        """
        Q = self.values(truth, where)
        m, s = self.gaussian()
        for j, p in enumerate(self.priors):
            if p.kind != "uniform" and p.name in truth and abs(float(Q[0, j] - m[j])) > TAIL * float(s[j]):
                lo, hi = (float(p.natural(torch.tensor([float(m[j] + k * TAIL * s[j])], dtype=torch.float64))[0])
                          for k in (-1, 1))
                raise PriorError(f"{where}: {p.name} = {float(truth[p.name]):g} lies outside its prior "
                                 f"{p.describe()} (which reaches [{lo:.4g}, {hi:.4g}], mean +- {TAIL:g} stds); "
                                 "choose a value inside the prior, or widen the prior")
        return Q

    def log_prior(self, Q: torch.Tensor) -> torch.Tensor:
        """log density of the coordinates Q (..., d) under the independent normal priors."""
        m, s = self.gaussian()
        return (-0.5 * ((Q - m) / s) ** 2 - torch.log(s * math.sqrt(2 * math.pi))).sum(-1)

    def describe(self) -> str:
        fixed = "; fixed: " + ", ".join(f"{n} = {v:g}" for n, v in self.fixed) if self.fixed else ""
        return "; ".join(p.describe() for p in self.priors) + fixed


def read_parameter_file(path) -> dict:
    """A TOML file with a ``[parameters]`` table of prior strings, and optional ``[fixed]`` values and
    ``[truth]`` values (of a synthetic recording)::

        [parameters]
        C10 = "lognormal:0.0062,0.0011"
        E_fiber = "lognormal:31000,6000"
        [fixed]
        C01 = 0.0
        [truth]
        C10 = 0.0048
        E_fiber = 25000

    Returns {"parameters": [specs], "fixed": [specs], "truth": {name: value}}, every entry checked."""
    import tomllib

    path = Path(path)
    text = read_text(path, what="parameter", max_bytes=MAX_PARAMETER_FILE_BYTES, error=PriorError)
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise PriorError(f"{path}: not valid TOML ({exc})") from None
    except RecursionError:  # tomllib parses nested arrays and inline tables recursively
        raise PriorError(f"{path}: arrays or inline tables nested too deep to read; a parameter file holds the "
                         "flat tables [parameters], [fixed] and [truth] of strings and numbers") from None
    unknown = sorted(set(data) - {"parameters", "fixed", "truth"})
    if unknown:
        raise PriorError(f"{path}: unknown tables {unknown}; a parameter file has [parameters], [fixed] and [truth]")
    for table, kinds, example in (("parameters", (str,), 'C10 = "lognormal:0.0062,0.0011"'),
                                  ("fixed", (int, float), "C01 = 0.0"), ("truth", (int, float), "C10 = 0.0048")):
        entries = data.get(table, {})
        if not isinstance(entries, dict):
            raise PriorError(f"{path}: {table} must be a table [{table}] of entries such as {example}")
        for key, value in entries.items():
            if not _NAME.fullmatch(key):
                raise PriorError(f"{path}: [{table}] {key!r} is not a parameter name (letters, digits and _, no "
                                 f"spaces or quotes); the model's parameters are {_known()}")
            if not isinstance(value, kinds) or isinstance(value, bool):
                what = "a prior string" if table == "parameters" else "a number"
                raise PriorError(f"{path}: [{table}] {key} = {value!r} is not {what}; write e.g. {example}")
    if not data.get("parameters"):
        raise PriorError(f"{path}: no [parameters] table with priors, e.g. C10 = \"lognormal:0.0062,0.0011\"")
    out = {"parameters": [f"{k}={v}" for k, v in data["parameters"].items()],
           "fixed": [f"{k}={v}" for k, v in data.get("fixed", {}).items()], "truth": {}}
    try:
        pset = ParameterSet.parse(out["parameters"], out["fixed"])
        out["truth"] = {k: float(v) for k, v in data.get("truth", {}).items()}
        if out["truth"]:
            pset.check_truth(out["truth"], where="[truth]")
    except PriorError as exc:
        raise PriorError(f"{path}: {exc}") from None
    return out


def parse_truth(items) -> dict[str, float]:
    """``--truth`` values: ``NAME=VALUE`` each, or a bare number for C10."""
    out = {}
    for text in items or ():
        name, value = text.split("=", 1) if "=" in text else ("C10", text)
        name = name.strip()
        if name in out:
            raise PriorError(f"--truth {text!r}: {name} is given twice")
        out[name] = _number(value.strip(), f"--truth {text!r}")
    return out


def paper_prior(mean: float, std: float, E_fiber: float = E_FIBER) -> ParameterSet:
    """The paper's one-parameter prior: C10 lognormal, E_fiber fixed (paper §4)."""
    return ParameterSet((Prior("C10", "lognormal", mean, std),), (("E_fiber", E_fiber),))
