"""Read a DIC export and its pressure trace into a recording the calibration and the diagnosis take.

    python examples/read_dic_export.py [FOLDER]      # default FOLDER: runs/example_dic

A real export comes from the DIC software, one file per frame; here a small one is written first (a
generic ``x, y, z, u, v, w`` point cloud in mm on the actuator's front face, x = 8 mm, bending
towards +y), so the example runs anywhere. The same import from the command line:
``torchfra import-dic FOLDER/export --format generic --units mm --camera-to-model identity
--pressure FOLDER/pressure.csv --out FOLDER/recording.csv``.
"""
import sys
from pathlib import Path

import numpy as np

from torchfra.io.dic.exports import read_dic, to_recording
from torchfra.io.pressure_trace import pressure_at_frames, read_pressure_trace
from torchfra.io.recordings import read_recording, write_recording
from torchfra.observation.registration import Similarity, evaluate, front_face

folder = Path(sys.argv[1] if len(sys.argv) > 1 else "runs/example_dic")
export = folder / "export"
export.mkdir(parents=True, exist_ok=True)

# -- a stand-in export: 5 frames (frame 0 is the undeformed reference) of a 5 x 12 grid of points --
y, z = np.meshgrid(np.linspace(-6.0, 6.0, 5), np.linspace(5.0, 55.0, 12))
points = np.stack([np.full(y.size, 8.0), y.ravel(), z.ravel()], 1)          # on the face x = 8 mm
kpa = np.array([0.0, 5.0, 10.0, 15.0, 20.0])                               # the frames' pressures
for frame, p in enumerate(kpa):
    uy = 0.5 * p * (points[:, 2] / 60.0) ** 2                                # a bending-like field (mm)
    uz = -0.02 * p * points[:, 1] / 8.0
    rows = np.column_stack([points, np.zeros(len(points)), uy, uz])
    np.savetxt(export / f"frame_{frame:03d}.csv", rows, delimiter=",", header="x,y,z,u,v,w", comments="", fmt="%.9g")
(folder / "pressure.csv").write_text("frame,time [s],pressure [kPa]\n"
                                     + "".join(f"{f},{0.5 * f:g},{p:g}\n" for f, p in enumerate(kpa)))

# -- the import: read every frame, give each its pressure, place the points on the model's face --
series = read_dic(export, "generic", units="mm")                           # the export's layout, checked
times, pressure = pressure_at_frames(read_pressure_trace(folder / "pressure.csv"), series.frames)  # kPa -> MPa
# the export's coordinates are already the model's here; a camera's need --camera-to-model register
placed = evaluate(series.X, front_face(), Similarity.identity(), 0.5, series.point_ids)
rec = to_recording(series, times, pressure, placed, source="example export")
path = write_recording(folder / "recording.csv", rec)

back = read_recording(path)   # what `torchfra calibrate --recording` and `torchfra diagnose` read
print(f"{back.n_frames} frames x {back.n_points} points, "
      f"pressure {back.pressure.min():g}..{back.pressure.max():g} MPa, "
      f"registration residual {placed.rms:.2g} mm")
print(f"largest uy {np.nanmax(back.Z[..., 0]):.3f} mm at the last frame; wrote {path}")
