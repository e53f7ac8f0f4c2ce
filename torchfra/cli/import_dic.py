"""Import a DIC export and its pressure trace as a recording (DESIGN §6: frame,time,pressure,
point_id,X,Y,Z,uy,uz in the model frame, mm, MPa).

    python scripts/import_dic.py exports/ --pressure pressure.csv --landmarks corners.csv --out runs/recordings/test1.csv
    python scripts/import_dic.py dice_out/ --format dice --scale 0.02 --pressure p.csv --landmarks lm.csv --out rec.csv
    python scripts/import_dic.py clouds/ --units m --camera-to-model identity --pressure p.csv --out rec.csv

Formats (``--format auto`` tells them by their headers): MatchID CSV (2024 and older headers),
VIC-3D CSV, DICe solution files (pixels: give ``--scale`` in mm per pixel), generic ``x,y,z,u,v,w``
point clouds (give ``--units``). One file per frame; the first (by the frame number in the names)
is the undeformed reference.

``--camera-to-model register`` (default) places the reference points on the actuator's front face
(x = +8 mm, y in [-8, 8], z in [0, 60]) by ICP; a flat face fixes only its normal and offset, so
the in-plane placement comes from ``--landmarks`` (a CSV of DIC point -> model point pairs, see
``torchfra.io.dic.exports.read_landmarks``). ``identity`` takes the DIC coordinates as model coordinates
(a coordinate system set up in the DIC software). Either way, points farther than ``--tol`` mm from
the face are dropped (listed by id), the others written at their closest face point, and the
displacements turned into the model frame. Beside the recording, ``<out>.import.json`` keeps the
transform, the residuals and the dropped ids.
"""
import argparse
import sys
import textwrap

from torchfra.cli.flags import Formatter
from torchfra.io.dic.exports import DicError
from torchfra.io.dic.importer import add_arguments, import_export
from torchfra.observation.recording import RecordingError
from torchfra.observation.registration import RegistrationError


def parse(argv):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=Formatter)
    p.add_argument("export", nargs="+", help="directory of per-frame export files, or the files themselves")
    p.add_argument("--out", required=True, help="recording to write (.csv or .npz)")
    add_arguments(p, pressure_required=True)
    p.add_argument("--camera", choices=("+x", "-x"), default="+x",
                   help="the side the camera sees the face from (the actuator's front face x = +8 mm: +x)")
    return p.parse_args(argv)


def convert(a) -> tuple[str, dict]:
    """Import the export of the parsed arguments ``a``: (the report's text, the import's record)."""
    return import_export(a.export, a, a.out)


def main(argv=None) -> int:
    a = parse(argv)
    try:
        text, _ = convert(a)
    except (DicError, RegistrationError, RecordingError, OSError) as exc:
        print(textwrap.fill(f"import_dic: {exc}", width=100), file=sys.stderr)
        return 2
    print(textwrap.fill(text, width=100))
    return 0



if __name__ == "__main__":
    from torchfra.cli.run import run

    run(main)
