"""Adaptation of a shipped model to the user's own camera (`holo-pose adapt`): BatchNorm statistics of the user's
images, pseudo-labels from the model's own confident fits (or with the robot's joint states), and keypoint
consistency fine-tuning guarded by rendered labelled views. No rclpy; bags are read with rosbags."""
