"""Recordings made by CalculiX on the decks torchfra writes (``--generator calculix``): an independent
solver for the same model."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import torch

GENERATORS = ("torchfra", "calculix")


# effects a CalculiX deck of write_inp carries (no history variables, morphs, renamed materials,
# per-segment fiber moduli, or delayed pressures)
CALCULIX_EFFECTS = ("none", "mooney_rivlin", "compressibility", "fiber_stiffness", "gravity", "compliant_base",
                    "pressure_sensor")


CALCULIX_TIMEOUT_S = 7200.0


CALCULIX_DP = 4e-4  # MPa: the largest pressure change of one CalculiX increment


def check_generator(effect: str, generator: str) -> None:
    """Refuse, by name, a generator that does not exist or cannot carry ``effect``."""
    if generator not in GENERATORS:
        raise ValueError(f"unknown generator {generator!r}; generators: {', '.join(GENERATORS)}")
    if generator == "calculix" and effect not in CALCULIX_EFFECTS:
        raise ValueError(f"effect {effect!r} has no CalculiX deck here (write_inp carries "
                         f"{', '.join(CALCULIX_EFFECTS)}); generate it with torchfra")


def _calculix_displacements(model, values: dict, lam: np.ndarray, n_nodes: int, deck_dir: Path, title: str
                            ) -> tuple[np.ndarray, np.ndarray | None]:
    """CalculiX's displacements (K, n_nodes, 3) of the deck of ``model`` at ``values`` (name -> number)
    through the load factors ``lam`` (K,), one increment each, written and run in ``deck_dir``, and the
    reference state (n_nodes, 3) the first step settles a weight acting before the load path into
    (None without one). All are measured from the unloaded body."""
    from torchfra.io.abaqus.write import CalculixError, dat_blocks, run_calculix, write_inp

    deck_dir.mkdir(parents=True, exist_ok=True)
    # increments of at most CALCULIX_DP MPa: its Newton on the rigid top's MPC and the follower
    # pressure fails on larger ones (2-2.5 % of 0.022 MPa converged, README "CalculiX, the actuator")
    steps = np.abs(np.diff(np.concatenate([[0.0], lam]))) * values["P"]
    per_entry = max(1, int(math.ceil(steps.max() / CALCULIX_DP - 1e-9)))
    deck = write_inp(deck_dir / "scenario.inp", model, values, element_type="C3D20R", truss_element="SPRINGA",
                     load_factors=lam, increments_per_entry=per_entry, title=title)
    try:
        run_calculix(deck, threads=torch.get_num_threads(), timeout=CALCULIX_TIMEOUT_S)
    except CalculixError as exc:  # a CalculixError (a RuntimeError): scripts end it in one paragraph
        raise CalculixError(f"CalculiX did not solve the scenario's deck {deck} ({str(exc).splitlines()[0]}); "
                            "choose a lower --pressure (its C3D20R bricks stop near 60 % of 0.022 MPa at "
                            "resolution 2)") from exc
    blocks = dat_blocks(deck.with_suffix(".dat"))
    U_ref, start = None, 0.0
    if model.has_preload:  # step 1 settles the weight (total time 0..1); the trace's step follows it
        first = [b for t, b in blocks if t <= 1.0 + 1e-9]
        if not first:
            raise CalculixError(f"CalculiX printed no reference state (end of step 1) in {deck}")
        U_ref = np.stack([first[-1][i] for i in range(n_nodes)])
        blocks, start = blocks[len(first):], 1.0
    times = np.array([t for t, _ in blocks]) - start
    K = lam.size
    U = np.full((K, n_nodes, 3), np.nan)
    for k in range(K):
        j = int(np.argmin(np.abs(times - (k + 1) / K))) if times.size else 0
        if not times.size or abs(times[j] - (k + 1) / K) > 1e-6:
            raise CalculixError(f"CalculiX printed no displacements at step time {(k + 1) / K:g} (frame {k}) of {deck}")
        block = blocks[j][1]
        U[k] = np.stack([block[i] for i in range(n_nodes)])
    return U, U_ref

