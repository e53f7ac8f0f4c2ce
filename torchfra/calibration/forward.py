"""Offline forward propagation of the prior ensemble through the actuator model (paper Eq. 15).

``Y_fe`` (N members x T frames x P points x 2 components) is what every hierarchical calibration
reuses. The ensemble is solved in member chunks, each one batched ``fem.solve`` call; every
finished chunk is saved under ``runs/<name>/members/`` so a killed run resumes where it stopped.

Prior (paper §4): C10 ~ lognormal with mean 1.1 kappa_t and std 0.2 kappa_t of C10 itself,
kappa_t = 0.005615 MPa. The body is made nearly incompressible with a fixed bulk ratio
K/mu = ``bulk_ratio`` (D1 = 1 / (bulk_ratio C10)), so every member is equally incompressible.


The run folder (checkpoints, locks): :mod:`torchfra.calibration.runfolder`.
"""
from __future__ import annotations

import os
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

from torchfra import fem
from torchfra.actuator.deck import CAMERAS, deck_summary, observed_faces, read_deck
from torchfra.calibration.config import CalibrationConfig, ForwardConfig
from torchfra.calibration.priors import ParameterSet, lognormal_parameters, paper_prior
from torchfra.calibration.runfolder import (
    _check_resume,
    _claim,
    _finished,
    _read_partial,
    _save_solution,
    _why_unreadable,
    _write_partial,
    load_chunk,
)
from torchfra.observation.operator import ObservationOperator, frame_times, interpolate_in_time


def sample_lognormal(n: int, mean: float, std: float, generator: torch.Generator) -> torch.Tensor:
    mu, sigma = lognormal_parameters(mean, std)
    return torch.exp(mu + sigma * torch.randn(n, generator=generator, dtype=torch.float64))




def with_deck(config):
    """``config`` with its deck read: ``inp_digest`` set, ``pressure`` the deck's ``P`` (a deck must
    load its cavity or faces by one pressure, the recording's). Without a deck, ``config`` itself."""
    import dataclasses

    if not config.inp:
        return config
    if not config.parameters:
        raise ValueError(f"--inp {config.inp}: name the uncertain parameters of the deck's model with --param "
                         "NAME=KIND:A,B (e.g. --param C10=lognormal:0.0062,0.0011)")
    values, digest = deck_summary(config.inp)
    bad = sorted(k for k, v in values.items() if not np.isfinite(v))
    if bad:
        raise ValueError(f"--inp {config.inp}: the deck gives {', '.join(bad)} no finite value (NaN or inf in its "
                         "material, section or load cards); correct the deck")
    pset = parameter_set(config)
    unknown = sorted(({*pset.names} | {n for n, _ in pset.fixed}) - set(values))
    if unknown:
        raise ValueError(f"--inp {config.inp}: the deck's model has no parameter {', '.join(unknown)} (its parameters: "
                         f"{', '.join(sorted(values))}); give priors or values of those only")
    if "P" not in values:
        loads = sorted(k for k in values if k.startswith("P_"))
        raise ValueError(f"--inp {config.inp}: the deck has no single pressure load P (found {loads or 'none'}); "
                         "a recording's pressure column drives one pressure: load every face with one *DLOAD magnitude")
    if config.camera not in CAMERAS:
        raise ValueError(f"--camera {config.camera!r}: the camera looks along x ('+x' or '-x'; the recording "
                         "contract observes uy and uz); rotate the deck so its observed face is normal to x")
    return dataclasses.replace(config, inp_digest=digest, pressure=float(values["P"]))


def forward_model(config) -> tuple[fem.Model, dict, dict[str, float] | None]:
    """The FE model of a forward (or calibration) config, its info, and the deck's parameter values
    (None for the paper's actuator)."""
    if not config.inp:
        model, info = parameter_set(config).build_model(config.resolution, config.integration)
        return model, info, None
    model, values, digest = read_deck(config.inp)
    if config.inp_digest and digest != config.inp_digest:
        raise ValueError(f"--inp {config.inp} changed since this run started (digest {digest}, was "
                         f"{config.inp_digest}); use another --name, or delete the run folder")
    trusses = sum(t.dofs.shape[0] for t in model.terms if isinstance(t, fem.Truss))
    info = {"elements": model.mesh.n_elements, "fiber_elements": trusses, "dofs": model.n_red, "deck": str(config.inp),
            "mesh": model.mesh}
    return model, info, values


