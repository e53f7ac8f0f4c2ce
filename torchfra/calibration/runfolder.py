"""A forward run's folder: per-member checkpoints (array-only ``.npz``, never unpickled), the state of a
reduced batch after each load step, and the lock files with which worker processes share the members
(host, PID and process start time: a lock left by a process that ended, by a PID now used by another
process, or by another host idle for an hour is taken over with a message)."""
from __future__ import annotations

import json
import os
import socket
import sys
import time
from dataclasses import asdict
from pathlib import Path

import numpy as np

from torchfra.calibration.config import ForwardConfig

# settings that change how members are solved, not what they are: a run resumes across them
HOW_NOT_WHAT = ("threads", "reduced_batch")


def _check_resume(run_dir: Path, config: ForwardConfig) -> None:
    path = run_dir / "config.json"
    saved = asdict(config)
    if path.exists():
        old = json.loads(path.read_text())
        defaults = json.loads(json.dumps(asdict(type(config)())))
        old = {**{k: v for k, v in defaults.items() if k not in old}, **old}  # fields added since: their defaults
        new = json.loads(json.dumps(saved))
        for k in HOW_NOT_WHAT:
            old[k] = new[k]
        if old != new:
            diff = sorted(k for k in saved if old.get(k) != new[k])
            raise ValueError(
                f"{run_dir} holds a forward run with other settings ({', '.join(diff)}); "
                "choose another --name, or delete that folder to start over"
            )
    else:
        run_dir.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(f"config.{os.getpid()}.tmp")  # several workers may start at once
        tmp.write_text(json.dumps(saved, indent=1))
        tmp.replace(path)


LOCK_EXPIRY_S = 3600.0  # a lock of another host older than this is taken as abandoned


def _process_start(pid: int) -> str | None:
    """Start time of a live process on this host (clock ticks since boot), None if there is none:
    tells a recycled PID from the process that wrote a lock."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
        return stat.rsplit(")", 1)[1].split()[19]
    except (OSError, IndexError):
        try:
            os.kill(pid, 0)
        except ProcessLookupError:
            return None
        except PermissionError:
            pass
        return "unknown"  # alive, start time not readable (no /proc)


def _lock_owner() -> dict:
    return {"host": socket.gethostname(), "pid": os.getpid(), "start": _process_start(os.getpid()),
            "time": time.time()}


def _stale(lock: Path) -> str | None:
    """Why a lock is abandoned (its process is gone, its PID was reused, or another host's lock
    expired, or this very process left it when interrupted), or None while its owner may still
    be working."""
    try:
        owner = json.loads(lock.read_text())
        host, pid, start = owner["host"], int(owner["pid"]), owner["start"]
    except (OSError, ValueError, KeyError, TypeError):
        age = time.time() - lock.stat().st_mtime if lock.exists() else 0.0
        return "it is unreadable" if age > 60.0 else None  # give a writer a moment to finish writing it
    if host != socket.gethostname():
        age = time.time() - float(owner.get("time", 0.0))
        return f"host {host} last touched it {age / 60:.0f} min ago" if age > LOCK_EXPIRY_S else None
    now = _process_start(pid)
    if now is None:
        return f"process {pid} has ended"
    if start is not None and now not in ("unknown", start):
        return f"process id {pid} now belongs to another process"
    if pid == os.getpid():  # one run_forward at a time per process: an earlier call here was interrupted
        return "an interrupted earlier run in this process left it"
    return None


def _claim(lock: Path, quiet: bool = False) -> bool:
    """Take the lock file of a member chunk, so several worker processes can share one run folder
    (``python scripts/forward_uq.py`` started twice on a 2-core machine). The lock names host, PID,
    process start time and time; an abandoned lock (dead process, recycled PID, another host's lock
    past ``LOCK_EXPIRY_S``) is taken over with a message, so a run never waits forever."""
    try:
        fd = os.open(lock, os.O_CREAT | os.O_EXCL | os.O_WRONLY)
    except FileExistsError:
        why = _stale(lock)
        if why is None:
            return False
        if not quiet:
            print(f"taking over {lock.name}: {why}", file=sys.stderr, flush=True)
        lock.unlink(missing_ok=True)
        return _claim(lock, quiet)
    with os.fdopen(fd, "w") as f:
        f.write(json.dumps(_lock_owner()))
    return True


CHUNK_ARRAYS = ("Y", "u_last", "status", "load_reached", "iterations", "increments", "cutbacks", "last_residual",
                "history_values", "history_lengths", "timings")


OPTIONAL_ARRAYS = ("method", "error_estimate", "states", "full_tangents")  # reduced-method records


def save_chunk(path: Path, history: list[list[float]], timings: dict, **arrays) -> None:
    """Write a solved member chunk in a format that carries arrays only (loaded without unpickling):
    the per-member residual histories flattened with their lengths, timings as a JSON string.
    Written aside and renamed, so a killed run never leaves half a chunk."""
    tmp = path.with_suffix(".tmp.npz")
    np.savez(tmp, **{k: np.asarray(v) if k != "status" else np.asarray(v, dtype=str) for k, v in arrays.items()},
             history_values=np.asarray([x for h in history for x in h], dtype=np.float64),
             history_lengths=np.asarray([len(h) for h in history], dtype=np.int64),
             timings=np.asarray(json.dumps(timings)))
    tmp.replace(path)


def _why_unreadable(exc: Exception) -> str:
    """Why an array file could not be read, without numpy's advice to load pickled data unsafely."""
    text = str(exc)
    return "it is not an array archive written by np.savez" if "pickle" in text else text


