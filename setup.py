"""Build script for the convbki_ros ament_python package (colcon or pip)."""

from glob import glob

from setuptools import find_packages, setup

package_name = "convbki_ros"


def _files(pattern: str) -> list[str]:
    """Sorted files matching ``pattern``, so files added later install too."""
    return sorted(glob(pattern))


data_files = [
    # Marker that puts the package on the ament index (what `ros2 run` and
    # ament_index_python.get_package_prefix look up).
    ("share/ament_index/resource_index/packages", ["resource/" + package_name]),
    ("share/" + package_name, ["package.xml"]),
    ("share/" + package_name + "/config", _files("config/*.yaml")),
    ("share/" + package_name + "/config/kernels", _files("config/kernels/*.yaml")),
    ("share/" + package_name + "/config/dds", _files("config/dds/*.xml")),
]
if _files("rviz/*.rviz"):
    data_files.append(("share/" + package_name + "/rviz", _files("rviz/*.rviz")))

setup(
    name=package_name,
    version="0.1.0",
    packages=find_packages(
        include=["convbki_core", "convbki_core.*", "convbki_ros", "convbki_ros.*"],
        exclude=["test", "test.*"],
    ),
    data_files=data_files,
    install_requires=["setuptools"],
    zip_safe=True,
    maintainer="convbki_ros maintainers",
    maintainer_email="maintainers@convbki-ros.dev",
    description="ConvBKI online 3D semantic mapping from labelled LiDAR, for ROS 2",
    license="Apache-2.0",
    entry_points={
        "console_scripts": [
            "mapper = convbki_ros.mapper:main",
            "kitti_to_bag = convbki_ros.tools.kitti_to_bag:main",
            "play_bag = convbki_ros.tools.play_bag:main",
            "evaluate = convbki_core.tools.evaluate:main",
            "train = convbki_core.tools.train:main",
            "synth = convbki_core.tools.synth:main",
            "bench = convbki_core.tools.bench:main",
            "map_tool = convbki_core.tools.map_tool:main",
            "realtime_check = convbki_ros.tools.realtime_check:main",
        ],
    },
)
