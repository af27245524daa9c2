"""Build script for the convbki_ros ament_python package (colcon or pip)."""

import os
import subprocess
import sys
from glob import glob

from setuptools import find_packages, setup
from setuptools.command.install import install

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
    ("share/" + package_name + "/config/traversability", _files("config/traversability/*.yaml")),
    ("share/" + package_name + "/config/dds", _files("config/dds/*.xml")),
    # SROS2 policies (docs/security.md): `ros2 security create_permission` reads them from here.
    ("share/" + package_name + "/config/security", _files("config/security/*.xml")),
]
if _files("launch/*.launch.py"):
    # `ros2 launch convbki_ros mapper.launch.py` looks in share/convbki_ros/launch.
    data_files.append(("share/" + package_name + "/launch", _files("launch/*.launch.py")))
if _files("rviz/*.rviz"):
    data_files.append(("share/" + package_name + "/rviz", _files("rviz/*.rviz")))



class InstallWarm(install):
    """``install``, then compile the installed copy's numba kernels into its cache, so that a
    node started right after ``colcon build`` is ready at once instead of compiling for a
    minute. Best effort: a build machine without the run-time dependencies (torch, numba)
    only says so. ``CONVBKI_SKIP_WARM_UP=1`` skips it."""

    def run(self):
        super().run()
        if os.environ.get("CONVBKI_SKIP_WARM_UP"):
            return
        environment = dict(os.environ, PYTHONPATH=os.pathsep.join(filter(None, [self.install_lib,
                                                                               os.environ.get("PYTHONPATH")])))
        # Run from the install folder, so that Python imports the copy just installed.
        result = subprocess.run([sys.executable, "-m", "convbki_core.tools.warm_up"], cwd=self.install_lib,
                                env=environment, stdin=subprocess.DEVNULL, capture_output=True, text=True)
        lines = (result.stdout + result.stderr).strip().splitlines()
        if result.returncode == 0:
            print(lines[-1] if lines else "warm_up: done")
        else:
            print(f"warning: the compiled kernels were not cached at install ({lines[-1] if lines else 'no output'}); "
                  "the node compiles them at its first start instead", file=sys.stderr)


setup(
    cmdclass={"install": InstallWarm},
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
            "mapper = convbki_ros.main:main",
            "kitti_to_bag = convbki_ros.tools.kitti_to_bag:main",
            "play_bag = convbki_ros.tools.play_bag:main",
            "evaluate = convbki_core.tools.evaluate:main",
            "train = convbki_core.tools.train:main",
            "synth = convbki_core.tools.synth:main",
            "label_noise = convbki_core.tools.label_noise:main",
            "bench = convbki_core.tools.bench:main",
            "map_tool = convbki_core.tools.map_tool:main",
            "realtime_check = convbki_ros.tools.realtime_check:main",
        ],
    },
)
