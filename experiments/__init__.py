"""Policy evaluation in the world model against the simulator, statistics, reports, sweeps: not built yet."""
