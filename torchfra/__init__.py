"""torchfra: ensemble finite element models of soft fiber-reinforced actuators and their calibration."""
__version__ = "0.1.0"
