"""Thinking with the simulator: batches of imagined futures (`Batch`: serial, processes, Ray).

Imports the kernel and the scenario layer, nothing above (the bridge and the CLI sit on top).
"""

from .batch import BACKENDS, Batch, BatchResult
from .branch import BranchOutcome, BranchStatus, BranchTask, run_branch

__all__ = ["BACKENDS", "Batch", "BatchResult", "BranchOutcome", "BranchStatus", "BranchTask", "run_branch"]
