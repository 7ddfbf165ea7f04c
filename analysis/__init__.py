"""ballbar.analysis: numbers in, findings out. Pure numpy/scipy, no I/O."""

from .errors import BallbarError, DataError, DetectionError, PlanError
from .plan import AnalysisOptions, MachineConfig, TestPlan

__all__ = [
    "AnalysisOptions",
    "BallbarError",
    "DataError",
    "DetectionError",
    "MachineConfig",
    "PlanError",
    "TestPlan",
]
