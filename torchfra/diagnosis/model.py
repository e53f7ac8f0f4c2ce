"""The actuator model with any set of candidate physics switched on, seen through a recording.

``ActuatorPhysics`` is the bridge between the FE library and the statistics of the diagnosis: it
names the free parameters (in the coordinates the statistics work in: log for scale parameters),
their priors, null values and admissible ranges, builds the FE model with the candidates switched
on, and evaluates the recording's observations ``Y`` (K frames x P points x (uy, uz)) and their
exact sensitivities ``dY/dz`` (implicit differentiation, :mod:`torchfra.fem.sensitivity`) at any
parameter point.

Frames are tied to the model by their pressure (quasi-static, hyperelastic: DESIGN §6): the model
is solved at ``load_steps`` evenly spaced load levels and each frame is read off by cubic Hermite
interpolation in the load factor, with ``du/dlambda`` from the same factorizations (error O(h^4):
measured below 1e-4 mm at 10 steps, tests/test_physics.py). A pressure sensor's gain and offset act
on that frame-to-load map only (the true pressure is ``gain * recorded + offset``).

Parameters, their coordinates, priors and null values: the registry :mod:`torchfra.actuator.candidates`.

The body's weight (the ``gravity`` candidate) acts before the reference image by default
(``weight="before_reference"``, :data:`torchfra.actuator.geometry.WEIGHT`): the model settles under
it first, the recording's points are positions on the settled body (located there at every parameter
point, :class:`torchfra.observation.operator.SettledPoints`) and ``Y`` is the displacement from the
settled state; ``dY/dz`` then carries the points' own motion with the settled state. ``"with_load"``
ramps the weight with the pressure from the unloaded body instead.

Viscoelasticity (:mod:`torchfra.actuator.history`) acts on the frame-to-load map only, like the pressure
sensor: the body creeps, and each frame is read off the relaxed (elastic) model at its effective
load level. Its parameters need no FE solve of their own (solves are keyed by the parameters the FE
model sees).
"""
from __future__ import annotations

import hashlib
import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from torchfra import fem
from torchfra.actuator.candidates import (
    BULK_RATIO,
    CANDIDATE_PARAMETERS,
    COORDINATES,
    E_FIBER,
    HISTORY_DEPENDENT_CANDIDATES,
    LOAD_MAP_ONLY,
    SECANT_STEPS,
    Coordinate,
    actuator_model,
    null_coordinate,
)
from torchfra.actuator.deck import DeckModel, observed_faces
from torchfra.actuator.geometry import WEIGHT, ActuatorGeometry, build_actuator_model
from torchfra.actuator.history import creep_load, delayed_load, normalized_time
from torchfra.fem.sensitivity import sensitivities
from torchfra.observation.operator import ObservationError, ObservationOperator, SettledPoints, visible_faces
from torchfra.observation.recording import Recording, RecordingError


@dataclass
class Evaluation:
    """Observations of one parameter point: Y (K, P, 2) mm at the recording's frames and points,
    J (K, P, 2, d) = dY/dz in the coordinates of ``names``; ``ok`` False when the solve failed."""

    z: dict[str, float]
    names: list[str]
    Y: np.ndarray
    J: np.ndarray
    ok: bool
    iterations: int
    seconds: float
    reused: bool = False


