"""holo_pose_ros: holistic robot pose (joint states + camera-to-robot pose) from one RGB image.

The ROS-free core lives in the sub-packages; `holo_pose_ros.nodes` holds the thin ROS 2 nodes.
"""

__version__ = "0.1.0"
