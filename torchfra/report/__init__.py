"""Reports of runs: TensorBoard logging and figures (``tensorboard.py``)."""
