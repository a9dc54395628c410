"""Pose-graph input and output: g2o files and synthetic pose graphs."""

from ._g2o import load_g2o as load_g2o, save_g2o as save_g2o
from ._gtsam import from_gtsam as from_gtsam, to_gtsam as to_gtsam
from ._pose_graph import make_pose_graph as make_pose_graph, PoseGraph as PoseGraph
from ._synthetic import synthetic_pose_graph_2d as synthetic_pose_graph_2d
