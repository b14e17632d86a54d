"""The GRAND-SLAM team with its agents and server in separate processes, over Zenoh: link messages, the agent's
and the server's nodes, and the drivers (`swarmsplat server`, `swarmsplat agent --server`, `run --processes`)."""
