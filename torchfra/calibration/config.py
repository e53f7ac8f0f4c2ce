"""The settings of a calibration run (:class:`CalibrationConfig`, :data:`SEED`: the paper's experiment), the
forward run it shares, and their fingerprints (what makes a cached forward ensemble or restart run reusable)."""
from __future__ import annotations

import hashlib
import json
from dataclasses import asdict, dataclass, field

import numpy as np

from torchfra.actuator.candidates import BULK_RATIO, E_FIBER, KAPPA_T
from torchfra.observation.recording import Recording


@dataclass
class ForwardConfig:
    """Settings of a forward ensemble (units mm, MPa)."""

    members: int = 100
    resolution: int = 2
    integration: str = "full"
    seed: int = 0
    c10_mean: float = 1.1 * KAPPA_T
    c10_std: float = 0.2 * KAPPA_T
    bulk_ratio: float = BULK_RATIO
    E_fiber: float = E_FIBER
    pressure: float = 0.022
    load_steps: int = 20
    frames: int = 100
    chunk: int = 1  # members per batched solve and checkpoint (batching gains nothing: 0.92x measured)
    threads: int = 1
    # min_increment: a member that cannot advance 0.1 % of the load is at its limit point and stops
    # there, flagged (the load steps are 5 % apart; halving further to 1e-5 only located the limit
    # more finely, at the cost of 1.75x the member's Newton iterations: 196 against 112 for member 48
    # of the paper's prior at resolution 1, which stops at 95 % either way)
    newton: dict = field(default_factory=lambda: {"stagnation_tol": 1e-6, "min_increment": 1e-3})
    method: str = "reduced"  # "reduced": a few members in full, the rest on their basis (fem.reduced); "full"
    snapshots: int = 0  # members solved in full for the basis (0: 1 + 2 x varying parameters, at least 3)
    reduced_tol: float = 5e-4  # mm: a reduced member whose check estimates more is solved in full
    # reduced members per batched solve: 8 took 3.6 s per member against 4.0-4.3 s with 4 (the
    # 3-parameter actuator prior at resolution 1, 16 members, 1 thread; 16: 3.5 s); a stopped run
    # loses at most one batch
    reduced_batch: int = 8
    newton_budget: int = 500  # Newton iterations one member may spend (a full-Newton member took 80-230
    # at resolution 1, the hopeless one included); a member that spends them stops, flagged
    newton_seconds: float = 0.0  # wall seconds a full-Newton solve may take per member (0: no limit; a
    # member at resolution 1 takes 7-20 s alone); one still solving then stops, flagged. Machine-dependent:
    # a budget in iterations (newton_budget) gives the same answer everywhere
    # any parameter set (torchfra.calibration.priors): prior specs "NAME=KIND:A,B" and fixed "NAME=VALUE"; empty:
    # the paper's prior, C10 lognormal (c10_mean, c10_std) with E_fiber fixed
    parameters: list = field(default_factory=list)
    fixed: list = field(default_factory=list)
    # the user's own model: an Abaqus/CalculiX deck (torchfra.io.read_inp) instead of the paper's
    # actuator; its parameters keep the deck's values unless given a prior or a fixed value, ``P`` is
    # the deck's pressure (``pressure`` then is that value), ``inp_digest`` what the deck held when
    # the run started (a changed deck, includes too, is another run)
    inp: str = ""
    inp_digest: str = ""
    # which side the camera looks from: "+x" (the actuator's front face) or "-x"; the recording
    # contract observes uy and uz, so a deck is oriented with its camera on the x axis
    camera: str = "+x"
    face: str = ""  # a deck's *SURFACE to observe instead of every face the camera sees


@dataclass
class CalibrationConfig:
    """Settings of a calibration run (units mm, MPa). ``recording`` None makes a synthetic one at
    ``truth_c10`` with noise N(0, noise^2) per component (the paper's experiment)."""

    members: int = 100
    resolution: int = 1
    seed: int = 0
    recording: str | None = None
    truth_c10: float = 0.0048
    noise: float = 1.0
    noise_seed: int = 1
    points: str = "nodes"  # synthetic recordings: "nodes" or a DIC grid spacing in mm, e.g. "2.0"
    frames: int = 100
    filter_seed: int = 2
    degree: int | str = "auto"  # polynomial slave: a degree, or "auto" (smallest leave-one-out error)
    restart: bool = True
    restart_every: int = 10
    coverage_seeds: int = 20
    grid: int = 4000
    pressure: float = 0.022  # MPa at t = 1 of the synthetic recording; the forward ensemble's range
    load_steps: int = 20
    method: str = "reduced"  # how the forward ensemble's members are solved (ForwardConfig.method)
    # any parameter set (torchfra.calibration.priors): prior specs "NAME=KIND:A,B" and fixed "NAME=VALUE" (empty:
    # the paper's prior of C10); ``truth``: values of the synthetic recording's uncertain parameters
    # other than C10 (``truth_c10``), a missing one at its null value
    parameters: list = field(default_factory=list)
    fixed: list = field(default_factory=list)
    truth: dict = field(default_factory=dict)
    # the hierarchical filters assimilate every n-th frame (the last included); 1: every frame, the
    # paper's. Fewer sequential updates keep the ensemble's spread along a weakly constrained
    # direction (studies/assimilation_stride.py); they are compared with the exact posterior
    # on the same frames
    assimilate_every: int = 1
    # the user's own model (torchfra.calibration.forward.ForwardConfig): an Abaqus/CalculiX deck, the camera's
    # side and the observed surface; ``pressure`` is then the deck's
    inp: str = ""
    camera: str = "+x"
    face: str = ""


SEED = CalibrationConfig()  # --config seed: the paper's numerical experiment (§4.1)








def recording_digest(rec: Recording) -> str:
    """Fingerprint of a recording's content (checkpoints must not resume against other data)."""
    h = hashlib.sha256()
    for a in (rec.frames, rec.times, rec.pressure, rec.point_ids, rec.X, rec.Z):
        h.update(np.ascontiguousarray(a).tobytes())
    if rec.ragged:
        h.update(b"slots" + np.ascontiguousarray(rec.slots).tobytes())
    return h.hexdigest()


def config_dict(config: CalibrationConfig) -> dict:
    return json.loads(json.dumps(asdict(config)))


FILTERS = ("hierarchical", "hierarchical_nonlinear", "restart", "exact")