def observed_surface(config):
    """The observed faces of ``config``'s model as a registration target (DIC points are placed on it)."""
    from torchfra.observation.registration import mesh_face

    model = forward_model(config)[0]
    return mesh_face(model.mesh, faces=observed_faces(model.mesh, config.camera, config.face))


def parameter_set(config) -> ParameterSet:
    """The uncertain and fixed parameters of a forward (or calibration) config."""
    if not config.parameters:
        if config.fixed:
            raise ValueError("fixed parameters need the uncertain ones named too (--param ...)")
        return paper_prior(config.c10_mean, config.c10_std, config.E_fiber)
    return ParameterSet.parse(config.parameters, config.fixed)


def prior_coordinates(config: ForwardConfig) -> torch.Tensor:
    """The members' prior draws in the filters' coordinates, (N, d) (log C10 for the paper's prior)."""
    return parameter_set(config).sample(config.members, torch.Generator().manual_seed(config.seed))


def member_parameters(config: ForwardConfig, base: dict | None = None) -> dict[str, torch.Tensor]:
    """Prior draws and the fixed parameters of every member: every FE model parameter, name -> (N,)
    (``base``: a deck's values, see :meth:`ParameterSet.model_parameters`)."""
    return parameter_set(config).model_parameters(prior_coordinates(config), config.pressure, config.bulk_ratio,
                                                  config.E_fiber, base=base)


def _reduced_model(run_dir: Path, model, snap_records: list[dict], params, snap, load, quiet: bool,
                   rebuild: bool = False):
    """The hyper-reduced model of the run: read from ``reduced_model.npz`` if a worker built it,
    else built from the full-Newton members' states (``snap_records`` of members ``snap``) and saved
    (arrays only, never unpickled). ``rebuild``: build it again from these members (the basis
    enriched by members whose reduced solve failed its check) and replace the file."""
    from torchfra.fem.reduced import HyperReducedModel, build_reduced

    path = run_dir / "reduced_model.npz"
    if path.exists() and not rebuild:
        try:
            with np.load(path, allow_pickle=False) as f:
                hyper = HyperReducedModel.from_arrays(model, {k: f[k] for k in f.files})
        except Exception as exc:
            raise ValueError(f"{path} is not a reduced model this version can read ({_why_unreadable(exc)}); delete it and rerun "
                             "to build it again from the solved snapshot members") from None
        if not quiet:
            print(f"forward ensemble: reusing the reduced model in {path} ({hyper.basis.size} modes)", flush=True)
        return hyper
    states = np.stack([r["states"][0] for r in snap_records])
    # a snapshot that stopped short of full load still brings the load steps it reached
    reached = np.isfinite(states).all(axis=2).any(axis=1)
    if not reached.any():
        return None
    idx = torch.as_tensor(np.asarray(snap)[reached])
    hyper = build_reduced(model, states[reached], {k: v[idx] for k, v in params.items()}, load)
    tmp = path.with_name(f"reduced_model.{os.getpid()}.tmp.npz")  # several workers may rebuild at once
    np.savez(tmp, **hyper.arrays())
    tmp.replace(path)
    return hyper


def _reduction_digest(hyper) -> str:
    """What a reduced batch's checkpoint was solved with: the basis, the sampled blocks, their weights."""
    import hashlib

    h = hashlib.sha256()
    for key, value in sorted(hyper.arrays().items()):
        h.update(key.encode())
        h.update(np.ascontiguousarray(value).tobytes())
    return h.hexdigest()[:32]


