"""hvo_graph: homography-based visual odometry fused in a GTSAM factor graph."""

__version__ = "0.1.0"
