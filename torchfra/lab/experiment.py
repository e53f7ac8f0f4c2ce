"""The virtual DIC experiment: the FE actuator filmed, correlated by a real DIC engine, imported.

1. The paper's actuator (no gravity) is solved at each frame's pressure of a ramp (frame 0
   unloaded); the displacement of its front face x = +8 mm is taken on a fine grid of material
   points (the FE face shape functions, :class:`torchfra.observation.operator.ObservationOperator`)
   and made a :class:`torchfra.lab.speckle.FaceField`.
2. A speckle pattern is painted on the face and the camera (:class:`torchfra.lab.camera.Camera`,
   framed to see every position the face reaches) renders the reference and the deformed images
   with grey-level noise (:func:`torchfra.lab.speckle.render`).
3. pyvale correlates them (:func:`torchfra.lab.engine.correlate`) over the reference face.
4. The engine's export is imported like any DIC export (:func:`torchfra.io.dic.import_export`,
   format ``pyvale``, ``--scale`` the pixel size), registered on the face by the face's corners
   as landmarks (the camera's calibration), with the pressure trace beside it.
5. The recording's displacements are compared with the FE truth at the same material points
   (:func:`torchfra.lab.budget.error_budget`).

Units: mm, MPa; images in grey levels [0, 1] (float32, 8-bit quantized).
"""
from __future__ import annotations

import argparse
import json
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from torchfra import fem
from torchfra.calibration.config import ForwardConfig
from torchfra.calibration.frames import ActuatorSolver
from torchfra.lab.budget import error_budget
from torchfra.lab.camera import Camera
from torchfra.lab.engine import EngineSettings, correlate, engine_version
from torchfra.lab.speckle import FaceField, face_mask, render, speckle_pattern
from torchfra.observation.operator import ObservationOperator, frame_times

FACE_BOUNDS = ((-8.0, 8.0), (0.0, 60.0))  # the front face's (y, z) extent, mm
FACE_X = 8.0


@dataclass(frozen=True)
class VirtualDicSettings:
    """Everything the experiment depends on (mm, MPa, pixels).

    pixel_size: mm per pixel; image_size: (rows, cols), None to frame the face's motion; speckle_size:
    dot diameter (mm); grey_noise: std of the grey-level noise (fraction of the full range);
    supersample: sample points per pixel side; subset_size, subset_step: pixels; frames: loaded
    frames of the ramp (plus the unloaded one); pressure: the ramp's top (MPa); c10: the body's
    C10 (MPa); resolution: of the FE mesh; working_distance: mm of a pinhole camera (None:
    telecentric); seed: of the speckle pattern and the noise; threads: the engine's.
    """

    pixel_size: float = 0.1
    image_size: tuple | None = None
    speckle_size: float = 0.4
    grey_noise: float = 0.01
    supersample: int = 2
    subset_size: int = 21
    subset_step: int = 10
    frames: int = 10
    pressure: float = 0.022
    c10: float = 0.0048
    resolution: int = 1
    working_distance: float | None = None
    seed: int = 0
    threads: int = 1

    def check(self) -> None:
        """Refuse a setting that cannot make an experiment, naming it."""
        for name in ("pixel_size", "speckle_size", "pressure", "c10"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v > 0):
                raise ValueError(f"{name} must be a positive number, got {v}")
        if not 0 <= self.grey_noise < 0.5:
            raise ValueError(f"grey_noise must lie in [0, 0.5) of the grey range, got {self.grey_noise}")
        if self.frames < 1:
            raise ValueError(f"frames must be >= 1, got {self.frames}")
        if self.speckle_size < 2.5 * self.pixel_size:
            raise ValueError(f"speckle_size {self.speckle_size:g} mm is under 2.5 pixels of {self.pixel_size:g} mm; "
                             "DIC needs dots of 3-5 pixels: enlarge the speckles or make the pixels smaller")
        EngineSettings(self.subset_size, self.subset_step).check()


def face_fields(settings: VirtualDicSettings, spacing: float = 0.25, progress: bool = False):
    """The FE solution at the frames: (times (K+1,), pressures (K+1,) MPa, fields [FaceField] per loaded
    frame, the solver). Frame 0 is unloaded (no field)."""
    solver = ActuatorSolver(settings.resolution, fwd=ForwardConfig(resolution=settings.resolution,
                                                                   pressure=settings.pressure))
    times = np.concatenate([[0.0], frame_times(settings.frames)])
    pressure = settings.pressure * times
    sol = fem.solve(solver.model, solver.params([settings.c10]), times[1:], solver.options(),
                    progress="virtual DIC: FE solve" if progress else False)
    if sol.status[0] != "converged":
        raise RuntimeError(f"the actuator did not converge at C10 = {settings.c10:g} MPa (reached "
                           f"{sol.load_reached[0]:.3f} of {settings.pressure:g} MPa); lower the pressure")
    (ylo, yhi), (zlo, zhi) = FACE_BOUNDS
    y = np.linspace(ylo, yhi, int(round((yhi - ylo) / spacing)) + 1)
    z = np.linspace(zlo, zhi, int(round((zhi - zlo) / spacing)) + 1)
    Y, Z = np.meshgrid(y, z, indexing="ij")
    pts = np.stack([np.full(Y.size, FACE_X), Y.ravel(), Z.ravel()], axis=1)
    op = ObservationOperator(solver.mesh, solver.faces, points=pts, components=(0, 1, 2), tol=1e-6)
    U = op(sol.u[0, :, : solver.mesh.n_nodes]).numpy()  # (K, P, 3)
    fields = [FaceField(y, z, U[k].reshape(len(y), len(z), 3)) for k in range(settings.frames)]
    return times, pressure, fields, solver, sol


