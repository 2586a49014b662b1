"""Modules shipped with dynabrain: physics cores, signal blocks, sensors, rules."""