def load_chunk(path: Path) -> dict:
    """Read a chunk written by :func:`save_chunk`; never unpickles. A file that is not such a chunk
    (an older format, a damaged or planted file) is refused by name."""
    try:
        with np.load(path, allow_pickle=False) as data:
            missing = [k for k in CHUNK_ARRAYS if k not in data.files]
            if missing:
                raise ValueError(f"arrays {missing} are missing")
            out = {k: data[k] for k in CHUNK_ARRAYS}
            for k in OPTIONAL_ARRAYS:
                if k in data.files:
                    out[k] = data[k]
        timings = json.loads(str(out.pop("timings")))
        if not isinstance(timings, dict):
            raise ValueError("timings is not a JSON object")
    except Exception as exc:  # zip, pickle, key and JSON errors alike: one clear message
        raise ValueError(
            f"{path} is not a forward-ensemble chunk this version can read ({_why_unreadable(exc)}); it may be from an "
            "older version, damaged, or planted: delete it and rerun to solve those members again"
        ) from None
    lengths = out.pop("history_lengths")
    values = out.pop("history_values")
    if lengths.sum() != values.size or (lengths < 0).any():
        raise ValueError(f"{path}: residual histories do not add up; delete it and rerun")
    edges = np.concatenate([[0], np.cumsum(lengths)])
    out["history"] = [values[edges[i]:edges[i + 1]].tolist() for i in range(lengths.size)]
    out["timings"] = timings
    return out


def _finished(chunks_dir: Path, spans: list[tuple[int, int]]) -> int:
    """Members whose chunk is on disk, whichever process solved it."""
    return sum(stop - start for start, stop in spans if (chunks_dir / f"chunk_{start:05d}.npz").exists())


def _save_solution(path: Path, Y, u_last, sol, wall: float, **extra) -> None:
    save_chunk(path, Y=Y, u_last=u_last, status=sol.status, load_reached=sol.load_reached,
               iterations=sol.iterations, increments=sol.increments, cutbacks=sol.cutbacks,
               last_residual=sol.last_residual, history=sol.residual_history,
               timings={**sol.timings, "wall": wall}, **extra)


def _write_partial(path: Path, batch: list[int], digest: str, state: dict) -> None:
    """A reduced batch's state after a load step (arrays only), so a kill loses one load step of it."""
    tmp = path.with_name(f"{path.stem}.{os.getpid()}.tmp.npz")
    np.savez(tmp, members=np.asarray(batch, dtype=np.int64), digest=np.array(digest), **state)
    tmp.replace(path)


def _read_partial(path: Path, batch: list[int], digest: str, load) -> dict | None:
    """The saved state of this very batch on this very reduction, or None (absent, another batch or
    basis, unreadable: solved from its start again)."""
    if not path.exists():
        return None
    try:
        with np.load(path, allow_pickle=False) as f:
            state = {k: f[k] for k in f.files}
        same = (state["members"].tolist() == list(batch) and str(state["digest"]) == digest
                and np.array_equal(state["load_factors"], load))
    except (OSError, ValueError, EOFError, KeyError) as err:  # a pickle payload is refused here, never run
        print(f"forward ensemble: {path} is not a readable batch checkpoint ({type(err).__name__}: {err}); "
              "its members are solved from the start", file=sys.stderr)
        return None
    return state if same else None

