"""Multi-robot pose graphs on GTSAM: odometry, loop closures, scale variables, solvers, g2o I/O.

    pose_graph     PoseGraph / Edge: robots' keyframe poses (GTSAM Symbol keys), odometry, intra/inter-robot
                   loops with information, confidence and up-to-scale flags; components and their anchors
    g2o            read (SE3:QUAT, SE2) / write (SE3:QUAT) with file:line errors; per-robot files and merge
    dpgo_csv       DPGO's robotN/measurements.csv;  team_files: a team from one g2o per robot, a DGS folder or DPGO's
    confidence     FLOCC eqs. 1-2: correspondence ratio, R_thr gate, logistic p, information * p
    scale_factors  IS loop factor (eqs. 7-8) as gtsam.CustomFactor and batched NumPy; SS smoothing factor
    information    SE-Sync's isotropic weights; policies for non-positive-definite matrices (repair/isotropic/strict)
    formulations   base (eq. 5 + eq. 6 scale) / IS / SS / shared problems; g2o or se-sync (SE-Sync's) objective
    solvers        LM (GTSAM's, or a Python loop over GTSAM's linear solver for scale graphs) and GNC-TLS
    newton         Newton steps for the se-sync objective (the curvature term GN lacks, per-pose HessianFactors)
    init           chordal initialisation; per component the better of it and GTSAM's InitializePose3
    metrics        SE-Sync cost, ATE;  synthetic: FLOCC-like multi-robot teams;  lie: batched SE(3)
    distributed/   every robot solves its own part (per-robot state + plain-data messages; simulated team)
"""
