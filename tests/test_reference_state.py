"""The reference state: loads that act before a DIC recording's reference image (the body's weight).

A DIC displacement is measured from the reference image, taken with the body already under its
weight. ``fem.Gravity(preload=True)`` settles the body under its weight first
(``Solution.u_reference``); the load path then ramps the other loads with the weight held, and the
recording sees ``u - u_reference``.

References: the equilibrium equations themselves (the settled state is the gravity-only solve; the
final state is the same equilibrium whichever path reaches it) and CalculiX 2.20 on the deck
``write_inp`` writes with two ``*STEP``s (the weight, then the pressure with the weight held), to the
1e-5 relative tolerance of the other CalculiX cross-checks (tests/test_candidates_calculix.py).
"""
import numpy as np
import pytest
import torch

from torchfra import fem
from torchfra.fem.structured import box_mesh
from torchfra.io.abaqus.write import dat_blocks, run_calculix, write_inp

NU = 0.45
CALCULIX_FACE_RULE = 2  # CalculiX's C3D20R face rule (see test_calculix.py)


def d1_for(mu):
    return 2.0 / (2 * mu * (1 + NU) / (3 * (1 - 2 * NU)))


def cantilever(preload: bool, gravity: bool = True) -> fem.Model:
    """4 x 4 x 12 mm block clamped at z = 0, its weight across its axis (-y), a follower pressure on y = 0."""
    mesh = box_mesh((4.0, 4.0, 12.0), (2, 2, 6))
    model = fem.Model(mesh)
    model.add(fem.Hex20Solid(mesh, fem.NeoHookean(), formulation="displacement"))
    model.clamp("zmin")
    if gravity:
        model.add(fem.Gravity(mesh, direction=(0.0, -1.0, 0.0), preload=preload))
    model.add(fem.FollowerPressure(mesh, "ymin", pressure="P", quadrature=CALCULIX_FACE_RULE))
    return model


C10 = 0.05
PARAMS = {"C10": C10, "D1": d1_for(2 * C10), "density": 2e-8, "P": 0.003}


def tensors(values, n=1):
    return {k: torch.full((n,), float(v), dtype=torch.float64) for k, v in values.items()}


def test_settled_reference_is_the_weight_alone_and_the_path_ends_at_the_same_equilibrium():
    sol = fem.solve(cantilever(preload=True), tensors(PARAMS), (0.5, 1.0))
    assert sol.converged.all() and sol.u_reference is not None
    # the reference state: the body under its weight alone (pressure off)
    weight_only = fem.solve(cantilever(preload=False), tensors({**PARAMS, "P": 0.0}), (1.0,))
    u_ref = weight_only.u[0, -1]
    sag = float(u_ref[:, 1].abs().max())
    assert sag > 1.0  # a soft body: the weight bends it by more than a quarter of its thickness
    assert float((sol.u_reference[0] - u_ref).abs().max()) < 1e-8 * sag
    # the end of the path is the equilibrium under weight + pressure, however it is reached
    ramped = fem.solve(cantilever(preload=False), tensors(PARAMS), (1.0,))
    scale = float(ramped.u[0, -1].abs().max())
    assert float((sol.u[0, -1] - ramped.u[0, -1]).abs().max()) < 1e-7 * scale
    # half way, the pressure is half its value and the weight is whole: not the ramped model's state
    half = fem.solve(cantilever(preload=False), tensors({**PARAMS, "P": 0.5 * PARAMS["P"]}), (1.0,))
    assert float((sol.u[0, 0] - half.u[0, -1]).abs().max()) < 1e-7 * scale


def test_zero_density_is_the_model_without_weight():
    p = {**PARAMS, "density": 0.0}
    sol = fem.solve(cantilever(preload=True), tensors(p), (1.0,))
    plain = fem.solve(cantilever(preload=True, gravity=False), tensors({k: v for k, v in p.items() if k != "density"}),
                      (1.0,))
    assert sol.converged.all() and plain.u_reference is None
    assert float(sol.u_reference.abs().max()) == 0.0
    assert float((sol.u[0, -1] - plain.u[0, -1]).abs().max()) < 1e-10 * float(plain.u.abs().max())


def test_members_settle_each_on_their_own():
    """An ensemble: each member settles under its own weight (densities 0, 1e-8, 2e-8)."""
    p = tensors(PARAMS, 3)
    p["density"] = torch.tensor([0.0, 1e-8, 2e-8], dtype=torch.float64)
    sol = fem.solve(cantilever(preload=True), p, (1.0,))
    assert sol.converged.all()
    sags = sol.u_reference[:, :, 1].abs().amax(dim=1)
    assert sags[0] == 0 and 0 < sags[1] < sags[2]
    one = fem.solve(cantilever(preload=True), tensors({**PARAMS, "density": 1e-8}), (1.0,))
    assert float((sol.u[1, -1] - one.u[0, -1]).abs().max()) < 1e-8 * float(one.u.abs().max())


