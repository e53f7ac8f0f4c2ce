"""Abaqus/CalculiX input decks: :func:`read_inp` builds a model from a deck (:mod:`.read`: the cards it
reads and the ones it refuses), :func:`write_inp` writes a model as a deck CalculiX solves
(:mod:`.write`), :func:`run_calculix` runs ``ccx`` on it and :func:`read_dat_displacements` reads the
displacements back."""
from torchfra.io.abaqus.read import InpError, InpIds, read_inp
from torchfra.io.abaqus.write import CalculixError, read_dat_displacements, run_calculix, write_inp

__all__ = ["CalculixError", "InpError", "InpIds", "read_dat_displacements", "read_inp", "run_calculix", "write_inp"]
