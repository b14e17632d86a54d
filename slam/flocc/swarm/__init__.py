"""Decentralised FLOCC-SLAM robots: messages (`messages`), transports (`transport` in-process, `zenoh_transport`),
rendezvous schedule (`rendezvous`), optimiser election (`election`), the robot node (`node`), the group solve
(`optimiser`), single-process runs (`run`, `outputs`) and one process per robot (`launch`, `clocked`)."""
