"""The DIC engine in the loop: pyvale's 2-D subset DIC (``pyvale.dic.calculate_2d``, MIT licence).

pyvale is the optional extra ``virtual-dic`` (~2 GB with its dependencies, never a default
dependency): ``pip install -c constraints-cpu.txt -e ".[virtual-dic]"``. It is imported only here,
when a correlation runs; without it :func:`require_engine` raises :class:`EngineMissing`, whose
message says how to install it.

The engine takes grey levels on the scale of 8-bit images (0..255, float32): on images scaled to
0..1 its reliability-guided scan stops after the seed's neighbours (measured with pyvale 2026.10.2),
so :func:`correlate` scales the images by 255. The reference image is correlated with itself as
the first image, so the export's frame 0 is the engine's own zero (what it reads in an unloaded
specimen) and the importer's reference frame. Large motion is followed frame to frame
(``incremental_update="IMAGE"``: the reference is updated after every image, the reported
displacements still run from the first reference at its subset centres).
"""
from __future__ import annotations

import glob
import os
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

INSTALL = 'pip install -c constraints-cpu.txt -e ".[virtual-dic]"'
GREY_SCALE = 255.0


class EngineMissing(RuntimeError):
    """pyvale is not installed; the message says how to install the extra."""


@dataclass(frozen=True)
class EngineSettings:
    """The correlation's settings: subsets of ``subset_size`` pixels every ``subset_step`` pixels, the
    largest motion between two images the search window covers (pixels), threads (None: all)."""

    subset_size: int = 21
    subset_step: int = 10
    max_displacement: int = 32
    threads: int | None = 1
    shape_function: str = "AFFINE"
    threshold: float = 0.9

    def check(self) -> None:
        """Refuse settings the engine would misuse, naming the setting."""
        if self.subset_size < 5 or self.subset_size % 2 == 0:
            raise ValueError(f"subset size must be an odd number of pixels >= 5, got {self.subset_size}")
        if self.subset_step < 1:
            raise ValueError(f"subset step must be a positive number of pixels, got {self.subset_step}")
        if self.max_displacement < 1:
            raise ValueError(f"max displacement must be a positive number of pixels, got {self.max_displacement}")


def require_engine():
    """``pyvale.dic``, or :class:`EngineMissing` saying how to install it."""
    if "pyvale.dic" in sys.modules:
        return sys.modules["pyvale.dic"]
    here = os.getcwd()
    # importing pyvale opens a log file (plotter_log.log) in the working directory: import it from a
    # scratch folder so that a run leaves none behind
    with tempfile.TemporaryDirectory(prefix="torchfra_pyvale_") as scratch:
        os.chdir(scratch)
        try:
            import pyvale.dic as dic
        except ImportError as exc:
            raise EngineMissing(f"the DIC engine pyvale is not installed ({exc}); install the optional extra: "
                                f"{INSTALL} (about 2 GB; in its own virtual environment if you prefer)") from None
        finally:
            os.chdir(here)
    return dic


def engine_version() -> str:
    """The installed pyvale's version."""
    from importlib.metadata import version

    return version("pyvale")


def correlate(reference: np.ndarray, deformed: np.ndarray, roi: np.ndarray, seed, out_dir,
              settings: EngineSettings = EngineSettings()) -> list[Path]:
    """Correlate the images with pyvale; returns its result files, one per image, in order.

    Parameters
    ----------
    reference : array (rows, cols)
        The reference image, grey levels in [0, 1].
    deformed : array (K, rows, cols)
        The deformed images in time order, grey levels in [0, 1]; the reference is correlated first
        (frame 0 of the export), then these (frames 1..K).
    roi : array (rows, cols) bool
        The region of interest in the reference image.
    seed : (col, row)
        The pixel the reliability-guided scan starts from (inside the ROI, away from its edges).
    out_dir : path
        Where the engine writes its CSV files (emptied of earlier results first).
    settings : EngineSettings
        Subset size and step, search range, threads.

    Returns
    -------
    list of Path
        ``out_dir/dic_results_def_img_0000.csv`` (the reference against itself) to ``..._{K:04d}.csv``.
    """
    dic = require_engine()
    settings.check()
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    for old in glob.glob(str(out_dir / "dic_results_*.csv")):
        Path(old).unlink()
    images = np.concatenate([reference[None], np.asarray(deformed)], axis=0) * GREY_SCALE
    col, row = (int(round(v)) for v in seed)
    if not roi[row, col]:
        raise ValueError(f"the seed pixel (col {col}, row {row}) is not in the region of interest")
    dic.calculate_2d(reference=(reference * GREY_SCALE).astype(np.float32), deformed=images.astype(np.float32),
                     roi_mask=np.asarray(roi, dtype=bool), seed=[(col, row)], subset_size=settings.subset_size,
                     subset_step=settings.subset_step, shape_function=settings.shape_function,
                     threshold=settings.threshold, num_threads=settings.threads,
                     max_displacement=settings.max_displacement, incremental_update="IMAGE",
                     incremental_update_value=1, output_basepath=str(out_dir), output_prefix="dic_results_",
                     print_level=0)
    files = sorted(Path(p) for p in glob.glob(str(out_dir / "dic_results_*.csv")))
    if len(files) != len(images):
        raise RuntimeError(f"pyvale wrote {len(files)} result files for {len(images)} images in {out_dir}")
    return files
