"""Candidate terms against CalculiX on the block of ``test_calculix.py`` (displacement-only bricks).

Reference: CalculiX 2.20 (``ccx``) solving the deck ``torchfra.io.abaqus.write_inp`` writes for the
very model torchfra solves: ``*HYPERELASTIC, MOONEY-RIVLIN`` (the same energy as ``MooneyRivlin``),
``*DENSITY`` with ``*DLOAD ..., GRAV`` (a dead body load, as ``Gravity``), and ``SPRING1`` /
``SPRING2`` scalar springs storing exactly the discrete energy of ``ElasticSupport``. Both codes
discretize one problem, so they must agree to solver tolerance; CalculiX prints 7 digits, so about
1e-7 of max |u| is the floor. Bound 1e-5, as for the Neo-Hookean check.
"""
import numpy as np
import pytest
import torch
from helpers import block_with_cavity

from torchfra import fem
from torchfra.fem.structured import box_mesh
from torchfra.io.abaqus.write import run_calculix, write_inp

LENGTH = 12.0
NU = 0.45  # small-strain Poisson ratio, as in test_calculix.py
TOLERANCE = 1e-5
CALCULIX_FACE_RULE = 2  # CalculiX's C3D20R face rule (see test_calculix.py)


def d1_for(mu):
    """D1 = 2 / K with K = 2 mu (1 + nu) / (3 (1 - 2 nu))."""
    return 2.0 / (2 * mu * (1 + NU) / (3 * (1 - 2 * NU)))


def block(material=None, clamp=True) -> fem.Model:
    """4 x 4 x 12 mm block, 2 x 2 x 6 displacement-only Hex20 bricks."""
    mesh = box_mesh((4.0, 4.0, LENGTH), (2, 2, 6))
    model = fem.Model(mesh)
    model.add(fem.Hex20Solid(mesh, material or fem.NeoHookean(), formulation="displacement"))
    if clamp:
        model.clamp("zmin")
    return model


def compare(model, params, tmp_path, name):
    sol = fem.solve(model, {k: torch.tensor([v]) for k, v in params.items()}, (1.0,))
    assert sol.converged.all(), sol.status
    u_torch = sol.u[0, -1].numpy()
    deck = write_inp(tmp_path / f"{name}.inp", model, params, increments=10, title=f"candidates {name}")
    u_ccx = run_calculix(deck)
    assert u_ccx.shape == u_torch.shape
    scale = np.abs(u_torch).max()
    rel = np.abs(u_ccx - u_torch).max() / scale
    print(f"{name}: max |u| = {scale:.4g} mm, max |u_torchfra - u_ccx| / max |u| = {rel:.3e}")
    return rel, scale, deck.read_text()


def test_mooney_rivlin_bending_matches_calculix(tmp_path):
    model = block(fem.MooneyRivlin())
    model.add(fem.FollowerPressure(model.mesh, "ymin", pressure="P", quadrature=CALCULIX_FACE_RULE))
    C10, C01 = 0.06, 0.04  # mu = 0.2 MPa as in test_calculix.py, 40 % of it from the second invariant
    rel, scale, deck = compare(model, {"C10": C10, "C01": C01, "D1": d1_for(2 * (C10 + C01)), "P": 0.006},
                               tmp_path, "mooney_rivlin")
    assert "*HYPERELASTIC, MOONEY-RIVLIN" in deck
    assert scale > 0.3 * LENGTH  # strongly nonlinear bending
    assert rel < TOLERANCE, f"max |u_torchfra - u_ccx| / max |u| = {rel:.3e}"  # measured 1.1e-7 of 5.49 mm


def test_gravity_sag_matches_calculix(tmp_path):
    """A soft cantilever bending under its own weight (gravity across its axis)."""
    model = block()
    model.add(fem.Gravity(model.mesh, direction=(0.0, 1.0, 0.0)))
    C10 = 0.02
    rel, scale, deck = compare(model, {"C10": C10, "D1": d1_for(2 * C10), "density": 2e-8}, tmp_path, "gravity")
    assert "*DENSITY" in deck and "SOLID0, GRAV, 9810.0, 0.0, 1.0, 0.0" in deck
    assert scale > 0.15 * LENGTH
    assert rel < TOLERANCE, f"max |u_torchfra - u_ccx| / max |u| = {rel:.3e}"  # measured 3.8e-7 of 3.33 mm


def test_elastic_support_matches_calculix_springs(tmp_path):
    """The bending block of test_calculix.py standing on distributed springs instead of the clamp."""
    model = block(clamp=False)
    model.add(fem.ElasticSupport(model.mesh, "zmin"))
    model.add(fem.FollowerPressure(model.mesh, "ymin", pressure="P", quadrature=CALCULIX_FACE_RULE))
    C10 = 0.1
    params = {"C10": C10, "D1": d1_for(2 * C10), "P": 0.006, "c_n": 1.0, "c_t": 2.0}
    rel, scale, deck = compare(model, params, tmp_path, "springs")
    assert "TYPE=SPRING1" in deck and "TYPE=SPRING2" in deck
    assert rel < TOLERANCE, f"max |u_torchfra - u_ccx| / max |u| = {rel:.3e}"  # measured 3.3e-7 of 6.90 mm
    sol = fem.solve(model, {k: torch.tensor([v]) for k, v in params.items()}, (1.0,))
    base = sol.u[0, -1, model.mesh.node_sets["zmin"]]
    assert base.abs().max() > 0.02 * scale  # the base moves (0.26 mm of 6.9 mm): the springs matter


