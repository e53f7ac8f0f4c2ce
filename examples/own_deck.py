"""Your own model from an Abaqus/CalculiX deck: read it and solve an ensemble of it in one batched call.

    python examples/own_deck.py [DECK]     # default: writes a small stand-in deck, runs/example_deck/block.inp

Any deck within what the reader supports (docs/own_deck.md) works: C3D20(H/R) bricks, T3D2/T3D3 trusses,
``*HYPERELASTIC, NEO HOOKE``, ``*DSLOAD`` pressures, ``*BOUNDARY``, ``*RIGID BODY``, embedded fibers.
Without a deck, a clamped block pressed on one side is written with ``write_inp`` first. The same deck
runs in every command with ``--inp DECK`` (``torchfra forward``, ``calibrate``, ``diagnose``).
"""
import sys
from pathlib import Path

import torch

from torchfra import fem
from torchfra.fem.structured import box_mesh
from torchfra.io.abaqus import read_inp, write_inp

torch.set_default_dtype(torch.float64)

if len(sys.argv) > 1:
    deck = Path(sys.argv[1])
else:  # a stand-in for your deck: the block of fem_block.py, written as Abaqus would read it
    deck = Path("runs/example_deck/block.inp")
    deck.parent.mkdir(parents=True, exist_ok=True)
    mesh = box_mesh((16.0, 16.0, 60.0), (2, 2, 6))
    block = fem.Model(mesh)
    block.add(fem.Hex20Solid(mesh, fem.NeoHookean()))
    block.add(fem.FollowerPressure(mesh, "ymin", pressure="P"))
    block.clamp("zmin")
    write_inp(deck, block, {"C10": 0.0056, "D1": 0.18, "P": 2e-4}, element_type="C3D20H")

model, values = read_inp(deck)        # an unfinalized model and the deck's parameter values
print(f"{deck}: parameters {values}")

# an ensemble around the deck's own values: C10 from 0.9x to 1.1x, everything else as the deck has it
n = 3
scale = torch.linspace(0.9, 1.1, n)
params = {k: torch.full((n,), float(v)) for k, v in values.items()}
params["C10"] = params["C10"] * scale
sol = fem.solve(model, params, load_factors=[0.5, 1.0])
tip = sol.u[:, -1, : model.mesh.n_nodes].norm(dim=-1).max(dim=-1).values   # largest displacement per member
for m in range(n):
    print(f"member {m}: C10 = {float(params['C10'][m]):.5f} MPa, {sol.status[m]}, largest displacement "
          f"{float(tip[m]):.3f} mm")