def test_two_step_deck_matches_calculix(tmp_path):
    model = cantilever(preload=True)
    sol = fem.solve(model, tensors(PARAMS), (1.0,))
    deck = write_inp(tmp_path / "settled.inp", model, PARAMS, increments=10, title="weight, then pressure")
    text = deck.read_text()
    assert text.count("*STEP") == 2 and text.index("GRAV") < text.index(", P3,")  # the weight in the first step
    u_end = run_calculix(deck)
    blocks = dat_blocks(deck.with_suffix(".dat"))
    u_ref_ccx = next(u for t, u in blocks if abs(t - 1.0) < 1e-6)
    u_ref_ccx = np.array([u_ref_ccx[i] for i in range(len(u_ref_ccx))])
    u_ref, u = sol.u_reference[0].numpy(), sol.u[0, -1].numpy()
    rel_ref = np.abs(u_ref_ccx - u_ref).max() / np.abs(u_ref).max()
    d_torch, d_ccx = u - u_ref, u_end - u_ref_ccx  # what a DIC recording sees
    rel = np.abs(d_ccx - d_torch).max() / np.abs(d_torch).max()
    print(f"reference {rel_ref:.2e} of {np.abs(u_ref).max():.3g} mm; relative displacement {rel:.2e} of "
          f"{np.abs(d_torch).max():.3g} mm")
    assert np.abs(u_ref).max() > 1.0 and np.abs(d_torch).max() > 1.0
    assert rel_ref < 1e-5 and rel < 1e-5  # measured 3.3e-7 of 1.31 mm and 6.0e-6 of 5.29 mm


@pytest.mark.slow  # minutes of FE work: outside the default run, run by python -m pytest -m slow
def test_diagnosis_sees_the_weight_from_the_settled_state_with_exact_sensitivities():
    """The diagnosis's gravity candidate with the weight before the reference image: a recording made
    that way (points in the reference image, displacements from the sagged state) is reproduced at the
    truth, and dY/dz (implicit differentiation plus the points' motion with the settled state) equals
    central differences of Y. Reference: central differences (error O(h^2), measured below)."""
    from torchfra.diagnosis.model import ActuatorPhysics
    from torchfra.observation.recording import Recording
    from torchfra.scenarios import clean_observations

    c10, density = 0.0062, 4e-10
    arrays, _ = clean_observations("gravity", density, c10, 1, 2.0, 3, "ramp", cache_dir=None)
    grid, _ = clean_observations("none", 0.0, c10, 1, 2.0, 3, "ramp", cache_dir=None)
    shift = np.abs(arrays["points"] - grid["points"]).max()
    assert shift > 0.5  # the points of the reference image sit on the sagged body (mm)
    rec = Recording(np.arange(3), arrays["times"], arrays["recorded"], np.arange(len(arrays["points"])),
                    arrays["points"], arrays["clean"])
    phys = ActuatorPhysics(rec, ("gravity",), 1, 4)
    assert phys.settles
    z = {"C10": float(np.log(c10)), "density": density}
    ev = phys.observe(z)
    assert ev.ok
    scale = np.abs(rec.Z).max()
    assert np.abs(ev.Y - rec.Z).max() < 2e-3 * scale  # the recording at its truth (load steps' Hermite error)
    # at the solve's own load steps (the frames' interpolation in the load factor left out)
    fe = {k: z[k] for k in phys.fe_names}
    u, du_dlam, du, *_ = phys._solve_nodal(fe)
    _, _, J = phys._seen(u, du_dlam, du)
    for name, h in (("density", 5e-12), ("C10", 1e-3)):  # at 2e-11 the truncation error of the difference is 1e-2
        i = phys.fe_names.index(name)
        plus, minus = ({**fe, name: fe[name] + s} for s in (h, -h))
        Yp, Ym = (phys._seen(*phys._solve_nodal(p, values_only=True)[:2], None)[0] for p in (plus, minus))
        fd = (Yp - Ym) / (2 * h)
        err = np.abs(J[..., i] - fd).max() / np.abs(fd).max()
        print(f"dY/d{name}: max |J - central difference| / max |fd| = {err:.2e}")
        assert err < 1e-4  # measured 1.7e-5 (density, h = 5e-12) and 5.2e-7 (log C10)
    # the points' own motion with the settled state is part of dY/d density: without it J is off
    from torchfra.observation.operator import SettledPoints

    pts = SettledPoints(phys.op, phys.mesh.nodes + u[0, : phys.mesh.n_nodes], rec.X)
    i = phys.fe_names.index("density")
    moving = pts.moving_term(u - u[:1], du[0])[..., i]
    still = pts.observe(du - du[:1])[..., i]
    print(f"moving-point term: {np.abs(moving).max() / np.abs(still).max():.3f} of the rest")
    assert np.abs(moving).max() > 0.05 * np.abs(still).max()  # measured 1.44 times the rest
