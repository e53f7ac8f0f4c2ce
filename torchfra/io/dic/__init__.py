"""DIC exports: the per-frame files of MatchID, VIC-3D, DICe and generic point clouds (:mod:`.exports`),
and their import as a recording on the model's face with a pressure trace (:mod:`.importer`)."""
from torchfra.io.dic.exports import FORMATS, read_dic, read_landmarks, to_recording
from torchfra.io.dic.importer import import_export
from torchfra.io.tables import DicError

__all__ = ["DicError", "FORMATS", "import_export", "read_dic", "read_landmarks", "to_recording"]
