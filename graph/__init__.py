"""Multi-robot pose graphs on GTSAM: odometry, loop closures, scale variables, solvers, g2o I/O.

    pose_graph     PoseGraph / Edge: robots' keyframe poses (GTSAM Symbol keys), odometry, intra/inter-robot
                   loops with information, confidence and up-to-scale flags; components and their anchors
    g2o            read (SE3:QUAT, SE2) / write (SE3:QUAT) with file:line errors; per-robot files and merge
    confidence     FLOCC eqs. 1-2: correspondence ratio, R_thr gate, logistic p, information * p
    scale_factors  IS loop factor (eqs. 7-8) as gtsam.CustomFactor and batched NumPy; SS smoothing factor
    formulations   base (eq. 5 + eq. 6 scale) / IS / SS / shared problems
    solvers        LM (GTSAM's, or a Python loop over GTSAM's linear solver for scale graphs) and GNC-TLS
    init           chordal initialisation per connected component; spanning-tree composition
    metrics        SE-Sync cost, ATE;  synthetic: FLOCC-like multi-robot teams;  lie: batched SE(3)
"""
