"""The pressure (load) trace recorded beside a DIC export, and its values at the DIC frames.

A CSV whose header names a time column and a pressure column with its unit, e.g.
``time [s],pressure [kPa]`` (``,``, ``;`` or tab separated; preamble lines allowed), and optionally
a frame column (``frame`` or ``image``) holding the DIC frame numbers. Pressure units: Pa, kPa, MPa,
bar, mbar, psi, N/mm^2, converted to MPa; a pressure column without a unit is refused unless the
caller names it. Time units: s, ms, min, h (converted to s); a time without a unit is kept as written
(normalized time, say).

Frames get their pressure

- by frame (``match="frame"``): the trace row with the frame's number in the frame column, or, with no
  frame column and one row per frame, the rows in file order;
- by time (``match="time"``): frame k is taken at ``first_frame_time + (frame_k - frame_0) /
  frame_rate`` and the pressure interpolated linearly in the trace.
"""
from __future__ import annotations

import csv
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from torchfra.io.tables import MAX_PREAMBLE, DicError, name_unit, read_lines, split_line, to_float

PRESSURE_UNITS = {"pa": 1e-6, "kpa": 1e-3, "mpa": 1.0, "bar": 0.1, "mbar": 1e-4, "psi": 6.894757293168361e-3,
                  "n/mm^2": 1.0, "n/mm2": 1.0, "n/mm²": 1.0}
TIME_UNITS = {"s": 1.0, "ms": 1e-3, "min": 60.0, "h": 3600.0}
TIME_NAMES = ("time", "t", "timestamp")
PRESSURE_NAMES = ("pressure", "p")
FRAME_NAMES = ("frame", "image", "frame number", "image number")


@dataclass
class PressureTrace:
    """n samples: time (n,) in s (as written if the header gives no unit), pressure (n,) MPa,
    frame (n,) DIC frame numbers or None."""

    time: np.ndarray
    pressure: np.ndarray
    frame: np.ndarray | None
    source: str


def _column(names: list[str], accepted) -> int | None:
    hits = [i for i, n in enumerate(names) if n.lower() in accepted]
    return hits[0] if hits else None


def read_pressure_trace(path, pressure_units: str | None = None) -> PressureTrace:
    """Read the trace; ``pressure_units`` names the unit when the header does not."""
    path = Path(path)
    lines = read_lines(path, what="pressure trace")
    for h, line in enumerate(lines[:MAX_PREAMBLE]):
        cells, delim = split_line(line)
        parsed = [name_unit(c) for c in cells]
        names = [n for n, _ in parsed]
        ip, it, iframe = (_column(names, PRESSURE_NAMES), _column(names, TIME_NAMES), _column(names, FRAME_NAMES))
        if ip is not None and it is not None:
            break
    else:
        first = next((ln for ln in lines if ln.strip()), "")
        raise DicError(f"{path}: no header with a time and a pressure column (first line: {first.strip()!r}); "
                       "write e.g. 'time [s],pressure [kPa]' (optionally a 'frame' column)")
    unit = parsed[ip][1] or pressure_units
    if unit is None:
        raise DicError(f"{path}: the pressure column {cells[ip]!r} gives no unit; write it in the header, e.g. "
                       f"'pressure [kPa]' (known: {', '.join(PRESSURE_UNITS)}), or give the pressure units")
    if parsed[ip][1] and pressure_units and parsed[ip][1].lower() != pressure_units.lower():
        raise DicError(f"{path}: the header says pressure in {parsed[ip][1]} but {pressure_units} was given")
    if unit.lower() not in PRESSURE_UNITS:
        raise DicError(f"{path}: unknown pressure unit {unit!r}; known: {', '.join(PRESSURE_UNITS)}")
    t_unit = parsed[it][1]
    if t_unit is not None and t_unit.lower() not in TIME_UNITS:
        raise DicError(f"{path}: unknown time unit {t_unit!r}; known: {', '.join(TIME_UNITS)}")
    cols = [it, ip] + ([iframe] if iframe is not None else [])
    rows = []
    for k, line in enumerate(lines[h + 1:], start=h + 2):
        if not line.strip():
            continue
        cells_k = next(csv.reader([line], delimiter=delim))
        try:
            rows.append([to_float(cells_k[c], delim != ",") for c in cols])
        except (ValueError, IndexError):
            raise DicError(f"{path}, line {k}: cannot read {line.strip()!r} as time and pressure") from None
    if not rows:
        raise DicError(f"{path}: the trace has a header but no rows")
    table = np.asarray(rows, dtype=np.float64)
    bad = np.flatnonzero(~np.all(np.isfinite(table), axis=1))
    if bad.size:
        raise DicError(f"{path}: data row {bad[0] + 1} has an empty or non-finite value; every sample needs its "
                       "time and pressure")
    time = table[:, 0] * (TIME_UNITS[t_unit.lower()] if t_unit else 1.0)
    frame = None
    if iframe is not None:
        frame = table[:, 2]
        if np.any(frame != np.round(frame)):
            raise DicError(f"{path}: the frame column {cells[iframe]!r} must hold integer frame numbers")
        frame = frame.astype(np.int64)
    return PressureTrace(time, table[:, 1] * PRESSURE_UNITS[unit.lower()], frame, str(path))


def pressure_at_frames(trace: PressureTrace, frames, match: str = "frame", frame_rate: float | None = None,
                       first_frame_time: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Times (K,) and pressures (K,) MPa of the DIC frames (frame numbers (K,), in order)."""
    frames = np.asarray(frames, dtype=np.int64)
    if match == "frame":
        if trace.frame is not None:
            row = {int(f): i for i, f in enumerate(trace.frame)}
            missing = [int(f) for f in frames if int(f) not in row]
            if missing:
                raise DicError(f"{trace.source}: no row for DIC frame(s) {missing[:10]}; the trace's frame column "
                               f"holds {trace.frame.min()}..{trace.frame.max()}")
            idx = np.asarray([row[int(f)] for f in frames])
            return trace.time[idx], trace.pressure[idx]
        if len(trace.time) != len(frames):
            raise DicError(f"{trace.source}: {len(trace.time)} samples for {len(frames)} DIC frames; with no frame "
                           "column the trace needs one row per frame, in order. Add a 'frame' column, or match "
                           "by time with the camera's frame rate")
        return trace.time.copy(), trace.pressure.copy()
    if match != "time":
        raise DicError(f"match must be 'frame' or 'time', got {match!r}")
    if frame_rate is None or not frame_rate > 0:
        raise DicError(f"matching by time needs the camera's frame rate in frames per second (got {frame_rate})")
    step = np.diff(trace.time)
    if np.any(step <= 0):
        k = int(np.flatnonzero(step <= 0)[0])
        raise DicError(f"{trace.source}: time does not increase at data row {k + 2} ({trace.time[k]:g} -> "
                       f"{trace.time[k + 1]:g}); times must increase to interpolate")
    times = first_frame_time + (frames - frames[0]) / frame_rate
    lo, hi = trace.time[0], trace.time[-1]
    outside = np.flatnonzero((times < lo - 1e-9 * max(1.0, abs(lo))) | (times > hi + 1e-9 * max(1.0, abs(hi))))
    if outside.size:
        k = int(outside[0])
        raise DicError(f"DIC frame {frames[k]} is at t = {times[k]:g} s, outside the trace's {lo:g}..{hi:g} s "
                       f"({outside.size} of {len(frames)} frames are); check the frame rate and first frame time")
    return times, np.interp(times, trace.time, trace.pressure)
