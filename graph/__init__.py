"""Multi-robot pose graphs on GTSAM: odometry, loop closures, scale variables, solvers, g2o I/O."""