def run_forward(config: ForwardConfig, run_dir: str | Path, progress: bool = True) -> dict:
    """Solve every member at ``load_steps`` load factors and observe them at the frame times.

    ``method="reduced"`` (default): the members ``fem.reduced.select_snapshots`` picks are solved in
    full, the others on the hyper-reduced basis of those solutions, each checked by one full Newton
    step and solved in full when the check estimates an error above ``reduced_tol`` mm
    (``fem.reduced``); ``method="full"``: every member by full Newton.
    Returns a dict with the model, observation operator, parameters, per-member solver records and
    ``Y_fe`` (N, frames, P, 2); members already on disk are loaded, not solved again.

    The steps (:class:`_ForwardRun`): the model and the members' spans, the full-Newton members (every
    one, or the snapshots), the reduced members on the snapshots' basis, and the records gathered. A
    member another worker held and left is solved here, and the run starts over from its files.
    """
    if config.method not in ("reduced", "full"):
        raise ValueError(f"forward method must be 'reduced' or 'full', got {config.method!r}")
    run = _ForwardRun(config, Path(run_dir), progress)
    run.solve_full_members()
    if run.config.method == "reduced":
        snap_records = run.wait_for(run.first)
        if snap_records is None:
            run.close_bar()
            return run_forward(run.config, run_dir, progress)
        run.solve_reduced_members(snap_records)
    records = run.wait_for(run.spans)
    if records is None:
        run.close_bar()
        return run_forward(run.config, run_dir, progress)
    return run.gather(records)


