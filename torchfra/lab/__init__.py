"""The virtual laboratory: a DIC experiment on the FE model with a real DIC engine in the loop.

:mod:`.camera` maps the camera's pixels to mm on the front face, :mod:`.speckle` paints a speckle
pattern on the face and renders it deformed by the FE solution, :mod:`.engine` runs the DIC engine
(pyvale, the ``virtual-dic`` extra) on the images, :mod:`.budget` measures the engine's error
against the FE truth, and :mod:`.experiment` puts them together into a recording.
"""
