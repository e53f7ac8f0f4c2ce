"""The weight before the reference image: how much of it a DIC recording sees, by the suite's camera.

    python studies/gravity_reference.py [--densities 3.5e-11 1e-10 4e-10 1.1e-9] [--resolution 1]

A DIC recording measures displacements from its reference image, taken with the actuator already
sagging under its weight (``weight="before_reference"``, the model's default). For each density: the
actuator (C10 0.0062 MPa, a 20-frame ramp to 0.022 MPa) settled under its weight, observed the way
the proof suite observes it (uy, uz on the face x = +8 at the shifted 2 mm DIC grid, the points at
their positions in the sagged reference image), against the base model without weight seen at the
same points. Reported per density: the sag (largest reference-state displacement, mm), how far the
grid's points moved in the reference image, and the SNR ||gravity - base|| / 1 mm over frames,
points and components (the proof suite's measure at noise 1 mm), with the FE solves' seconds.
Writes studies/results/study_gravity_reference.json (``--out``).
"""
from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import torch

from torchfra.scenarios import PRESSURE_MAX, clean_observations

C10 = 0.0062


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--densities", type=float, nargs="+", default=[3.5e-11, 1e-10, 4e-10, 1.1e-9],
                   help="densities to measure (t/mm^3; silicone ~1.1e-9)")
    p.add_argument("--resolution", type=int, default=1, help="mesh resolution of the actuator")
    p.add_argument("--frames", type=int, default=20)
    p.add_argument("--out", default="studies/results/study_gravity_reference.json")
    a = p.parse_args(argv)
    torch.set_num_threads(1)
    setting = dict(c10=C10, resolution=a.resolution, spacing=2.0, frames=a.frames, trace="ramp",
                   pressure=PRESSURE_MAX, cache_dir=None)
    grid, _ = clean_observations("none", 0.0, **setting)
    rows = []
    for rho in a.densities:
        t0 = time.perf_counter()
        rec, _ = clean_observations("gravity", rho, **setting)
        base, _ = clean_observations("none", 0.0, **setting, points=rec["points"])
        snr = float(np.linalg.norm(rec["clean"] - base["clean"]))
        moved = float(np.linalg.norm(rec["points"] - grid["points"], axis=1).max())
        rows.append({"density": rho, "snr_noise_1mm": round(snr, 2), "points_moved_max_mm": round(moved, 3),
                     "points": int(len(rec["points"])), "seconds": round(time.perf_counter() - t0, 1)})
        print(f"density {rho:.3g} t/mm^3: points moved up to {moved:.3f} mm in the reference image; SNR {snr:.2f} "
              f"at noise 1 mm ({rows[-1]['seconds']:.0f} s)")
    out = {"command": "python studies/gravity_reference.py " + " ".join(argv or []),
           "setting": {"c10": C10, "resolution": a.resolution, "frames": a.frames, "trace": "ramp",
                       "pressure": PRESSURE_MAX, "spacing_mm": 2.0, "weight": "before_reference"},
           "rows": rows}
    Path(a.out).parent.mkdir(parents=True, exist_ok=True)
    Path(a.out).write_text(json.dumps(out, indent=1) + "\n")
    return out


if __name__ == "__main__":
    main()