def frame_camera(settings: VirtualDicSettings, fields) -> Camera:
    """The camera: ``settings.image_size`` if given (refused if the face leaves it), else the smallest
    image that sees the face in every frame with a margin of one subset."""
    (ylo, yhi), (zlo, zhi) = FACE_BOUNDS
    edge = np.concatenate([np.stack([np.linspace(ylo, yhi, 50), np.full(50, z)], 1) for z in (zlo, zhi)]
                          + [np.stack([np.full(200, y), np.linspace(zlo, zhi, 200)], 1) for y in (ylo, yhi)])
    pos = [edge] + [edge + f(edge)[:, 1:3] for f in fields]
    allpos = np.concatenate(pos)
    margin = settings.subset_size
    cam = Camera.framing(settings.pixel_size, (allpos[:, 0].min(), allpos[:, 0].max()),
                         (allpos[:, 1].min(), allpos[:, 1].max()), margin, settings.working_distance)
    if settings.image_size is None:
        return cam
    rows, cols = settings.image_size
    if rows < cam.shape[0] or cols < cam.shape[1]:
        raise ValueError(f"an image of {rows} x {cols} pixels of {settings.pixel_size:g} mm cannot see the face in "
                         f"every frame: it needs at least {cam.shape[0]} x {cam.shape[1]} (rows x cols); enlarge "
                         "it, make the pixels larger, or leave the image size out")
    extra_r, extra_c = rows - cam.shape[0], cols - cam.shape[1]
    return Camera(settings.pixel_size, (rows, cols),
                  (cam.origin[0] - (extra_c // 2) * settings.pixel_size,
                   cam.origin[1] + (extra_r // 2) * settings.pixel_size), settings.working_distance)


def max_step_pixels(camera: Camera, fields) -> float:
    """The largest motion (pixels) of a face point from one frame to the next (frame 0 unloaded)."""
    (ylo, yhi), (zlo, zhi) = FACE_BOUNDS
    g = np.stack(np.meshgrid(np.linspace(ylo, yhi, 17), np.linspace(zlo, zhi, 61), indexing="ij"), -1).reshape(-1, 2)
    prev = np.zeros((len(g), 2))
    step = 0.0
    for f in fields:
        cur = f(g)[:, 1:3]
        step = max(step, float(np.linalg.norm(cur - prev, axis=1).max()))
        prev = cur
    return step / camera.pixel_size


def run_virtual_dic(settings: VirtualDicSettings, out, work_dir=None, progress: bool = True) -> dict:
    """Run the virtual experiment (the module's docstring) and write the recording ``out``.

    Parameters
    ----------
    settings : VirtualDicSettings
        Camera, speckle, engine and load.
    out : path
        The recording to write (.csv or .npz); beside it ``<out>.import.json`` (the import) and
        ``<out>.virtual_dic.json`` (the settings and the error budget).
    work_dir : path, optional
        Where images, the engine's export, the pressure trace and the landmarks go (default:
        ``<out>`` without suffix, + ``_lab``).
    progress : bool
        Print what is being done.

    Returns
    -------
    dict
        The summary written to ``<out>.virtual_dic.json``: settings, camera, engine, timings, the
        import's report, and the error budget (:func:`torchfra.lab.budget.error_budget`).
    """
    from torchfra.io.dic.importer import import_export

    settings.check()
    out = Path(out)
    work = Path(work_dir) if work_dir is not None else out.with_name(out.stem + "_lab")
    work.mkdir(parents=True, exist_ok=True)
    say = print if progress else (lambda *a, **k: None)
    t0 = time.perf_counter()
    times, pressure, fields, solver, sol = face_fields(settings, progress=progress)
    t_fe = time.perf_counter() - t0
    camera = frame_camera(settings, fields)
    speckle = speckle_pattern(FACE_BOUNDS, settings.speckle_size, seed=settings.seed)
    rng = np.random.default_rng(settings.seed + 1)
    say(f"virtual DIC: rendering {settings.frames + 1} images of {camera.shape[0]} x {camera.shape[1]} pixels")
    t1 = time.perf_counter()
    kw = dict(supersample=settings.supersample, noise=settings.grey_noise, rng=rng)
    reference = render(camera, speckle, None, **kw)
    deformed = np.stack([render(camera, speckle, f, **kw) for f in fields])
    t_render = time.perf_counter() - t1
    np.save(work / "reference.npy", reference)
    np.save(work / "deformed_last.npy", deformed[-1])
    roi = face_mask(camera, speckle)
    seed = camera.to_pixels(np.array([[0.0, 3.0]]))[0]  # near the clamped base: the smallest motion
    step = max_step_pixels(camera, fields)
    max_disp = int(min(np.ceil(1.5 * step) + 8, min(camera.shape) // 2 - 1))
    engine = EngineSettings(settings.subset_size, settings.subset_step, max_disp, settings.threads)
    say(f"virtual DIC: pyvale {engine_version()} correlating (subsets {settings.subset_size} px every "
        f"{settings.subset_step} px, frame-to-frame motion up to {step:.1f} px)")
    t2 = time.perf_counter()
    files = correlate(reference, deformed, roi, seed, work / "dic", engine)
    t_dic = time.perf_counter() - t2
    trace, landmarks = _calibration_files(work, camera, times, pressure)
    args = argparse.Namespace(pressure=str(trace), format="pyvale", scale=settings.pixel_size, units=None,
                              pressure_units=None, match="frame", frame_rate=None, first_frame_time=0.0,
                              camera_to_model="register", landmarks=str(landmarks), fit_scale=False, tol=0.5)
    text, info = import_export(files, args, out)
    from torchfra.io.recordings import read_recording

    rec = read_recording(info["out"])
    truth = fe_truth(solver, sol, rec.X)
    yz = rec.X[:, 1:3]
    curvature = _bending(fields[-1], yz)
    budget = error_budget(yz, rec.Z, truth, FACE_BOUNDS, band=settings.subset_size * settings.pixel_size,
                          curvature=curvature, spacing=settings.subset_step * settings.pixel_size)
    summary = {
        "settings": asdict(settings), "camera": {"shape": list(camera.shape), "origin_mm": list(camera.origin),
                                                 "pixel_size_mm": camera.pixel_size,
                                                 "working_distance_mm": camera.working_distance},
        "engine": {"name": "pyvale", "version": engine_version(), **asdict(engine), "files": len(files)},
        "frames": len(times), "pressure_MPa": pressure.tolist(), "points": int(rec.n_points),
        "subsets_in_export": int(info["points_reference"] + len(info["lost_in_reference"])),
        "lost_in_reference": len(info["lost_in_reference"]), "import": text, "recording": str(info["out"]),
        "seconds": {"fe": t_fe, "render": t_render, "correlate": t_dic, "total": time.perf_counter() - t0},
        "max_step_px": step, "budget": budget,
    }
    Path(info["out"]).with_suffix(".virtual_dic.json").write_text(json.dumps(summary, indent=1))
    np.savez(work / "truth.npz", X=rec.X, truth=truth, engine=rec.Z)
    return summary


def fe_truth(solver, sol, X) -> np.ndarray:
    """(K+1, P, 2) FE (uy, uz) mm at reference points X (P, 3) of the face; frame 0 unloaded (zero)."""
    op = ObservationOperator(solver.mesh, solver.faces, points=X, tol=1e-4)
    U = op(sol.u[0, :, : solver.mesh.n_nodes]).numpy()
    return np.concatenate([np.zeros((1,) + U.shape[1:]), U], axis=0)


def _bending(field: FaceField, yz) -> np.ndarray:
    """(P,) magnitude of the second derivatives of (uy, uz) at material points (mm^-1)."""
    parts = [s.ev(yz[:, 0], yz[:, 1], dx=a, dy=b) for s in field.splines[1:] for a, b in ((2, 0), (1, 1), (0, 2))]
    return np.sqrt(np.sum(np.square(parts), axis=0))


def _calibration_files(work: Path, camera: Camera, times, pressure) -> tuple[Path, Path]:
    """The pressure trace (one row per frame) and the landmarks: the face's four corners in the
    reference image (pixels) and on the model (mm), what a camera calibration gives."""
    trace = work / "pressure.csv"
    trace.write_text("frame,time,pressure [MPa]\n" + "".join(
        f"{k},{float(t)!r},{float(p)!r}\n" for k, (t, p) in enumerate(zip(times, pressure))))
    (ylo, yhi), (zlo, zhi) = FACE_BOUNDS
    corners = np.array([[ylo, zlo], [yhi, zlo], [yhi, zhi], [ylo, zhi]])
    px = camera.to_pixels(corners)
    landmarks = work / "landmarks.csv"
    landmarks.write_text("dic_x,dic_y,model_x,model_y,model_z\n" + "".join(
        f"{float(c)!r},{float(r)!r},{FACE_X!r},{float(y)!r},{float(z)!r}\n" for (c, r), (y, z) in zip(px, corners)))
    return trace, landmarks

