"""Offline trajectory estimation with aefabmap's loop closures (`aefabmap slam`, extra ``aefabmap[slam]``).

RGB-D visual odometry (ORB + depth, PnP RANSAC), loop-closure edges from the detector's verified
loops (PnP on the verified matches), pose-graph optimisation (gtsam, robust kernel), trajectory
metrics (evo). A laptop tool: the board runtime (aefabmap_runtime) never imports
this package, gtsam or evo (pyproject.toml's import contracts, tests/test_house.py).

Poses are 4x4 float64 camera-to-world matrices (TUM convention: x right, y down, z forward in the
camera); ``T_a_b`` maps points of frame b into frame a.
"""
