"""The dynabrain kernel: World, the module contract, time, the bus, schedule, history, scenarios, CLI."""
