"""Writes the pyvale export beside this file: a speckled 8 x 6 mm face at 0.1 mm per pixel, its
reference image and the image displaced by the affine field of ``truth.json``, correlated by pyvale
(the ``virtual-dic`` extra). Run from the repository root: ``python tests/data/pyvale/make_export.py``."""
import json
from pathlib import Path

import numpy as np

from torchfra.lab.camera import Camera
from torchfra.lab.engine import EngineSettings, correlate, engine_version
from torchfra.lab.speckle import FaceField, face_mask, render, speckle_pattern

HERE = Path(__file__).parent
BOUNDS = ((-4.0, 4.0), (0.0, 6.0))
A = [[0.02, -0.01], [0.015, -0.03]]  # d(uy, uz)/d(y, z)
B = [0.35, -0.22]  # mm

if __name__ == "__main__":
    camera = Camera.framing(0.1, (-5.0, 5.0), (-1.0, 7.0))
    speckle = speckle_pattern(BOUNDS, 0.4, seed=3)
    rng = np.random.default_rng(4)
    ref = render(camera, speckle, None, noise=0.005, rng=rng)
    deformed = render(camera, speckle, FaceField.affine(BOUNDS, A, B), noise=0.005, rng=rng)
    seed = camera.to_pixels(np.array([[0.0, 3.0]]))[0]
    files = correlate(ref, deformed[None], face_mask(camera, speckle), seed, HERE, EngineSettings(max_displacement=16))
    (HERE / "truth.json").write_text(json.dumps({
        "engine": f"pyvale {engine_version()}", "pixel_size_mm": camera.pixel_size, "origin_mm": list(camera.origin),
        "shape": list(camera.shape), "A": A, "b_mm": B, "files": [f.name for f in files],
        "note": "file 0: the reference image against itself; file 1: the image displaced by uyz = A @ (y, z) + b"},
        indent=1) + "\n")