class _ForwardRun:
    """One forward run on a run folder, step by step (:func:`run_forward`): its settings, model, members
    and their files, the progress bar, and the torchrun ranks sharing the members."""

    def __init__(self, config: ForwardConfig, run_dir: Path, progress: bool):
        from torchfra.fem.reduced import select_snapshots
        from torchfra.runtime.distributed import ranks

        self.run_dir = run_dir
        self.r = ranks()  # torchrun: members are shared out by rank, not claimed through lock files
        self.progress = progress and self.r.rank == 0
        config = with_deck(config)
        torch.set_num_threads(config.threads)
        self.t0 = time.perf_counter()
        self.model, self.info, base = forward_model(config)
        if config.method == "reduced" and any(t.global_dofs for t in self.model.terms):
            if self.progress:  # a fiber pitch: each member's own fiber embedding, no shared blocks to hyper-reduce
                print("forward ensemble: the model couples each member's dofs its own way (a fiber pitch); every "
                      "member is solved by full Newton", flush=True)
            config = replace(config, method="full")
        self.config = config
        _check_resume(run_dir, config)
        self.mesh = self.model.mesh
        self.operator = ObservationOperator(self.mesh, observed_faces(self.mesh, config.camera, config.face),
                                            points="nodes")
        self.params = member_parameters(config, base)
        self.load = np.arange(1, config.load_steps + 1) / config.load_steps
        self.chunks_dir = run_dir / "members"
        self.chunks_dir.mkdir(exist_ok=True)
        M = config.members
        if config.method == "full":
            self.spans = [(s, min(s + config.chunk, M)) for s in range(0, M, config.chunk)]
            self.first = self.spans
            self.snap = []
        else:  # one file per member: snapshots first, then the reduced members
            self.spans = [(m, m + 1) for m in range(M)]
            self.snap = sorted(select_snapshots(self.params, config.snapshots or None).tolist())
            self.first = [(m, m + 1) for m in self.snap]
        self.path_of = {start: self.chunks_dir / f"chunk_{start:05d}.npz" for start, _ in self.spans}
        self.stop_of = dict(self.spans)
        self.bar, self.phase = None, self.first
        reused = _finished(self.chunks_dir, self.spans)
        if self.progress and reused:
            print(f"forward ensemble: reusing {reused} of {M} members already solved in {self.chunks_dir}", flush=True)
        self.open_bar(self.first, "FE solves" if config.method == "full" else "snapshot members, full Newton")

    # -- progress ------------------------------------------------------------------------------------
    def open_bar(self, span_list, what):
        """One bar per phase (full Newton members, reduced members: their rates differ ~5x, so one
        bar's time left would mislead). initial = members already on disk: the rate, hence the time
        left, comes from members solved in this run only (by this process or any other worker on the
        same folder), never from loading cached ones."""
        self.close_bar()
        self.phase = span_list
        if self.progress:
            from tqdm.auto import tqdm

            total = sum(stop - start for start, stop in span_list)
            self.bar = tqdm(total=total, initial=_finished(self.chunks_dir, span_list), unit="member", smoothing=0,
                            desc=f"forward ensemble, {self.model.n_red} dofs, {what}")

    def tick(self):
        if self.bar is not None:
            self.bar.update(_finished(self.chunks_dir, self.phase) - self.bar.n)

    def close_bar(self):
        if self.bar is not None:
            self.bar.close()

    # -- members and their files ---------------------------------------------------------------------
    def solve_full(self, start, stop, **extra):
        """Members ``start..stop-1`` by full Newton, saved to their chunk file."""
        config = self.config
        chunk_params = {k: v[start:stop] for k, v in self.params.items()}
        t_chunk = time.perf_counter()
        sol = fem.solve(self.model, chunk_params, self.load,
                        fem.NewtonOptions(**{"member_budget": config.newton_budget,
                                             "member_seconds": config.newton_seconds, **config.newton}))
        u = sol.u[:, :, : self.mesh.n_nodes]
        states = {"states": sol.a.numpy()} if config.method == "reduced" else {}
        _save_solution(self.path_of[start], self.operator(u).numpy(), sol.u[:, -1].numpy(), sol,
                       time.perf_counter() - t_chunk, method=np.array(["full"] * (stop - start)), **states, **extra)

    def wait_for(self, span_list):
        """Records of these spans; chunks other workers hold are waited for (a dead worker's lock
        is taken over and the member solved here). None if this process took one over."""
        records = []
        for start, _ in span_list:
            path = self.path_of[start]
            while not path.exists():
                if _claim(path.with_suffix(".lock"), quiet=not self.progress):
                    path.with_suffix(".lock").unlink()
                    return None
                self.tick()  # members other workers finish count as progress too
                time.sleep(2.0)
            records.append(load_chunk(path))
        return records

    def todo(self, starts):
        """torchrun: the spans still to solve, as rank 0's run folder lists them (every rank agrees)."""
        from torchfra.runtime.distributed import broadcast_ints

        return broadcast_ints([s for s in starts if not self.path_of[s].exists()] if self.r.rank == 0 else None,
                              self.r)

    def share(self, solved):
        from torchfra.runtime.distributed import share_files

        share_files([self.path_of[s] for s in solved], [self.r.owner(solved, s) for s in solved], self.r)

    # -- the steps -----------------------------------------------------------------------------------
    def solve_full_members(self):
        """Step 1: the full-Newton members (every member, or the snapshots of the reduced basis), shared
        out by rank (torchrun) or claimed one by one through lock files (workers on one folder)."""
        if self.r.parallel:
            mine = self.todo([start for start, _ in self.first])
            for start in self.r.share(mine):
                self.solve_full(start, self.stop_of[start])
                self.tick()
            self.share(mine)
            return
        for start, stop in self.first:
            path = self.path_of[start]
            if path.exists() or not _claim(path.with_suffix(".lock"), quiet=not self.progress):
                continue  # done, or another worker on the same run folder is solving it
            self.solve_full(start, stop)
            path.with_suffix(".lock").unlink()
            self.tick()

    def reduced_model(self, snap_records, rest):
        """The hyper-reduced model of the snapshots when members are left to solve (rank 0 builds it, the
        other torchrun ranks read its file), None otherwise; and the members left."""
        from torchfra.runtime.distributed import broadcast_ints, share_file

        r, hyper = self.r, None
        left = self.todo(rest) if r.parallel else [m for m in rest if not self.path_of[m].exists()]
        if left:
            if self.progress:
                print("forward ensemble: building the reduced basis and its hyper-reduction", flush=True)
            if r.rank == 0:
                hyper = _reduced_model(self.run_dir, self.model, snap_records, self.params, self.snap, self.load,
                                       quiet=not self.progress)
            if r.parallel and broadcast_ints([int(hyper is not None)] if r.rank == 0 else None, r)[0]:
                share_file(self.run_dir / "reduced_model.npz", r, 0)
                if r.rank != 0:
                    hyper = _reduced_model(self.run_dir, self.model, snap_records, self.params, self.snap, self.load,
                                           quiet=True)
        return hyper, left

    def next_batch(self, queue, i):
        """Up to ``reduced_batch`` members of ``queue`` from ``i`` on that this process takes (torchrun: its
        share; otherwise those not on disk whose lock it gets), and where the queue continues."""
        batch = []
        while i < len(queue) and len(batch) < self.config.reduced_batch:
            m = queue[i]
            i += 1
            if self.r.parallel or (not self.path_of[m].exists()
                                   and _claim(self.path_of[m].with_suffix(".lock"), quiet=not self.progress)):
                batch.append(m)
        return batch, i

    def solve_reduced_batch(self, hyper, batch, digest):
        """One batch of members on the reduced basis, resumed from its checkpoint after the last load step
        it saved; members that pass the check are saved. Returns those to solve in full and the solution."""
        from torchfra.fem.reduced import solve_reduced

        load, redo = self.load, []
        t_batch = time.perf_counter()
        idx = torch.as_tensor(batch)
        partial = self.path_of[batch[0]].with_name(f"batch_{batch[0]:05d}.partial.npz")
        resume = _read_partial(partial, batch, digest, load)
        if resume is not None and self.progress:
            self.bar.write(f"forward ensemble: resuming reduced members {batch} after load step "
                           f"{int(resume['step']) + 1} of {load.size} (saved in {partial.name})")
        rs = solve_reduced(hyper, {k: v[idx] for k, v in self.params.items()}, load, resume=resume,
                           on_step=lambda state: _write_partial(partial, batch, digest, state))
        wall = (time.perf_counter() - t_batch) / len(batch)
        for j, m in enumerate(batch):
            if rs.status[j] != "converged" or not rs.error_estimate[j] <= self.config.reduced_tol:
                redo.append(m)
                continue
            u = rs.u[j : j + 1, :, : self.mesh.n_nodes]
            rec = fem.Solution(load, rs.u[j:j + 1], rs.a[j:j + 1], np.array(["converged"]), np.ones(1),
                               rs.iterations[j:j + 1] + rs.polish[j:j + 1], np.full(1, load.size),
                               np.zeros(1, dtype=int), np.full(1, np.nan), [[]],
                               {k: v / len(batch) for k, v in rs.timings.items()}, None, None)
            _save_solution(self.path_of[m], self.operator(u).numpy(), rs.u[j:j + 1, -1].numpy(), rec, wall,
                           method=np.array(["reduced"]), error_estimate=rs.error_estimate[j:j + 1],
                           full_tangents=rs.full_tangents[j:j + 1])
        partial.unlink(missing_ok=True)  # its members are saved (or go to full Newton next)
        return redo, rs

    def enrich(self, redo, basis_members, basis_records):
        """Greedy enrichment: the members the basis failed join it, and the basis is built again (a prior
        over several parameters needs more snapshots than the first few; each failure shows where)."""
        for m in redo:
            rec = load_chunk(self.path_of[m])
            if "states" in rec:
                basis_members.append(m)
                basis_records.append(rec)
        order = np.argsort(basis_members)
        if self.progress:
            self.bar.write(f"forward ensemble: {len(redo)} member(s) failed the reduced check; the basis now "
                           f"holds {len(basis_members)} full solves, rebuilding it")
        return _reduced_model(self.run_dir, self.model, [basis_records[j] for j in order], self.params,
                              [basis_members[j] for j in order], self.load, quiet=True, rebuild=True)

    def solve_reduced_members(self, snap_records):
        """Step 2 (``method="reduced"``): every other member on the snapshots' basis in batches, those that
        fail the check by full Newton, the basis enriched by them while members are left."""
        rest = [m for m in range(self.config.members) if m not in set(self.snap)]
        hyper, left = self.reduced_model(snap_records, rest)
        basis_members, basis_records = list(self.snap), list(snap_records)
        self.open_bar([(m, m + 1) for m in rest], "reduced members")
        queue = self.r.share(left) if self.r.parallel else rest
        digest, digest_of = "", None
        i = 0
        while i < len(queue):
            batch, i = self.next_batch(queue, i)
            if not batch:
                continue
            redo, rs = batch, None
            if hyper is not None:
                if digest_of is not hyper:  # once per reduction (built again on enrichment)
                    digest, digest_of = _reduction_digest(hyper), hyper
                redo, rs = self.solve_reduced_batch(hyper, batch, digest)
            for m in redo:  # the reduced answer failed its check: Newton on the full model
                self.solve_full(m, m + 1, error_estimate=np.asarray(
                    [np.nan if rs is None else rs.error_estimate[batch.index(m)]]))
            if hyper is not None and redo and any(not self.path_of[m].exists() for m in queue[i:]):
                hyper = self.enrich(redo, basis_members, basis_records)
            for m in batch:
                self.path_of[m].with_suffix(".lock").unlink(missing_ok=self.r.parallel)
            self.tick()
        self.share(left if self.r.parallel else [])

    def gather(self, records) -> dict:
        """Step 3: every member's records into the run's outputs, observed at the frame times."""
        config, load = self.config, self.load
        for spent in self.chunks_dir.glob("batch_*.partial.npz"):  # every member is saved: checkpoints of
            spent.unlink(missing_ok=True)  # batches an earlier stopped run shared out (other ranks, workers) are spent
        if self.bar is not None:
            self.bar.update(self.bar.total - self.bar.n)
            self.bar.close()
        Y_steps = np.concatenate([r["Y"] for r in records])  # (N, S, P, 2) at the load steps
        times = frame_times(config.frames)
        # pressure ramps linearly in normalized time: load factor = t; u = 0 at t = 0
        Y0 = np.zeros_like(Y_steps[:, :1])
        Y_fe = interpolate_in_time(np.concatenate([[0.0], load]), np.concatenate([Y0, Y_steps], axis=1), times,
                                   axis=1)
        cat = {k: np.concatenate([r[k] for r in records]) for k in
               ("status", "load_reached", "iterations", "increments", "cutbacks", "last_residual", "u_last")}
        n_of = [r["status"].size for r in records]
        cat["method"] = np.concatenate([r.get("method", np.array(["full"] * n)) for r, n in zip(records, n_of)])
        cat["error_estimate"] = np.concatenate([r.get("error_estimate", np.full(n, np.nan))
                                                for r, n in zip(records, n_of)])
        timings: dict[str, float] = {}
        for r in records:
            for k, v in r["timings"].items():
                timings[k] = timings.get(k, 0.0) + v
        return {
            "model": self.model, "info": self.info, "operator": self.operator, "params": self.params,
            "load_factors": load, "times": times, "pressure": config.pressure * times, "Y_fe": Y_fe,
            "Y_steps": Y_steps, "history": [h for r in records for h in r["history"]], "timings": timings,
            "wall_s": time.perf_counter() - self.t0, **cat,
        }


