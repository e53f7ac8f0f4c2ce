"""The device suite: the brick kernel on the CPU and, when present, on CUDA."""
from __future__ import annotations

import numpy as np
import torch

from torchfra import fem
from torchfra.cli.bench.common import (
    Config, DTYPE, KERNEL_AMPLITUDE, log, measure, measure_members, member_params, members
)


DEVICE_DEFINITIONS = {
    "kernel": "fem.Hex20Solid.evaluate of the actuator's bricks (hybrid, 3x3x3 Gauss points, Neo-Hookean): "
    "residual and element tangents of every brick for M members at a random displacement of strain ~1 % "
    "(KERNEL_AMPLITUDE), what a Newton iteration's tangent costs before assembly. CPU: member-chunked as "
    "Model.evaluate does (chunk_size members at a time), torch threads = --threads. CUDA: all M members at "
    "once, the term's tensors moved to the GPU, timed between torch.cuda.synchronize() calls.",
    "member_elements_per_s": "M x bricks / s",
    "deviation": "max |CUDA - CPU| / max |CPU| over the first member's residual and tangents (float64 both)",
    "scope": "the element kernel only: a measurement towards an optional CUDA path; assembly, the constraint "
    "reduction and the sparse factorization stay on the CPU in torchfra",
}


def _term_to(term, device):
    """A copy of ``term`` with every tensor attribute (its material's too) on ``device``."""
    import copy

    out = copy.copy(term)
    for k, v in vars(term).items():
        if torch.is_tensor(v):
            setattr(out, k, v.to(device))
    mat = copy.copy(term.material)
    for k, v in vars(term.material).items():
        if torch.is_tensor(v):
            setattr(mat, k, v.to(device))
    out.material = mat
    return out


def device_suite(cfg: Config, args) -> dict:
    """The brick kernel on the CPU and, when present, on CUDA, side by side (DEVICE_DEFINITIONS)."""
    import traceback

    from torchfra.actuator.geometry import ActuatorGeometry, build_actuator_model

    model, info = build_actuator_model(ActuatorGeometry(resolution=args.mesh))
    model.finalize()
    solid = next(t for t in model.terms if isinstance(t, fem.Hex20Solid))
    E = solid.conn.shape[0]
    counts = [int(v) for v in args.members.split(",")] if args.members else ([1, 4] if args.quick else [1, 10, 100])
    edge = float(np.min(np.linalg.norm(np.diff(model.mesh.nodes[model.mesh.elements[:, :2]], axis=1), axis=-1)))
    chunk = model._chunk_size()
    log(f"device: resolution {args.mesh}, {E} bricks, members {counts}, CPU chunk {chunk}, "
        f"CUDA {'available: ' + torch.cuda.get_device_name(0) if torch.cuda.is_available() else 'not available'}")
    rows, reference = [], {}
    devices = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])
    for device in devices:
        term = solid if device == "cpu" else _term_to(solid, device)
        for n in counts:
            row = {"device": device, "members": n, "bricks": E}
            try:
                params = {k: v.to(device) for k, v in member_params(n, cfg.seed).items()}
                g = torch.Generator().manual_seed(cfg.seed)
                u = (KERNEL_AMPLITUDE * edge * torch.randn(n, model.n_nodes, 3, generator=g, dtype=DTYPE)).to(device)
                lam = torch.ones(n, dtype=DTYPE, device=device)

                def run(lo, hi):
                    out = term.evaluate(u[lo:hi], members(params, slice(lo, hi)), lam[lo:hi], tangent=True)
                    if device == "cuda":
                        torch.cuda.synchronize()
                    return out

                if device == "cpu":
                    rec = measure_members(run, n, chunk, cfg)
                else:
                    run(0, n)  # warm-up: kernels compiled, memory pooled
                    rec, _ = measure(lambda: run(0, n), cfg)
                row.update(rec)
                row["member_elements_per_s"] = n * E / rec["s"]
                first = run(0, 1)
                fe, Ke = first.fe.double().cpu(), first.Ke.double().cpu()
                if device == "cpu" and n == counts[0]:
                    reference = {"fe": fe, "Ke": Ke}
                elif device != "cpu":
                    row["deviation"] = max(float((fe - reference["fe"]).abs().max() / reference["fe"].abs().max()),
                                           float((Ke - reference["Ke"]).abs().max() / reference["Ke"].abs().max()))
                if device == "cuda":
                    row["peak_memory_mb"] = torch.cuda.max_memory_allocated() / 2**20
                log(f"  {device}, {n} members: {rec['s']:.4f} s, {row['member_elements_per_s']:.4g} member-elements/s"
                    + (f", deviation {row['deviation']:.2e}" if "deviation" in row else ""))
            except Exception as exc:  # a device that cannot run the kernel is reported, not fatal
                row["error"] = "".join(traceback.format_exception_only(type(exc), exc)).strip()
                row["traceback"] = traceback.format_exc()
                log(f"  {device}, {n} members: {row['error']}")
            rows.append(row)
    speedups = {}
    for n in counts:
        cpu = next((r for r in rows if r["device"] == "cpu" and r["members"] == n and "s" in r), None)
        gpu = next((r for r in rows if r["device"] == "cuda" and r["members"] == n and "s" in r), None)
        if cpu and gpu:
            speedups[str(n)] = cpu["s"] / gpu["s"]
    return {"mesh": {"resolution": args.mesh, "bricks": E, "nodes": int(model.n_nodes)},
            "threads": torch.get_num_threads(), "rows": rows, "cuda_over_cpu": speedups,
            "cuda_device": torch.cuda.get_device_name(0) if torch.cuda.is_available() else None}
