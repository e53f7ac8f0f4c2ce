"""A virtual DIC experiment: the FE actuator filmed through a speckle pattern, correlated by pyvale.

    torchfra virtual-dic --out runs/virtual_dic/recording.csv
    torchfra virtual-dic --pixel-size 0.2 --speckle-size 0.8 --frames 4 --peak-pressure 0.011 --out rec.csv
    torchfra virtual-dic --grey-noise 0.02 --subset 31 --step 10 --working-distance 300 --out rec.csv

The paper's actuator (C10 ``--c10``, no gravity) is solved along a pressure ramp (``--frames``
loaded frames up to ``--peak-pressure`` MPa, plus the unloaded one); a speckle pattern (dots of
``--speckle-size`` mm) painted on its front face is rendered by a camera of ``--pixel-size`` mm per
pixel (the image framed to see the face in every frame, or ``--image-size ROWSxCOLS``; a pinhole
at ``--working-distance`` mm turns out-of-plane motion into a magnification change; telecentric
without it) with grey-level noise ``--grey-noise`` (std as a fraction of the grey range, 8-bit
images); pyvale correlates the images (subsets of ``--subset`` pixels every ``--step``); its export
is imported as a recording (``torchfra import-dic``'s importer, the face corners as landmarks). The
summary gives the engine's error against the FE truth: bias and RMS in the interior, in the edge
band (one subset wide) and where the field bends most, and the error's correlation length.
Written: the recording ``--out``, ``<out>.import.json``, ``<out>.virtual_dic.json`` (settings and
error budget) and, in ``<out stem>_lab/``, the images, the engine's export, the pressure trace and
the landmarks.

pyvale is the optional extra ``virtual-dic``: ``pip install -c constraints-cpu.txt -e ".[virtual-dic]"``.
Without it the command says so and exits 2.
"""
from __future__ import annotations

import argparse
import sys
import textwrap
from pathlib import Path

from torchfra.cli.flags import Formatter, add_peak_pressure, add_resolution


def _image_size(text: str) -> tuple[int, int]:
    try:
        rows, cols = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"image size must be ROWSxCOLS in pixels, e.g. 700x560, got {text!r}") from None
    return rows, cols


def parse(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(prog="torchfra virtual-dic", description=__doc__,
                                formatter_class=Formatter)
    p.add_argument("--out", required=True, help="recording to write (.csv or .npz)")
    p.add_argument("--pixel-size", type=float, default=0.1, help="mm per pixel on the face (default 0.1)")
    p.add_argument("--image-size", type=_image_size, default=None, metavar="ROWSxCOLS",
                   help="image size in pixels (default: framed to see the face in every frame)")
    p.add_argument("--working-distance", type=float, default=None,
                   help="pinhole camera at this distance from the face, mm (default: telecentric)")
    p.add_argument("--speckle-size", type=float, default=0.4, help="speckle dot diameter, mm (default 0.4)")
    p.add_argument("--grey-noise", type=float, default=0.01,
                   help="grey-level noise std, fraction of the grey range (default 0.01)")
    p.add_argument("--subset", type=int, default=21, help="subset size, pixels (odd; default 21)")
    p.add_argument("--step", type=int, default=10, help="subset step, pixels (default 10)")
    p.add_argument("--frames", type=int, default=10, help="loaded frames of the pressure ramp (default 10)")
    add_peak_pressure(p, 0.022, "top of the pressure ramp, MPa")
    p.add_argument("--c10", type=float, default=0.0048, help="C10 of the body, MPa (default 0.0048)")
    add_resolution(p)
    p.add_argument("--seed", type=int, default=0, help="seed of the speckle pattern and the noise")
    p.add_argument("--threads", type=int, default=1, help="threads of the FE solve and the engine")
    a = p.parse_args(argv)
    if Path(a.out).suffix.lower() not in (".csv", ".npz"):
        p.error(f"--out must end in .csv or .npz, got {a.out!r}")
    return a


def summary_text(s: dict) -> str:
    """The error budget as a few lines of text."""
    b = s["budget"]
    um = 1e3

    def row(name):
        r = b["regions"][name]
        if r["bias_mm"][0] is None:
            return f"  {name:<13} no point observed"
        bias, rms = r["bias_mm"], r["rms_mm"]
        return (f"  {name:<13} {b['points'][name]:>5} points  bias uy {bias[0] * um:+7.2f} uz {bias[1] * um:+7.2f} um"
                f"   RMS uy {rms[0] * um:6.2f} uz {rms[1] * um:6.2f} um   observed {100 * r['observed']:.1f} %")

    cam = s["camera"]
    lines = [
        f"virtual DIC: {s['frames']} frames, camera {cam['shape'][0]} x {cam['shape'][1]} pixels of "
        f"{cam['pixel_size_mm']:g} mm, pyvale {s['engine']['version']} (subset {s['engine']['subset_size']} px, "
        f"step {s['engine']['subset_step']} px): {s['points']} points "
        f"({s['lost_in_reference']} subsets lost in the reference), {s['seconds']['total']:.0f} s",
        f"engine - FE truth over the loaded frames (edge band {b['band_mm']:g} mm):",
        *(row(n) for n in ("interior", "edge", "high_gradient", "all") if n in b["regions"]),
        f"  error correlation length {b['correlation_length_mm']:.2f} mm (squared-exponential fit)",
        f"recording: {s['recording']}",
    ]
    return "\n".join(lines)


def main(argv=None) -> int:
    a = parse(argv)
    from torchfra.lab.engine import EngineMissing, require_engine

    try:
        require_engine()
    except EngineMissing as exc:
        print(textwrap.fill(f"virtual-dic: {exc}", width=100), file=sys.stderr)
        return 2
    import torch

    from torchfra.lab.experiment import VirtualDicSettings, run_virtual_dic

    torch.set_default_dtype(torch.float64)
    torch.set_num_threads(a.threads)
    settings = VirtualDicSettings(pixel_size=a.pixel_size, image_size=a.image_size, speckle_size=a.speckle_size,
                                  grey_noise=a.grey_noise, subset_size=a.subset, subset_step=a.step,
                                  frames=a.frames, pressure=a.peak_pressure, c10=a.c10, resolution=a.resolution,
                                  working_distance=a.working_distance, seed=a.seed, threads=a.threads)
    settings.check()
    Path(a.out).parent.mkdir(parents=True, exist_ok=True)
    summary = run_virtual_dic(settings, a.out)
    print(summary_text(summary))
    return 0


if __name__ == "__main__":
    from torchfra.cli.run import run

    run(main)