# -- the forward run a calibration shares ------------------------------------------------------------

def forward_dir(config: CalibrationConfig, runs_dir) -> Path:
    """Where the forward ensemble of ``config`` is cached: ``<runs>/forward_cache/<settings>/``, shared by
    every calibration run with the same prior, mesh and load (a new recording needs no new FE work)."""
    f = forward_config(config)
    method = "" if f.method == "full" else f"_{f.method}"
    prior = f"_prior{parameter_set(f).key()}" if f.parameters else ""  # the paper's prior keeps its old name
    model = (f"deck{f.inp_digest[:10]}{f.camera}{f.face}" if f.inp else
             f"mesh{f.resolution}")  # a deck's cache is keyed by what it holds, not by its path
    return Path(runs_dir) / "forward_cache" / (f"{model}_N{f.members}_seed{f.seed}_P{f.pressure:g}"
                                               f"_steps{f.load_steps}{method}{prior}")


def forward_config(config: CalibrationConfig) -> ForwardConfig:
    """The forward ensemble's settings (a deck read: its digest and pressure, see ``with_deck``)."""
    return with_deck(ForwardConfig(members=config.members, resolution=config.resolution, seed=config.seed,
                                   pressure=config.pressure, load_steps=config.load_steps, method=config.method,
                                   parameters=list(config.parameters), fixed=list(config.fixed),
                                   inp=config.inp, camera=config.camera, face=config.face))


def truth_values(config: CalibrationConfig) -> dict[str, float]:
    """The synthetic recording's value of every uncertain parameter (C10 from ``truth_c10``, the
    others from ``truth`` or their null value)."""
    pset = parameter_set(forward_config(config))
    given = {"C10": config.truth_c10, **config.truth} if "C10" in pset.names else dict(config.truth)
    Q = pset.values(given, where="truth of the synthetic recording")  # checks every value against its prior
    return {n: float(given[n]) if n in given else float(p.natural(Q[:, j])[0]) for j, (n, p) in
            enumerate(zip(pset.names, pset.priors))}
