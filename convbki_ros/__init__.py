"""ROS 2 front end of ConvBKI: the mapper node, PointCloud2 codec and rosbag2 tools."""
