"""Benchmarks of the finite element core on Hex20 box meshes, for one member and for an ensemble.

    python scripts/bench.py --suite fem --threads 1 --out runs/bench/fem.json
    python scripts/bench.py --suite fem --quick          # smoke test on tiny meshes, < 1 min
    python scripts/bench.py --suite forward --members 10 --threads 1 --out runs/bench/forward.json
    python scripts/bench.py --suite sensitivity --mesh 1 --load-steps 10 --out runs/bench/sensitivity.json
    python scripts/bench.py --suite ensemble --mesh 2 --members 100 --old-members 10 --out runs/bench/ensemble.json
    python scripts/bench.py --suite device --mesh 2 --members 1,10,100 --threads 2 --out runs/bench/device.json

Suite ``ensemble`` (issue "Forward ensembles in minutes"): the old path (full Newton per member) and the new
one (fem.reduced: snapshots, hyper-reduced Newton, check, fallback) side by side on one ensemble, with the
accuracy of every compared member; see ENSEMBLE_DEFINITIONS.

Suite ``forward`` (issue 3, "Performance"): the prior ensemble of torchfra.calibration.forward on the actuator mesh,
one member alone vs. M members in one batched fem.solve; see FORWARD_DEFINITIONS.

Prints one JSON document (``definitions`` in it says what every timing means) and writes it to
``--out``; progress goes to stderr. Measurements that would take long have time budgets: past a
budget a member-chunked measurement stops and is extrapolated linearly in members, and a Newton
solve that would not fit is replaced by a measured batched iteration or an estimate. The JSON
says which (``extrapolated``, ``mode``, ``skipped``). Every available sparse solver backend of
``fem.linsolve`` is measured; MKL (PARDISO) runs with ``--threads`` threads, as torch does.
Timings are only meaningful on a quiet machine: the load averages at start and end are recorded.

One module per suite (:mod:`.fem`, :mod:`.forward`, :mod:`.sensitivity`, :mod:`.ensemble`, :mod:`.device`),
what they share in :mod:`.common` (timing records, the sparse solvers' memory, the bending block), the command
in :mod:`.command`.
"""
from torchfra.cli.bench.command import main

__all__ = ["main"]
