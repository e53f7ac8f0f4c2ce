"""Shared fixtures-by-function for the tests (small meshes and models)."""
from __future__ import annotations

import importlib
import importlib.util
from pathlib import Path

import numpy as np
import torch

from torchfra import fem
from torchfra.fem.elements import HEX20_FACES
from torchfra.fem.structured import box_mesh


def assemble_dense(term, u, params, lam, n_dofs):
    """Dense global residual (N, n) and tangent (N, n, n) of one term, by brute-force scatter."""
    out = term.evaluate(u, params, lam, tangent=True)
    N = u.shape[0]
    dofs = torch.as_tensor(term.dofs)
    r = torch.zeros(N, n_dofs).index_add_(1, dofs.ravel(), out.fe.reshape(N, -1))
    K = torch.zeros(N, n_dofs, n_dofs)
    for b in range(dofs.shape[0]):
        K[:, dofs[b][:, None], dofs[b][None, :]] += out.Ke[:, b]
    return r, K


def block_with_cavity(n=3, size=3.0):
    """An n x n x n block (n odd) with its central element removed: face set 'cavity' closes it.
    size: edge length, or (x, y, z) lengths."""
    size = np.broadcast_to(np.asarray(size, dtype=np.float64), (3,))
    full = box_mesh(tuple(float(v) for v in size), (n, n, n))
    centre = int(np.argmin(np.linalg.norm(full.nodes[full.elements].mean(1) - size / 2, axis=1)))
    keep = np.setdiff1d(np.arange(full.n_elements), [centre])
    hole_faces = {frozenset(full.elements[centre][f].tolist()) for f in HEX20_FACES}
    elements = full.elements[keep]
    cavity = [
        (e, f) for e in range(elements.shape[0]) for f in range(6)
        if frozenset(elements[e][HEX20_FACES[f]].tolist()) in hole_faces
    ]
    remap = -np.ones(full.n_elements, dtype=np.int64)
    remap[keep] = np.arange(keep.size)
    face_sets = {k: np.stack([remap[v[:, 0]], v[:, 1]], 1) for k, v in full.face_sets.items()}
    face_sets = {k: v[v[:, 0] >= 0] for k, v in face_sets.items()}
    face_sets["cavity"] = np.array(cavity)
    return fem.Mesh(full.nodes, elements, full.node_sets, face_sets)


# the user commands' modules (scripts/<name>.py is a thin wrapper of each)
COMMANDS = {"calibrate": "calibrate", "diagnose": "diagnose", "forward_uq": "forward", "make_recording": "make_recording",
            "import_dic": "import_dic", "scenarios": "scenarios", "fem_demo": "demo", "bench": "bench"}


def load_script(name: str):
    """The module behind ``scripts/<name>.py``: a command's ``torchfra.cli`` module, or a study under
    ``studies/`` (imported from its file: the studies are not a package)."""
    if name in COMMANDS:
        return importlib.import_module(f"torchfra.cli.{COMMANDS[name]}")
    root = Path(__file__).resolve().parents[1]
    path = next((p for p in (root / "studies" / f"{name.removeprefix('study_')}.py", root / "scripts" / f"{name}.py")
                 if p.exists()), root / "scripts" / f"{name}.py")
    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def assert_same_json(got, stored, path="", rtol=1e-6, skip=("seconds",)):
    """``got`` equals ``stored`` field for field: the same keys, lists of the same length, equal strings,
    integers and booleans, floats within ``rtol`` (a different CPU's BLAS may move the last digits);
    fields named in ``skip`` (wall times) are left out. The first difference is named by its path."""
    if isinstance(stored, dict):
        assert isinstance(got, dict), f"{path}: {type(got).__name__} instead of an object"
        assert sorted(got) == sorted(stored), f"{path}: keys {sorted(set(got) ^ set(stored))} differ"
        for k in stored:
            if k not in skip:
                assert_same_json(got[k], stored[k], f"{path}.{k}", rtol, skip)
    elif isinstance(stored, list):
        assert isinstance(got, list) and len(got) == len(stored), f"{path}: {got!r} against {stored!r}"
        for i, (g, s) in enumerate(zip(got, stored)):
            assert_same_json(g, s, f"{path}[{i}]", rtol, skip)
    elif isinstance(stored, float) and not isinstance(got, bool):
        assert isinstance(got, (int, float)), f"{path}: {got!r} against {stored!r}"
        assert abs(got - stored) <= rtol * max(abs(stored), 1e-12) or (np.isnan(got) and np.isnan(stored)), \
            f"{path}: {got!r} against {stored!r}"
    else:
        assert got == stored and type(got) is type(stored), f"{path}: {got!r} against {stored!r}"
