"""Start the ConvBKI mapper (and, on request, RViz).

    ros2 launch convbki_ros mapper.launch.py                       # a robot: live clouds + odometry
    ros2 launch convbki_ros mapper.launch.py use_sim_time:=true    # a bag played with --clock
    ros2 launch convbki_ros mapper.launch.py --show-args           # every argument

See docs/launch.md.
"""

import os

from ament_index_python.packages import PackageNotFoundError, get_package_prefix, get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, LogInfo
from launch.conditions import IfCondition
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node
from launch_ros.parameter_descriptions import ParameterValue

PACKAGE = "convbki_ros"


def _installed(package: str) -> bool:
    """Whether ``package`` is on the ament index (rviz2 is absent where ROS 2 comes from the wheels)."""
    try:
        get_package_prefix(package)
    except PackageNotFoundError:
        return False
    return True


def generate_launch_description() -> LaunchDescription:
    share = get_package_share_directory(PACKAGE)
    params_file = LaunchConfiguration("params_file")
    use_sim_time = LaunchConfiguration("use_sim_time")
    rviz = LaunchConfiguration("rviz")

    arguments = [
        DeclareLaunchArgument("params_file", default_value=os.path.join(share, "config", "mapper.yaml"),
                              description="parameters of the mapper (YAML, `/**:` or `convbki_mapper:` at the top)"),
        DeclareLaunchArgument("namespace", default_value="",
                              description="namespace of the node (its relative topics and services move under it)"),
        DeclareLaunchArgument("use_sim_time", default_value="false", choices=["true", "false"],
                              description="use /clock (a bag played with `play_bag BAG --clock`)"),
        DeclareLaunchArgument("cloud_topic", default_value="/cloud_in",
                              description="labelled sensor_msgs/PointCloud2 input (a relative name follows namespace)"),
        DeclareLaunchArgument("odom_topic", default_value="/odom",
                              description="nav_msgs/Odometry input (a relative name follows namespace)"),
        DeclareLaunchArgument("corrections_topic", default_value="pose_corrections",
                              description="nav_msgs/Path of a SLAM's optimised keyframe poses (docs/slam.md; a "
                              "relative name follows namespace)"),
        DeclareLaunchArgument("log_level", default_value="info",
                              description="log level of the node: debug, info, warn, error or fatal"),
        DeclareLaunchArgument("rviz", default_value="false", choices=["true", "false"],
                              description="also start rviz2 with the package's rviz/convbki.rviz, where rviz2 exists"),
    ]

    mapper = Node(
        package=PACKAGE,
        executable="mapper",
        name="convbki_mapper",
        namespace=LaunchConfiguration("namespace"),
        output="screen",
        # The params file first: a use_sim_time given on the command line wins over the file's.
        parameters=[params_file, {"use_sim_time": ParameterValue(use_sim_time, value_type=bool)}],
        remappings=[("cloud_in", LaunchConfiguration("cloud_topic")), ("odom", LaunchConfiguration("odom_topic")),
                    ("pose_corrections", LaunchConfiguration("corrections_topic"))],
        ros_arguments=["--log-level", LaunchConfiguration("log_level")],
    )

    if _installed("rviz2"):
        viewer = Node(
            package="rviz2",
            executable="rviz2",
            name="rviz2",
            arguments=["-d", os.path.join(share, "rviz", "convbki.rviz")],
            parameters=[{"use_sim_time": ParameterValue(use_sim_time, value_type=bool)}],
            output="screen",
            condition=IfCondition(rviz),
        )
    else:
        # Without rviz2 (e.g. ROS 2 from the PyPI wheels) the mapper still starts; say so once.
        viewer = LogInfo(msg="rviz:=true, but rviz2 is not installed: starting the mapper without RViz",
                         condition=IfCondition(rviz))

    return LaunchDescription([*arguments, mapper, viewer])
