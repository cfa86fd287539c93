"""ROS 2 without ROS: CDR messages through rosbags' typestore (``messages``), the rmw_zenoh and zenoh-bridge-ros2dds
wire conventions (``wire``), and robot logs (ROS 1 bags, ROS 2 bags, MCAP) read whole (``logs``). docs/ros2.md."""
