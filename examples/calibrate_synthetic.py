"""Calibrate C10 from a recording the model made itself, with the four posteriors side by side.

    python examples/calibrate_synthetic.py [RUN_FOLDER]          # default RUN_FOLDER: runs/example_calibration
    TORCHFRA_EXAMPLE_QUICK=1 python examples/calibrate_synthetic.py   # a smoke run: 4 members, 6 frames

The paper's experiment (§4.1) made small: a synthetic recording at C10 = 0.0048 MPa with Gaussian
noise, a forward ensemble of the prior C10 ~ logN(0.0062, 0.0011^2) MPa, and the paper's hierarchical
filter (linear slave), the same with a polynomial slave, and the exact posterior. The run folder gets
summary.json, bands.png, pdfs.png and TensorBoard events (``tensorboard --logdir RUN_FOLDER``); the
forward ensemble is cached beside it (forward_cache/), so a second run starts at the filters.
"""
import os
import sys
from pathlib import Path

import torchfra

run = Path(sys.argv[1] if len(sys.argv) > 1 else "runs/example_calibration")
quick = os.environ.get("TORCHFRA_EXAMPLE_QUICK") == "1"
# members of the prior ensemble, frames of the recording; a low peak pressure and 2 load steps keep
# the smoke run's FE solves short
size = (dict(members=4, frames=6, pressure=0.004, load_steps=2, degree=2, grid=400) if quick
        else dict(members=16, frames=20))

result = torchfra.calibrate(
    None,                 # no recording: a synthetic one at the truth
    truth=0.0048,         # C10 (MPa) of the synthetic recording
    noise=0.05,           # its noise std (mm), known to the filters
    run_dir=run,
    resolution=1,         # the coarsest actuator mesh
    restart=False,        # skip the restart filter (FE re-solves at every step: the costly baseline)
    coverage_seeds=0,     # skip the repeated-noise coverage study
    progress=not quick,
    **size,
)
print(result.summary())

c10 = result.posterior["C10"]
paper = c10.filters["hierarchical"]
print(f"exact: {c10.mean:.6f} +- {c10.std:.2g} MPa; the paper's filter: {paper['mean']:.6f} +- {paper['std']:.2g} MPa, "
      f"{paper['spread_ratio_to_exact']:.1f}x the exact spread")
for name, fig in result.plot().items():   # the same figures, to restyle or save elsewhere
    fig.savefig(run / f"{name}_again.png", dpi=150)
print(f"figures and summary.json in {run}")
