"""A distributed solver for FLOCC's scale-aware pose graphs: every robot solves its own part.

    partition  which poses, loops, scales and separators each robot holds; loop owners; colours
    messages   the estimate a robot sends a neighbour, as bytes (separator poses, owned scales, GNC weights,
               the shared scale's consensus terms)
    robot      one robot's state and step (block-coordinate descent on its part; GNC weights of its loops)
    team       simulated robots in one process: schedule, faults, GNC outer loop, the team's cost and bytes
"""
