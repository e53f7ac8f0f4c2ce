"""An ensemble of soft blocks bent by a follower pressure: every member in one batched Newton solve.

    python examples/fem_block.py

Three blocks of 16 x 16 x 60 mm, each with its own C10, clamped at the base, their tops held flat
(a rigid face), pressed on one side. Prints each member's Newton status and how far its top moved.
"""
import torch

from torchfra import fem
from torchfra.fem.structured import box_mesh

torch.set_default_dtype(torch.float64)  # the FE model works in float64

mesh = box_mesh((16.0, 16.0, 60.0), (2, 2, 6))               # 2 x 2 x 6 Hex20 bricks, lengths in mm
model = fem.Model(mesh)
model.add(fem.Hex20Solid(mesh, fem.NeoHookean()))             # hybrid u-p brick (C3D20H); parameters C10, D1
model.add(fem.FollowerPressure(mesh, "ymin", pressure="P"))   # a follower pressure on the y = 0 face
model.clamp("zmin")                                           # the base is fixed
model.rigid("zmax")                                           # the top moves as one rigid body

# one value per ensemble member: three silicones, the same bulk compliance and pressure (MPa, 1/MPa)
c10 = torch.tensor([0.0050, 0.0056, 0.0062])
params = {"C10": c10, "D1": torch.full((3,), 0.18), "P": torch.full((3,), 2e-4)}

# the load in four steps; every member's Newton iterations run in lockstep
sol = fem.solve(model, params, load_factors=[0.25, 0.5, 0.75, 1.0])
print("displacements:", tuple(sol.u.shape), "(members, load factors, nodes, 3)")

# the rigid top's translation (mm) and rotation vector (rad) at every load factor
t, theta = model.rigid_motion(sol.a)
for m in range(len(c10)):
    print(f"member {m}: C10 = {float(c10[m]):.4f} MPa, {sol.status[m]}, {int(sol.iterations[m])} Newton iterations, "
          f"top moved uy = {float(t[m, -1, 1]):.3f} mm, rotated {float(theta[m, -1].norm()):.4f} rad")
