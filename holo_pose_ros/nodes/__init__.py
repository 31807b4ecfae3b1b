"""ROS 2 nodes: thin wrappers that convert messages (msg_adapters) and call the ROS-free core."""
