"""torchfra: ensemble finite element models of soft fiber-reinforced actuators and their calibration."""
__version__ = "0.1.0"

from torchfra.runtime.allocator import keep_freed_memory as _keep_freed_memory

_keep_freed_memory()
