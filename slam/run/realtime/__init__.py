"""Real-time mode of `swarmsplat run` (`--realtime`, config `runtime`): a sequence's frames arrive at the sensor's
rate (feed), one agent tracks each frame it can take in time on the calling thread and maps keyframes on a worker
thread beside it (agent), and the run writes what a run writes plus the latency and throughput it measured (run,
summary)."""
