"""Member-parallel FE work on ``torch.distributed``: ranks started by ``torchrun`` split an ensemble.

``torchrun --standalone --nproc-per-node K scripts/forward_uq.py ...`` (one machine) or
``torchrun --nnodes N --nproc-per-node K --rdzv-endpoint HOST:PORT ...`` (several) starts K (x N)
copies of a script with ``RANK``, ``WORLD_SIZE``, ``MASTER_ADDR`` and ``MASTER_PORT`` set.
:func:`ranks` joins them into a gloo process group (CPU); ``torchfra.calibration.forward.run_forward`` then
hands each rank its share of the members (round robin over the members still to solve, as rank
0's run folder lists them, so every rank agrees) and :func:`share_files` copies each solved
member's checkpoint from the rank that solved it to every other rank. Every rank ends with the
whole ensemble in its own run folder, whether or not the ranks share a file system, so a killed
run resumes from any rank's folder like a one-process run.

Files travel as their bytes (uint8 tensors): the array-only ``.npz`` checkpoints, read back with
``allow_pickle=False`` as always. Nothing is pickled (``all_gather_object`` would pickle).
"""
from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import torch


@dataclass(frozen=True)
class Ranks:
    """This process's ``rank`` among ``size`` processes; ``size == 1``: no process group."""

    rank: int = 0
    size: int = 1

    @property
    def parallel(self) -> bool:
        return self.size > 1

    def share(self, items: list) -> list:
        """This rank's round-robin share of ``items``."""
        return items[self.rank::self.size]

    def owner(self, items: list, item) -> int:
        return items.index(item) % self.size


def ranks() -> Ranks:
    """The process group of a ``torchrun`` launch (joined once, gloo backend), or one process when
    the environment names none (``WORLD_SIZE`` unset or 1)."""
    import torch.distributed as dist

    size = int(os.environ.get("WORLD_SIZE", "1"))
    if size <= 1 or not dist.is_available():
        return Ranks()
    if not dist.is_initialized():
        dist.init_process_group("gloo")
    return Ranks(dist.get_rank(), dist.get_world_size())


def broadcast_ints(values: list[int] | None, r: Ranks, src: int = 0) -> list[int]:
    """``values`` of rank ``src`` on every rank."""
    import torch.distributed as dist

    if not r.parallel:
        return list(values or [])
    n = torch.tensor([len(values) if r.rank == src else 0], dtype=torch.int64)
    dist.broadcast(n, src)
    data = torch.tensor(values if r.rank == src else [0] * int(n), dtype=torch.int64)
    dist.broadcast(data, src)
    return data.tolist()


def share_file(path: Path, r: Ranks, src: int) -> None:
    """Copy ``path`` from rank ``src`` to every rank that does not have it (written aside and renamed)."""
    import torch.distributed as dist

    if not r.parallel:
        return
    data = path.read_bytes() if r.rank == src else b""
    n = torch.tensor([len(data)], dtype=torch.int64)
    dist.broadcast(n, src)
    buf = torch.frombuffer(bytearray(data), dtype=torch.uint8) if r.rank == src else torch.empty(int(n), dtype=torch.uint8)
    dist.broadcast(buf, src)
    if r.rank != src and not path.exists():
        tmp = path.with_name(f"{path.stem}.rank{r.rank}.tmp")
        tmp.write_bytes(buf.numpy().tobytes())
        tmp.replace(path)


def share_files(paths: list[Path], owners: list[int], r: Ranks) -> None:
    """Every file of ``paths`` from the rank that wrote it (``owners``) to all the others."""
    for path, src in zip(paths, owners):
        share_file(path, r, src)


def barrier(r: Ranks) -> None:
    if r.parallel:
        import torch.distributed as dist

        dist.barrier()


def finish(r: Ranks, wait: bool = True) -> None:
    """Leave the process group after the last collective (``wait``: once every rank is there)."""
    if r.parallel:
        import torch.distributed as dist

        if wait:
            dist.barrier()
        dist.destroy_process_group()


def _header(t: torch.Tensor | None) -> torch.Tensor:
    head = torch.zeros(9, dtype=torch.int64)
    if t is not None:
        head[0] = t.ndim
        head[1 : 1 + t.ndim] = torch.tensor(t.shape, dtype=torch.int64)
    return head


def broadcast_tensor(t: torch.Tensor | None, r: Ranks, src: int = 0, dtype=torch.float64) -> torch.Tensor:
    """Rank ``src``'s tensor (any shape, at most 8 dimensions, of ``dtype``) on every rank."""
    import torch.distributed as dist

    if not r.parallel:
        return t
    head = _header(t.to(dtype) if r.rank == src else None)
    dist.broadcast(head, src)
    shape = head[1 : 1 + int(head[0])].tolist()
    data = t.to(dtype).contiguous() if r.rank == src else torch.empty(shape, dtype=dtype)
    dist.broadcast(data, src)
    return data


def send_tensors(tensors: list[torch.Tensor], dst: int) -> None:
    """Point to point: ``tensors`` (float64) to rank ``dst``, each with its shape."""
    import torch.distributed as dist

    for t in tensors:
        t = t.to(torch.float64).contiguous()
        dist.send(_header(t), dst)
        dist.send(t, dst)


def recv_tensors(n: int, src: int) -> list[torch.Tensor]:
    """The ``n`` tensors :func:`send_tensors` sent from rank ``src``."""
    import torch.distributed as dist

    out = []
    for _ in range(n):
        head = torch.empty(9, dtype=torch.int64)
        dist.recv(head, src)
        t = torch.empty(head[1 : 1 + int(head[0])].tolist(), dtype=torch.float64)
        dist.recv(t, src)
        out.append(t)
    return out


def gather_bytes(data: bytes, r: Ranks, dst: int = 0) -> list[bytes]:
    """Every rank's ``data`` on rank ``dst`` (in rank order; ``[]`` on the other ranks)."""
    import torch.distributed as dist

    if not r.parallel:
        return [data]
    if r.rank != dst:
        dist.send(torch.tensor([len(data)], dtype=torch.int64), dst)
        if data:
            dist.send(torch.frombuffer(bytearray(data), dtype=torch.uint8), dst)
        return []
    out = []
    for src in range(r.size):
        if src == dst:
            out.append(data)
            continue
        n = torch.empty(1, dtype=torch.int64)
        dist.recv(n, src)
        buf = torch.empty(int(n), dtype=torch.uint8)
        if int(n):
            dist.recv(buf, src)
        out.append(buf.numpy().tobytes())
    return out
