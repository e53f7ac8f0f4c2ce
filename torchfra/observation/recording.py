"""Recordings: what a camera (DIC) and a pressure sensor give, and nothing else (DESIGN §6).

CSV, one row per point per frame::

    frame,time,pressure,point_id,X,Y,Z,uy,uz

time normalized (or in s), pressure in MPa, reference coordinates X, Y, Z and displacements uy, uz
in mm. An empty or NaN ``uy``/``uz`` is a missing observation; a point absent from a frame is
missing too. Missing values are masked (NaN in ``Recording.Z``), never zero-filled. The NPZ form holds
the same names as arrays (1-D, or frames x points, see :mod:`torchfra.io.recordings`).

A recording that follows its points through the frames is stored frames x points. One whose
points come and go (each frame sees at most half of all its points: a DIC export that renumbers
its points per frame, a point per frame) is stored *ragged*: each frame's observed points packed
into ``slots`` (frames x the most points one frame sees), so memory follows the observations
present, not frames x points.

Validation refuses, naming the culprit: an empty file, missing columns, a frame without a finite
time or pressure or with two different times, duplicated ``(frame, point_id)`` rows, times that do
not increase with the frame number, a point whose reference coordinates change between frames, and
displacements larger than ``max_displacement`` (default 1000 mm; a unit mix-up such as metres vs
mm shows up as values off by 1000), an infinite value anywhere, and a recording without a single
observed displacement. What is not a recording file at all (a folder, a device, a compressed,
binary or UTF-16 file, an object array) is refused before parsing, see :mod:`torchfra.io.recordings`;
limits on the size of what is read are keyword arguments of :func:`read_recording`.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

COLUMNS = ("frame", "time", "pressure", "point_id", "X", "Y", "Z", "uy", "uz")
# Limits on what a reader takes in (keyword arguments of read_recording raise them): a CSV line, data
# rows (or NPZ array entries), frames x points of the (K, P, 2) array (320 MB of float64; ragged:
# frames x the fullest frame's points).
MAX_LINE_BYTES = 1 << 20
MAX_ROWS = 5_000_000
MAX_FRAME_POINTS = 20_000_000


class RecordingError(ValueError):
    """A recording that cannot be used as it is; the message names the file, row, frame or point."""


@dataclass
class Recording:
    """K frames x P points.

    frames (K,) int, times (K,), pressure (K,) MPa, point_ids (P,) int, X (P, 3) mm reference
    coordinates, Z (K, P, 2) observed (uy, uz) in mm with NaN where not observed.

    Ragged (``slots`` given): Z (K, S, 2) holds frame k's observations in its S slots, slot j being
    point ``slots[k, j]`` (an index into ``point_ids``; -1 and NaN in Z for an empty slot).
    """

    frames: np.ndarray
    times: np.ndarray
    pressure: np.ndarray
    point_ids: np.ndarray
    X: np.ndarray
    Z: np.ndarray
    source: str = "<memory>"
    slots: np.ndarray | None = None

    @property
    def ragged(self) -> bool:
        """True when frames observe different points, stored per frame (``slots``)."""
        return self.slots is not None

    @property
    def mask(self) -> np.ndarray:
        """(K, P, 2) (ragged: (K, S, 2)) True where observed."""
        return np.isfinite(self.Z)

    def require_followed_points(self, what: str) -> None:
        """Refuse a ragged recording where ``what`` needs every point followed through the frames."""
        if self.ragged:
            raise RecordingError(
                f"{self.source}: its frames observe different points ({self.n_points} points, at most "
                f"{self.Z.shape[1]} in one frame); {what} follows each point through the frames. Register the DIC "
                "export's points on its reference frame (scripts/import_dic.py) so each point keeps its id; "
                "scripts/calibrate.py takes the recording as it is")

    @property
    def n_frames(self) -> int:
        return len(self.frames)

    @property
    def n_points(self) -> int:
        return len(self.point_ids)


def from_table(t: dict[str, np.ndarray], source: str = "<memory>", max_displacement: float = 1000.0,
               max_frame_points: int = MAX_FRAME_POINTS) -> Recording:
    """Validate a long table (one entry per point per frame) and arrange it as frames x points (or
    per frame when ragged, see the module's docstring)."""
    for c in COLUMNS:
        bad = np.flatnonzero(np.isinf(t[c]))
        if bad.size:
            raise RecordingError(f"{source}: data row {bad[0] + 1} has {c} = {t[c][bad[0]]}; a missing value is "
                                 "empty or NaN, never infinite")
    for c in ("frame", "point_id"):
        v = t[c]
        # float64 holds every integer below 2^53 exactly; above it distinct ids could merge
        bad = np.flatnonzero(~np.isfinite(v) | (v != np.round(v)) | (np.abs(v) >= 2.0 ** 53))
        if bad.size:
            raise RecordingError(f"{source}: data row {bad[0] + 1} has {c} = {v[bad[0]]!r}; {c} must be an integer "
                                 "of magnitude below 2^53")
    for c in ("X", "Y", "Z"):
        bad = np.flatnonzero(~np.isfinite(t[c]))
        if bad.size:
            raise RecordingError(f"{source}: point {int(t['point_id'][bad[0]])} (frame {int(t['frame'][bad[0]])}) "
                                 f"has no reference coordinate {c}; every row needs X, Y, Z in mm")
    frame, pid = t["frame"].astype(np.int64), t["point_id"].astype(np.int64)
    frames, fi = np.unique(frame, return_inverse=True)
    pids, pi = np.unique(pid, return_inverse=True)
    K, P = len(frames), len(pids)
    S = int(np.bincount(fi, minlength=K).max(initial=0))  # the most rows one frame has
    ragged = 2 * S <= P  # every frame sees at most half the points: store per frame
    if K * (S if ragged else P) > max_frame_points:
        layout = (f"{K} frames x {S} observed points in the fullest frame" if ragged
                  else f"{K} frames x {P} points")
        raise RecordingError(f"{source}: {layout} = {K * (S if ragged else P)} entries per displacement component, "
                             f"more than the limit max_frame_points = {max_frame_points}; if the recording is "
                             "right, raise the limit with read_recording(..., max_frame_points=...)")
    key = fi.astype(np.int64) * P + pi
    order = np.argsort(key, kind="stable")  # one sort serves the duplicate check and the ragged layout
    sorted_key = key[order]
    dup = np.flatnonzero(sorted_key[1:] == sorted_key[:-1])
    if dup.size:
        k = int(sorted_key[dup[0]])
        raise RecordingError(f"{source}: point {pids[k % P]} appears {int(np.sum(sorted_key == k))} times in frame "
                             f"{frames[k // P]}; each (frame, point_id) must appear once")
    times, pressure = np.full(K, np.nan), np.full(K, np.nan)
    for name, out in (("time", times), ("pressure", pressure)):
        v = t[name]
        lo = np.full(K, np.inf)
        hi = np.full(K, -np.inf)
        np.minimum.at(lo, fi, np.where(np.isfinite(v), v, np.inf))
        np.maximum.at(hi, fi, np.where(np.isfinite(v), v, -np.inf))
        bad = np.flatnonzero(~np.isfinite(lo))
        if bad.size:
            raise RecordingError(f"{source}: frame {frames[bad[0]]} has no finite {name}; every frame needs "
                                 f"its {name} (drop the frame if the sensor failed)")
        diff = np.flatnonzero(hi - lo > 1e-9 * np.maximum(1.0, np.abs(hi)))
        if diff.size:
            raise RecordingError(f"{source}: frame {frames[diff[0]]} has rows with different {name}s "
                                 f"({lo[diff[0]]:g} and {hi[diff[0]]:g})")
        out[:] = lo
    dec = np.flatnonzero(np.diff(times) <= 0)
    if dec.size:
        k = int(dec[0])
        raise RecordingError(f"{source}: time does not increase from frame {frames[k]} (t = {times[k]:g}) to "
                             f"frame {frames[k + 1]} (t = {times[k + 1]:g}); frames must be in time order")
    X = np.full((P, 3), np.nan)
    X[pi] = np.stack([t["X"], t["Y"], t["Z"]], axis=1)
    spread = np.zeros(P)
    for c, col in enumerate(("X", "Y", "Z")):
        lo = np.full(P, np.inf)
        hi = np.full(P, -np.inf)
        np.minimum.at(lo, pi, t[col])
        np.maximum.at(hi, pi, t[col])
        spread = np.maximum(spread, hi - lo)
    bad = np.flatnonzero(spread > 1e-6)
    if bad.size:
        raise RecordingError(f"{source}: point {pids[bad[0]]} changes its reference coordinates between frames "
                             f"(by {spread[bad[0]]:.3g} mm); X, Y, Z are the reference position")
    slots = None
    if ragged:  # frame k's rows in slots 0, 1, ... in the order of their point ids
        start = np.concatenate([[0], np.cumsum(np.bincount(fi, minlength=K))])
        slot = np.empty(frame.size, dtype=np.int64)
        slot[order] = np.arange(frame.size) - start[fi[order]]
        slots = np.full((K, S), -1, dtype=np.int64)
        slots[fi, slot] = pi
        Z = np.full((K, S, 2), np.nan)
        Z[fi, slot, 0], Z[fi, slot, 1] = t["uy"], t["uz"]
    else:
        Z = np.full((K, P, 2), np.nan)
        Z[fi, pi, 0], Z[fi, pi, 1] = t["uy"], t["uz"]
    if not np.isfinite(Z).any():
        raise RecordingError(f"{source}: no observed displacements: every uy and uz is empty or NaN, so there is "
                             "nothing to calibrate on")
    big = np.abs(np.nan_to_num(Z)) > max_displacement
    if big.any():
        k, p, c = np.argwhere(big)[0]
        point = pids[slots[k, p] if ragged else p]
        raise RecordingError(f"{source}: frame {frames[k]}, point {point}: u{'yz'[c]} = {Z[k, p, c]:g} mm is "
                             f"larger than {max_displacement:g} mm; check the units (mm expected)")
    return Recording(frames, times, pressure, pids, X, Z, source, slots)


def to_table(rec: Recording) -> dict[str, np.ndarray]:
    K, S = rec.Z.shape[:2]
    fi, si = np.repeat(np.arange(K), S), np.tile(np.arange(S), K)
    if rec.ragged:  # the filled slots only
        pi = rec.slots[fi, si]
        fi, si, pi = fi[pi >= 0], si[pi >= 0], pi[pi >= 0]
    else:
        pi = si
    return {
        "frame": rec.frames[fi], "time": rec.times[fi], "pressure": rec.pressure[fi], "point_id": rec.point_ids[pi],
        "X": rec.X[pi, 0], "Y": rec.X[pi, 1], "Z": rec.X[pi, 2],
        "uy": rec.Z[fi, si, 0], "uz": rec.Z[fi, si, 1],
    }
