"""Thinking with the simulator: batches of imagined futures (`Batch`: serial, processes, Ray) and
planning by simulating them (`search`: A* whose children are evaluated as one batch).

Imports the kernel and the scenario layer, nothing above (the bridge and the CLI sit on top).
"""

from ..kernel.branch import BranchOutcome, BranchStatus, BranchTask, run_branch
from .batch import BACKENDS, Batch, BatchResult
from .plan import Action, Outcome, Plan, PlanStats, search

__all__ = ["BACKENDS", "Action", "Batch", "BatchResult", "BranchOutcome", "BranchStatus", "BranchTask", "Outcome",
           "Plan", "PlanStats", "run_branch", "search"]
