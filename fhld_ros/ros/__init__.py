"""ROS 2 plumbing: the lane_detector node, its diagnostics, executor and parameter declarations,
`fhld play`, and the DDS environment that keeps traffic on loopback. Importing this package
needs no rclpy."""