def test_spring_cards_store_the_support_energy():
    """The SPRING1/SPRING2 decomposition reproduces u^T K u / 2 of the term for random u (1e-13)."""
    from torchfra.io.abaqus.candidates import support_springs

    mesh = box_mesh((2.0, 3.0, 1.0), (2, 3, 1), distortion=0.2)
    term = fem.ElasticSupport(mesh, "zmin")
    values = {"c_n": 0.7, "c_t": 3.0}
    grounded, pairs = support_springs(term, values)
    assert min(k for _, _, k in grounded) < 0  # Quad8 corner weights are negative
    rng = np.random.default_rng(0)
    u = rng.normal(size=(mesh.n_nodes, 3))
    springs = sum(0.5 * k * u[n, c] ** 2 for n, c, k in grounded)
    springs += sum(0.5 * k * (u[a, c] - u[b, c]) ** 2 for a, b, c, k in pairs)
    W = term.evaluate(torch.as_tensor(u)[None], {k: torch.tensor([v]) for k, v in values.items()},
                      torch.ones(1), tangent=False, energy=True).energy
    assert abs(springs - float(W[0])) < 1e-13 * abs(springs)  # measured 6.7e-16


def test_candidate_deck_cards_and_errors(tmp_path):
    cavity = block_with_cavity()
    model = fem.Model(cavity)
    model.add(fem.Hex20Solid(cavity, fem.NeoHookean(), formulation="displacement"))
    model.add(fem.SensorCavityPressure(cavity, "cavity"))
    model.clamp("zmin")
    deck = write_inp(tmp_path / "sensor.inp", model, {"C10": 0.1, "D1": 1.0, "P": 0.01, "pressure_gain": 1.5,
                                                        "pressure_offset": 0.002}).read_text()
    assert deck.count(", 0.017") == 6  # the true pressure 1.5 * 0.01 + 0.002 on the six cavity faces

    mesh = box_mesh((4.0, 4.0, LENGTH), (2, 2, 6))
    model = block()
    model.add(fem.Gravity(mesh, elements=np.arange(5)))
    with pytest.raises(NotImplementedError, match="covers part of solid term 0"):
        write_inp(tmp_path / "bad.inp", model, {"C10": 0.1, "D1": 1.0, "density": 1e-9})
    turned = fem.Mesh(mesh.nodes @ fem.rotation_matrix(torch.tensor([0.3, 0.0, 0.0])).numpy().T, mesh.elements,
                      mesh.node_sets, mesh.face_sets)
    tilted = fem.Model(turned)
    tilted.add(fem.Hex20Solid(turned, fem.NeoHookean(), formulation="displacement"))
    tilted.add(fem.ElasticSupport(turned, "zmin"))
    with pytest.raises(NotImplementedError, match="coordinate axis"):
        write_inp(tmp_path / "bad.inp", tilted, {"C10": 0.1, "D1": 1.0, "c_n": 1.0, "c_t": 2.0})


def test_a_load_trace_in_one_calculix_step_matches_each_load_factor(tmp_path):
    """``write_inp(load_factors=...)``: a loading-unloading trace as one ``*STATIC`` step through an
    ``*AMPLITUDE`` (increments_per_entry increments per entry); CalculiX's displacements at the end
    of each entry's increments against torchfra solved at that load factor (hyperelastic: the path
    does not matter). Reference CalculiX 2.20; without hold increments its linear convergence on the
    follower pressure leaves 2.3e-5 to 1.3e-4 of max |u| (measured; the most after unloading), bound
    5e-4; a neighbouring entry would be off by 20 % or more."""
    from torchfra.io.abaqus.write import dat_blocks

    model = block()
    model.add(fem.FollowerPressure(model.mesh, "ymin", pressure="P", quadrature=CALCULIX_FACE_RULE))
    params = {"C10": 0.1, "D1": d1_for(0.2), "P": 0.006}
    trace = np.array([0.4, 1.0, 0.7, 0.2])
    sol = fem.solve(model, {k: torch.tensor([v]) for k, v in params.items()}, np.unique(trace))
    assert sol.converged.all(), sol.status
    deck = write_inp(tmp_path / "trace.inp", model, params, load_factors=trace, increments_per_entry=5)
    text = deck.read_text()
    assert "*AMPLITUDE, NAME=TRACE" in text and "*STATIC, DIRECT\n0.05, 1.0" in text
    run_calculix(deck)
    blocks = dict((round(t, 6), u) for t, u in dat_blocks(deck.with_suffix(".dat")))
    for k, lam in enumerate(trace):
        u_ccx = np.stack([blocks[round((k + 1) / trace.size, 6)][i] for i in range(model.n_nodes)])
        u_torch = sol.u[0, int(np.searchsorted(np.unique(trace), lam))].numpy()
        rel = np.abs(u_ccx - u_torch).max() / np.abs(u_torch).max()
        assert rel < 5e-4, f"entry {k} (load factor {lam}): {rel:.2e}"
    with pytest.raises(ValueError, match="load_factors must be"):
        write_inp(tmp_path / "bad.inp", model, params, load_factors=[0.5, 1.5])
