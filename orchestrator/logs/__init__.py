"""MCAP logs: the logger (an observer) and its writer process, the schema, reading, verifying by
re-simulation, plotting, the live Foxglove view, recovering a damaged file, and the replay summary.

Imports the kernel and the scenario layer (verify rebuilds a run from its scenario), nothing above.
"""