class ActuatorPhysics:
    """The actuator at ``resolution`` with ``candidates`` switched on, observed at ``rec``'s points.

    ``cache_dir``: where solves are kept (array-only .npz keyed by the model, the load steps and
    the parameter point): a resumed run, or another recording with the same model, reuses them.
    ``weight``: when the ``gravity`` candidate's weight acts (:data:`WEIGHT`; see the module docstring)."""

    def __init__(self, rec: Recording, candidates=(), resolution: int = 1, load_steps: int = 10,
                 cache_dir: str | Path | None = None, newton: dict | None = None, deck: DeckModel | None = None,
                 weight: str = "before_reference"):
        if weight not in WEIGHT:
            raise ValueError(f"weight must be one of {sorted(WEIGHT)}, got {weight!r}")
        self.weight = weight
        unknown = sorted(set(candidates) - set(CANDIDATE_PARAMETERS))
        if unknown:
            raise ValueError(f"unknown candidate physics {unknown}; known: {sorted(CANDIDATE_PARAMETERS)}")
        self.rec = rec
        self.candidates = tuple(sorted(candidates))
        self.resolution, self.load_steps = int(resolution), int(load_steps)
        self.newton = {"stagnation_tol": 1e-6, **(newton or {})}
        self.deck = deck
        material = fem.MooneyRivlin() if "mooney_rivlin" in self.candidates else None
        self.deck_values, self.deck_digest = (None, None) if deck is None else deck.values()
        if deck is None:
            self.model, self.info = actuator_model(self.candidates, self.resolution, weight=weight)
            faces = None
        else:
            self.model, self.info = self._deck_model(material)
            faces = observed_faces(self.model.mesh, deck.camera, deck.face)
        self.model.finalize()
        self.mesh = self.model.mesh
        faces = visible_faces(self.mesh, (1.0, 0.0, 0.0)) if faces is None else faces
        # with the weight before the reference image, the points are positions on the settled body, which
        # the body's own coordinates need not hold: they are checked on it (SettledPoints) once it is solved
        self.settles = self.model.has_preload
        try:
            op = ObservationOperator(self.mesh, faces, points=rec.X, point_ids=rec.point_ids, tol=0.05)
            W = op.weights.tocsr()
        except ObservationError as exc:
            # points off the faces in depth or just beside their outline (as a sagged reference image's are):
            # located by what the camera sees of them, their observed (in-plane) coordinates
            op = ObservationOperator(self.mesh, faces, points=rec.X, point_ids=rec.point_ids, tol=np.inf)
            W = self._in_plane_weights(op, exc)
        self.op = op
        self.W = W[:, :self.mesh.n_nodes] if W.shape[1] > self.mesh.n_nodes else W
        self.cache_dir = None if cache_dir is None else Path(cache_dir)
        self.names = ["C10"] + [p for c in self.candidates for p in CANDIDATE_PARAMETERS[c]]
        # what the FE model sees: solves are keyed and differentiated by these alone, so a candidate
        # on the frame-to-load map (viscoelasticity) shares the base model's solves
        self.fe_names = [n for n in self.names if n not in LOAD_MAP_ONLY]
        self.fe_candidates = tuple(c for c in self.candidates if c not in HISTORY_DEPENDENT_CANDIDATES)
        self._memo: dict[str, tuple] = {}
        self.steps = np.arange(1, self.load_steps + 1) / self.load_steps

    # how far beside its face (in the face's natural coordinates) and off it in depth (a fraction of the
    # observed faces' extent) a recording's point may be located by its in-plane coordinates
    BESIDE_FACE, OFF_FACE_DEPTH = 0.5, 0.1

    def _in_plane_weights(self, op: ObservationOperator, exc: ObservationError):
        """The observation weights of the recording's points located by their observed coordinates on
        the body as it is (:class:`SettledPoints` on the mesh's own nodes); refuses, with the operator's own
        message ``exc``, points farther beside the faces or off them in depth than the class's limits."""
        import scipy.sparse as sp

        pts = SettledPoints(op, self.mesh.nodes, self.rec.X)
        Xf = self.mesh.nodes[op.face_nodes]
        extent = float(np.ptp(Xf.reshape(-1, 3), axis=0).max())
        x = np.einsum("pa,pai->pi", pts.N, self.mesh.nodes[pts.index])
        depth = np.linalg.norm(self.rec.X - x, axis=1)
        bad = np.flatnonzero((pts.offset > self.BESIDE_FACE) | (depth > self.OFF_FACE_DEPTH * extent))
        if self.settles or not bad.size:
            rows = np.repeat(np.arange(len(pts.points)), pts.N.shape[1])
            return sp.csr_matrix((pts.N.ravel(), (rows, pts.index.ravel())), shape=(len(pts.points), op.n_nodes))
        raise RecordingError(f"{self.rec.source}: {exc}")

    def _deck_model(self, material):
        from torchfra.io.abaqus.read import read_inp

        bad = self.deck.available(self.candidates)
        if bad:
            c, why = next(iter(bad.items()))
            raise ValueError(f"candidate {c!r} on the deck {self.deck.path}: {why}")
        model, _ = read_inp(self.deck.path)
        if material is not None:
            from torchfra.fem.transforms import with_material

            with_material(model, material)
        if "gravity" in self.candidates:
            model.add(fem.Gravity(model.mesh, direction=self.deck.gravity, preload=self.weight == "before_reference"))
        return model, {"mesh": model.mesh, "deck": str(self.deck.path)}

    # -- parameters --------------------------------------------------------------------------------
    def coordinate(self, name: str) -> Coordinate:
        """The coordinate of ``name`` for this model: a deck centres C10's and D1's priors on its own
        values and puts the fibers' null at its E_fiber."""
        from dataclasses import replace

        c = COORDINATES[name]
        if self.deck_values is None:
            return c
        v = self.deck_values
        if name == "C10":
            return replace(c, prior_mean=math.log(v["C10"]))
        if name == "D1" and "D1" in v:
            return replace(c, prior_mean=math.log(v["D1"]))
        if name == "E_fiber" and "E_fiber" in v:
            return replace(c, prior_mean=math.log(v["E_fiber"]), null=v["E_fiber"])
        return c

    def coordinates(self) -> list[Coordinate]:
        return [self.coordinate(n) for n in self.names]

    def null_coordinate(self, name: str, c10: float) -> float:
        """The coordinate at which parameter ``name`` switches its candidate off, at C10 = ``c10``."""
        if self.deck_values is not None and name == "D1":
            return math.log(self._deck_d1(c10))
        if self.deck_values is not None and name == "E_fiber":
            return math.log(self.deck_values["E_fiber"])
        return null_coordinate(name, c10)

    def _deck_d1(self, c10):
        """The deck's compressibility at C10 = ``c10``: its K/mu kept (D1 = 0 in the deck: 1/(1000 C10))."""
        v = self.deck_values
        if v.get("D1", 0.0) > 0:
            return v["D1"] * v["C10"] / c10
        return 1.0 / (BULK_RATIO * c10)

    def null_point(self, c10: float) -> dict[str, float]:
        """Every candidate at its null, C10 as given (coordinates)."""
        return {n: (math.log(c10) if n == "C10" else self.null_coordinate(n, c10)) for n in self.names}

    def _natural(self, z: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        return {n: COORDINATES[n].natural(z[n]) for n in z}

    def _pressure_scale(self, nat) -> torch.Tensor:
        """True pressure at load factor 1: the largest true pressure among the frames."""
        p = torch.as_tensor(self.rec.pressure, dtype=torch.float64)
        g = nat.get("pressure_gain", torch.ones(1, dtype=torch.float64))
        o = nat.get("pressure_offset", torch.zeros(1, dtype=torch.float64))
        return (g * p.max() + o).reshape(-1)

    def params_of(self, z: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        """Model parameters (name -> (1,)) of the coordinates ``z``."""
        nat = self._natural(z)
        c10 = nat["C10"].reshape(-1)
        one = torch.ones_like(c10)
        if self.deck_values is None:
            d1, e_fiber = 1.0 / (BULK_RATIO * c10), E_FIBER * one
        else:  # the deck's other values as they are; its K/mu kept as C10 moves
            d1, e_fiber = self._deck_d1(c10), self.deck_values.get("E_fiber", E_FIBER) * one
        p = {"C10": c10, "D1": nat["D1"].reshape(-1) if "D1" in nat else d1,
             "E_fiber": nat["E_fiber"].reshape(-1) if "E_fiber" in nat else e_fiber,
             "P": self._pressure_scale(nat) * one}
        if self.deck_values is not None:
            needed = set(self.model.param_names())
            p = {k: val for k, val in p.items() if k in needed}
            for k, val in self.deck_values.items():
                if k in needed and k not in p:
                    p[k] = float(val) * one
        if "mooney_rivlin" in self.candidates:
            p["C01"] = nat["C01"].reshape(-1)
        if "gravity" in self.candidates:
            p["density"] = nat["density"].reshape(-1)
        if "compliant_base" in self.candidates:
            p["c_n"], p["c_t"] = nat["c_n"].reshape(-1), nat["c_t"].reshape(-1)
        if "cavity_offset" in self.candidates:
            p["delta_y"] = nat["delta_y"].reshape(-1)
        if "fiber_pitch" in self.candidates:
            p["fiber_pitch"] = nat["fiber_pitch"].reshape(-1)
        return p

    def frame_loads(self, z: dict[str, torch.Tensor]) -> torch.Tensor:
        """Load factor of every frame (K,): true pressure / true pressure at load factor 1."""
        nat = self._natural(z)
        p = torch.as_tensor(self.rec.pressure, dtype=torch.float64)
        g = nat.get("pressure_gain", torch.ones(1, dtype=torch.float64))
        o = nat.get("pressure_offset", torch.zeros(1, dtype=torch.float64))
        lam = (g * p + o) / self._pressure_scale(nat)
        if "pressure_lag" in self.candidates:
            lam = delayed_load(lam, normalized_time(self.rec.times), nat["pressure_lag"])
        if "viscoelasticity" in self.candidates:
            lam = creep_load(lam, normalized_time(self.rec.times), nat["g1"], nat["tau1"])
        return lam

    # -- evaluation ----------------------------------------------------------------------------------
    def _key(self, z: dict[str, float]) -> str:
        desc = {"resolution": self.resolution if self.deck is None else f"deck {self.deck_digest}",
                "observed": None if self.deck is None else [self.deck.camera, self.deck.face],
                "candidates": self.fe_candidates, "steps": self.load_steps,
                "pmax": float(np.max(self.rec.pressure)), "newton": self.newton,
                "z": {k: float(f"{v:.15e}") for k, v in sorted(z.items())}}
        if "gravity" in self.fe_candidates:
            desc["weight"] = self.weight
        return hashlib.sha256(json.dumps(desc, sort_keys=True).encode()).hexdigest()[:20]

    def _solve_nodal(self, z: dict[str, float], values_only: bool = False):
        """u and du/dlambda at lambda = 0, steps (S+1, n, 3) and du/dz (S+1, n, 3, d) for ``fe_names``
        (NaN with ``values_only``); iterations. u is measured from the unloaded body: with the weight
        before the reference image, u[0] is the settled reference state. Solves are kept in memory (the last few) and in ``cache_dir``."""
        z = {n: float(z[n]) for n in self.fe_names}
        key = self._key(z)
        if key in self._memo:
            return (*self._memo[key][:-1], True)
        if values_only and key + "_values" in self._memo:
            return (*self._memo[key + "_values"][:-1], True)
        out = self._solve_nodal_uncached(z, key, values_only)
        key = key + "_values" if values_only else key
        if len(self._memo) >= 8:
            self._memo.pop(next(iter(self._memo)))
        self._memo[key] = out
        return out

    def _solve_nodal_uncached(self, z: dict[str, float], key: str, values_only: bool = False):
        path = None if self.cache_dir is None else self.cache_dir / f"solve_{key}.npz"
        if values_only and path is not None and not path.exists():
            path = self.cache_dir / f"solve_{key}_values.npz"
        if path is not None and path.exists():
            with np.load(path, allow_pickle=False) as f:
                return f["u"], f["du_dlam"], f["du"], bool(f["ok"]), int(f["iterations"]), True
        zt = {k: torch.tensor([v], dtype=torch.float64) for k, v in z.items()}
        params = self.params_of(zt)
        sol = fem.solve(self.model, params, self.steps, fem.NewtonOptions(**self.newton))
        n = self.mesh.n_nodes
        d = len(self.fe_names)
        ok = bool(sol.converged[0])
        u = np.zeros((self.load_steps + 1, n, 3))
        du_dlam = np.zeros_like(u)
        du = np.zeros((self.load_steps + 1, n, 3, d))
        if ok:
            # the reference state (lambda = 0: unloaded, or settled under the weight) joins the steps; its
            # du/dlambda is the Euler velocity and its du/dz the settled state's own sensitivity
            u0 = torch.zeros_like(sol.u[:, :1]) if sol.u_reference is None else sol.u_reference[:, None]
            a0 = torch.zeros_like(sol.a[:, :1]) if sol.a_reference is None else sol.a_reference[:, None]
            sol0 = fem.Solution(np.concatenate([[0.0], sol.load_factors]),
                                torch.cat([u0, sol.u], 1), torch.cat([a0, sol.a], 1), sol.status,
                                sol.load_reached, sol.iterations, sol.increments, sol.cutbacks,
                                sol.last_residual, sol.residual_history)
            S = sensitivities(self.model, self.params_of, zt, sol0, names=[] if values_only else self.fe_names)
            u = sol0.u[0, :, :n].numpy()
            du_dlam = S.du_dlambda[0, :, :n].numpy()
            du = np.full_like(du, np.nan) if values_only else S.du[0, :, :n].numpy()
        if path is not None:
            path.parent.mkdir(parents=True, exist_ok=True)
            tmp = path.with_name(path.stem + ".tmp.npz")
            np.savez(tmp, u=u, du_dlam=du_dlam, du=du, ok=ok, iterations=int(sol.iterations[0]))
            tmp.replace(path)
        return u, du_dlam, du, ok, int(sol.iterations[0]), False

    def _seen(self, u: np.ndarray, du_dlam: np.ndarray, du: np.ndarray | None):
        """Y, dY/dlambda (S+1, P, 2) and dY/dz (S+1, P, 2, d) (None without ``du``) at the solve's steps:
        at the recording's fixed points, or, with the weight before the reference image, displacements from
        the settled state at the points located on it (their motion with the settled state in dY/dz)."""
        if not getattr(self, "settles", False):  # (stand-ins built without __init__ have no weight)
            return self._observed(u), self._observed(du_dlam), None if du is None else self._observed(du)
        pts = SettledPoints(self.op, self.mesh.nodes + u[0, : self.mesh.n_nodes], self.rec.X)
        far = np.flatnonzero(pts.offset > 0.05)
        if far.size:
            i = int(far[0])
            raise RecordingError(
                f"{self.rec.source}: point id {self.rec.point_ids[i]} at {np.round(self.rec.X[i], 4).tolist()} mm lies "
                f"off the body settled under its weight ({far.size} of {self.rec.X.shape[0]} points): "
                "the recording's points must be positions in the reference image, on the body as it sags")
        u_rel = u - u[:1]
        Y, dY = pts.observe(u_rel), pts.observe(du_dlam)
        if du is None:
            return Y, dY, None
        J = pts.observe(du - du[:1]) + pts.moving_term(u_rel, du[0])
        return Y, dY, J

    def _observed(self, field: np.ndarray) -> np.ndarray:
        """(S+1, n, 3, ...) nodal fields -> (S+1, P, 2, ...) at the recording's points (uy, uz)."""
        f = field[:, :, 1:3]
        flat = np.moveaxis(f, 1, 0).reshape(f.shape[1], -1)
        return np.moveaxis((self.W @ flat).reshape((self.W.shape[0],) + f.shape[:1] + f.shape[2:]), 0, 1)

    def at_steps(self, z: dict[str, float]) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        """``(load factors (S+1,), Y (S+1, P, 2), dY/dlambda)`` at the solve's own load steps (lambda = 0
        included), None if the solve failed."""
        u, du_dlam, _, ok, _, _ = self._solve_nodal(z)
        if not ok:
            return None
        Y, dY, _ = self._seen(u, du_dlam, None)
        return np.concatenate([[0.0], self.steps]), Y, dY

    def observe(self, z: dict[str, float], values_only: bool = False) -> Evaluation:
        """Y and dY/dz at the recording's frames and points for coordinates ``z`` (every name);
        ``values_only``: Y alone (J NaN), without the parameter sensitivities' cost."""
        import time

        missing = sorted(set(self.names) - set(z))
        if missing:
            raise ValueError(f"parameters {missing} have no value; the model's parameters are {self.names}")
        t0 = time.perf_counter()
        z = {n: float(z[n]) for n in self.names}
        u, du_dlam, du, ok, its, reused = self._solve_nodal(z, values_only=True) if values_only else self._solve_nodal(z)
        K, P, d = self.rec.n_frames, self.W.shape[0], len(self.names)
        if not ok:
            return Evaluation(z, list(self.names), np.full((K, P, 2), np.nan), np.full((K, P, 2, d), np.nan), False,
                              its, time.perf_counter() - t0, reused)
        Ys, dYs, Jfe = self._seen(u, du_dlam, du)
        Js = np.zeros(Jfe.shape[:-1] + (d,))
        Js[..., [self.names.index(n) for n in self.fe_names]] = Jfe
        zt = {k: torch.tensor([v], dtype=torch.float64) for k, v in z.items()}
        lam = self.frame_loads(zt).numpy()
        dlam = np.stack([_derivative(self.frame_loads, zt, n) for n in self.names], axis=1)  # (K, d)
        s = np.concatenate([[0.0], self.steps])
        lam_c = np.clip(lam, 0.0, 1.0)
        i = np.clip(np.searchsorted(s, lam_c, side="right") - 1, 0, s.size - 2)
        h = s[i + 1] - s[i]
        t = (lam_c - s[i]) / h
        h00, h10, h01, h11 = 2 * t**3 - 3 * t**2 + 1, t**3 - 2 * t**2 + t, -2 * t**3 + 3 * t**2, t**3 - t**2
        e = (slice(None), None, None)
        Y = h00[e] * Ys[i] + (h * h10)[e] * dYs[i] + h01[e] * Ys[i + 1] + (h * h11)[e] * dYs[i + 1]
        # dY/dlambda of the Hermite cubic, for the frames' load factors that move with the sensor parameters
        g00, g10, g01, g11 = (6 * t**2 - 6 * t) / h, 3 * t**2 - 4 * t + 1, (-6 * t**2 + 6 * t) / h, 3 * t**2 - 2 * t
        dY = g00[e] * Ys[i] + g10[e] * dYs[i] + g01[e] * Ys[i + 1] + g11[e] * dYs[i + 1]
        J = (1 - t)[:, None, None, None] * Js[i] + t[:, None, None, None] * Js[i + 1] + dY[..., None] * dlam[:, None, None, :]
        for name, step in SECANT_STEPS.items():
            if name in self.names and not values_only:
                J[..., self.names.index(name)] = self._secant(z, name, step, Y)
        return Evaluation(z, list(self.names), Y, J, True, its, time.perf_counter() - t0, reused)

    @property
    def solves_per_observation(self) -> int:
        """FE solves an observation with sensitivities costs: one, and two more per secant parameter."""
        return 1 + 2 * sum(1 for n in SECANT_STEPS if n in self.names)

    def _secant(self, z: dict[str, float], name: str, step: float, Y: np.ndarray) -> np.ndarray:
        """dY/dz[name] as the central secant over +-``step`` (one-sided at the admissible range's end or
        where a side does not converge; NaN when neither does)."""
        c = COORDINATES[name]
        sides = {}
        for h in (step, -step):
            zh = c.clip(z[name] + h)
            if zh != z[name]:
                ev = self.observe({**z, name: zh}, values_only=True)
                if ev.ok:
                    sides[zh] = ev.Y
        if len(sides) == 2:
            (a, Ya), (b, Yb) = sides.items()
            return (Ya - Yb) / (a - b)
        if len(sides) == 1:
            (a, Ya), = sides.items()
            return (Ya - Y) / (a - z[name])
        return np.full(Y.shape, np.nan)


def _derivative(fn, z: dict[str, torch.Tensor], name: str) -> np.ndarray:
    import torch.autograd.forward_ad as fwAD

    with fwAD.dual_level():
        zz = {k: fwAD.make_dual(v, torch.ones_like(v)) if k == name else v for k, v in z.items()}
        out = fwAD.unpack_dual(fn(zz))
        return np.zeros(out.primal.shape) if out.tangent is None else out.tangent.numpy().copy()


def prehistory(t: np.ndarray, lam: np.ndarray) -> tuple[float, bool]:
    """What the body went through before a recording's first frame (normalized times ``t``, load
    factors ``lam``): a recording that starts part-way up a ramp (first load > 0 and rising) is taken
    to have started from rest, unloaded, on the first segment's ramp extended back to zero load:
    returns (that start time, True); any other (starting unloaded, at a hold, or coming down) is
    taken relaxed under its first frame's load: (t[0], False)."""
    if t.size > 1 and lam[0] > 0 and lam[1] > lam[0]:
        slope = (lam[1] - lam[0]) / (t[1] - t[0])
        return float(t[0] - lam[0] / slope), True
    return float(t[0]), False


class HistoryPhysics:
    """The creeping body of the ``viscoelasticity`` candidate with history variables in its element
    kernel (``fem.viscoelastic``), seen through a recording: the FE model the load-level
    approximation of :class:`ActuatorPhysics` stands in for (it misses 5-8 % of the effect on the
    actuator, ``studies/viscoelastic.py``). Same interface as ``ActuatorPhysics`` for the
    parameters ``C10, g1, tau1`` (coordinates: log, linear, log; tau1 in units of the recording's
    duration). Before the first frame: see :func:`prehistory` (a recording that starts part-way up a
    ramp started from rest; measured on the suite's g1 = 0.4 recording, which starts at 10 % of its
    largest pressure 0.05 after rest: taking the body relaxed there instead left a loop at the
    lowest unloading pressures, directional z 3.6 and 2.7).

    Each observation marches the FE model through the recording's frames in steps of at most 0.1 in
    load factor and ``dt_fraction`` tau1 in time, the latter waived for steps of at most
    ``dt_free_dlam`` in load factor (``fem.viscoelastic.time_increments``: the history's recurrence
    is exact for a stress linear in time, however long the step against tau1;
    ``studies/history_steps.py`` measured what the waiver costs in accuracy). Its
    sensitivities are forward differences (one march per parameter): ``1 + 3`` marches per
    evaluation, each kept in ``cache_dir``."""

    STEPS = {"C10": 1e-4, "g1": 1e-4, "tau1": 1e-3}  # forward-difference steps in the coordinates

    def __init__(self, rec: Recording, resolution: int = 1, cache_dir=None, deck: DeckModel | None = None,
                 dt_fraction: float = 0.5, newton: dict | None = None, dt_free_dlam: float | None = 0.025):
        self.base = ActuatorPhysics(rec, ("viscoelasticity",), resolution, 2, None, newton, deck)
        self.rec, self.deck, self.resolution = rec, deck, int(resolution)
        self.names = list(self.base.names)  # C10, g1, tau1
        self.dt_fraction = float(dt_fraction)
        self.dt_free_dlam = None if dt_free_dlam is None else float(dt_free_dlam)
        self.newton = {"stagnation_tol": 1e-6, **(newton or {})}
        self.cache_dir = None if cache_dir is None else Path(cache_dir)
        if deck is None:
            self.model, _ = build_actuator_model(ActuatorGeometry(resolution=self.resolution))
        else:
            from torchfra.io.abaqus.read import read_inp

            self.model, _ = read_inp(deck.path)
        fem.with_viscoelasticity(self.model)
        self.model.finalize()
        self.n_nodes = self.base.mesh.n_nodes
        self.marches = 0
        self._memo: dict[str, np.ndarray | None] = {}

    def coordinate(self, name: str) -> Coordinate:
        return self.base.coordinate(name)

    def null_coordinate(self, name: str, c10: float) -> float:
        return self.base.null_coordinate(name, c10)

    def _key(self, z: dict[str, float]) -> str:
        desc = {"model": "actuator" if self.deck is None else f"deck {self.base.deck_digest}",
                "resolution": self.resolution, "observed": None if self.deck is None else [self.deck.camera, self.deck.face],
                "times": np.asarray(self.rec.times, dtype=float).tolist(),
                "pressure": np.asarray(self.rec.pressure, dtype=float).tolist(), "dt": self.dt_fraction,
                "dt_free_dlam": self.dt_free_dlam,
                "prehistory": "ramp from rest, else relaxed at the first frame",
                "newton": self.newton, "z": {k: float(f"{v:.15e}") for k, v in sorted(z.items())}}
        return hashlib.sha256(json.dumps(desc, sort_keys=True).encode()).hexdigest()[:20]

    def march(self, z: dict[str, float]) -> np.ndarray | None:
        """Y (K, P, 2) at the recording's frames for coordinates ``z``, None if the march failed."""
        key = self._key(z)
        if key in self._memo:
            return self._memo[key]
        path = None if self.cache_dir is None else self.cache_dir / f"history_{key}.npz"
        if path is not None and path.exists():
            with np.load(path, allow_pickle=False) as f:
                Y = f["Y"] if bool(f["ok"]) else None
            self._memo[key] = Y
            return Y
        zt = {k: torch.tensor([v], dtype=torch.float64) for k, v in z.items()}
        params = self.base.params_of(zt)
        nat = self.base._natural(zt)
        params["g1"], params["tau1"] = nat["g1"].reshape(-1), nat["tau1"].reshape(-1)
        lam = self.base.frame_loads({**zt, "g1": torch.zeros(1, dtype=torch.float64)}).numpy()  # the pressures'
        t = normalized_time(self.rec.times)
        start, ramp = prehistory(t, lam)
        options = fem.NewtonOptions(**self.newton)
        max_dt = self.dt_fraction * float(nat["tau1"])
        if ramp:  # from rest, up the first segment's ramp extended back to zero pressure
            sol = fem.solve_history(self.model, params, t, lam, max_dt=max_dt, options=options, t0=start,
                                    dt_free_dlam=self.dt_free_dlam)
        else:  # relaxed under the first frame's pressure
            sol = fem.solve_history(self.model, params, t[1:], lam[1:], max_dt=max_dt, options=options,
                                    t0=float(t[0]), relaxed_at=float(lam[0]), dt_free_dlam=self.dt_free_dlam)
        self.marches += 1
        ok = bool(sol.converged[0])
        Y = None
        if ok:
            u = sol.u if ramp else torch.cat([sol.u_start[:, None], sol.u], dim=1)
            Y = self.base._observed(u[0, :, : self.n_nodes].numpy())  # (K, P, 2)
        if path is not None:
            path.parent.mkdir(parents=True, exist_ok=True)
            tmp = path.with_name(path.stem + ".tmp.npz")
            np.savez(tmp, Y=Y if ok else np.zeros(0), ok=ok)
            tmp.replace(path)
        self._memo[key] = Y
        return Y

    def observe(self, z: dict[str, float]) -> Evaluation:
        import time

        t0 = time.perf_counter()
        z = {n: float(z[n]) for n in self.names}
        Y = self.march(z)
        K, P, d = self.rec.n_frames, self.base.W.shape[0], len(self.names)
        if Y is None:
            return Evaluation(z, list(self.names), np.full((K, P, 2), np.nan), np.full((K, P, 2, d), np.nan), False,
                              0, time.perf_counter() - t0)
        J = np.zeros((K, P, 2, d))
        for i, n in enumerate(self.names):
            c = self.coordinate(n)
            h = self.STEPS[n] if z[n] + self.STEPS[n] == c.clip(z[n] + self.STEPS[n]) else -self.STEPS[n]
            Yh = self.march(z | {n: z[n] + h})
            if Yh is None:
                return Evaluation(z, list(self.names), Y, np.full((K, P, 2, d), np.nan), False, 0,
                                  time.perf_counter() - t0)
            J[..., i] = (Yh - Y) / h
        return Evaluation(z, list(self.names), Y, J, True, 0, time.perf_counter() - t0)
