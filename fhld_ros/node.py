"""`lane_detector` node (ros2 run fhld_ros lane_detector).

Foundation stage: declares its parameters, logs them and spins; detection is wired in by the
node issue. The math lives in pipeline.py, never here.
"""
from __future__ import annotations

import sys

PARAMETERS: dict[str, tuple[object, str]] = {
    'points_topic': ('points', 'input sensor_msgs/PointCloud2 topic'),
    'odom_topic': ('odom', 'input nav_msgs/Odometry topic (optional)'),
    'lanes_topic': ('lanes', 'output visualization_msgs/MarkerArray topic'),
}


def main(args: list[str] | None = None) -> int:
    import rclpy
    from rcl_interfaces.msg import ParameterDescriptor
    from rclpy.executors import ExternalShutdownException
    from rclpy.node import Node

    class LaneDetectorNode(Node):
        def __init__(self) -> None:
            super().__init__('lane_detector')
            for name, (default, description) in PARAMETERS.items():
                self.declare_parameter(name, default, ParameterDescriptor(description=description))
            values = {name: self.get_parameter(name).value for name in PARAMETERS}
            self.get_logger().info(f'lane_detector started with parameters {values}')

    rclpy.init(args=args)
    node = LaneDetectorNode()
    try:
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
    return 0


if __name__ == '__main__':
    sys.exit(main())
