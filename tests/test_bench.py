"""``torchfra bench``: one module per suite under torchfra/cli/bench/, the same command, flags and JSON. The
smoke run is the documented one (``--suite fem --quick``), as a subprocess; ``--help`` needs no torch."""
import importlib
import json
import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SUITES = ("device", "ensemble", "fem", "forward", "sensitivity")


def _run(*args, **kw):
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    return subprocess.run([sys.executable, *args], cwd=ROOT, env=env, capture_output=True, text=True, **kw)


def test_help_lists_every_suite_and_imports_no_torch():
    done = _run("-X", "importtime", "-m", "torchfra", "bench", "--help")
    assert done.returncode == 0, done.stderr
    assert "--suite {device,ensemble,fem,forward,sensitivity}" in done.stdout
    for flag in ("--out", "--threads", "--quick", "--meshes", "--members", "--mesh", "--load-steps", "--old-members",
                 "--vary", "--newton-budget-s", "--chunk-budget-s", "--superlu-max-unknowns"):
        assert flag in done.stdout
    imported = {line.rsplit("|", 1)[-1].strip() for line in done.stderr.splitlines() if line.startswith("import time:")}
    assert "torch" not in imported and "numpy" not in imported


def test_every_suite_is_a_module_with_its_suite_and_definitions():
    from torchfra.cli.bench import command

    assert command.SUITES == SUITES
    for name in SUITES:
        suite = importlib.import_module(f"torchfra.cli.bench.{name}")
        assert callable(getattr(suite, f"{name}_suite")), name
    # the JSON's "definitions": a suite's own where it has them, the FE core's for fem and sensitivity
    for name in ("forward", "ensemble", "device"):
        assert isinstance(getattr(importlib.import_module(f"torchfra.cli.bench.{name}"), f"{name.upper()}_DEFINITIONS"),
                          dict)
    assert not hasattr(importlib.import_module("torchfra.cli.bench.sensitivity"), "SENSITIVITY_DEFINITIONS")


def test_quick_fem_suite_writes_its_json(tmp_path):
    out = tmp_path / "fem.json"
    done = _run("scripts/bench.py", "--suite", "fem", "--quick", "--out", str(out), timeout=1200)
    assert done.returncode == 0, done.stderr[-3000:]
    from torchfra.cli.bench.fem import DEFINITIONS

    record = json.loads(out.read_text())
    assert record == json.loads(done.stdout)
    assert record["suite"] == "fem" and record["quick"] is True
    assert record["definitions"] == DEFINITIONS
    assert set(record) == {"suite", "quick", "environment", "config", "newton_pilot", "meshes", "definitions",
                           "total_wall_s"}
    assert [m["divisions"] for m in record["meshes"]] == [[2, 2, 4], [2, 2, 8]]
    for mesh in record["meshes"]:
        assert set(mesh) >= {"elements", "nodes", "dofs", "reduced_dofs", "build", "kernel", "assembly",
                             "factorization", "newton"}
        assert mesh["dofs"] == 3 * mesh["nodes"]
        single = mesh["newton"][0]
        assert single["members"] == 1 and single["linear_solver"] in record["environment"]["linear_solver_backends"]
        # a solve runs when its estimate fits the budget (machine-dependent), else it is estimated
        assert single["mode"] in ("full_solve", "estimated")
        if single["mode"] == "full_solve":
            assert single["converged_members"] == 1 and single["load_reached_min"] == 1.0
        else:
            want = single["per_iteration_s"] * (single["assumed_iterations"] + 1)
            assert abs(single["estimated_wall_s"] - want) <= 1e-5 * want  # the JSON keeps 6 digits
