"""ament_python set-up: colcon installs the executables into lib/nmpc_avoid_ros (see setup.cfg)."""

from glob import glob

from setuptools import find_packages, setup

PACKAGE = "nmpc_avoid_ros"
#: every command of nmpc_avoid_ros/cli.py COMMANDS (test_readme.py keeps README, cli and this list equal)
EXECUTABLES = ("controller", "plant", "recorder", "obstacles", "simulate", "figures", "analyze", "replay", "demo",
               "bench", "campaign", "send")

setup(
    name=PACKAGE,
    version="0.1.0",
    packages=find_packages(exclude=["test", "test.*", "bench"]),
    # the HTML report's script and the uPlot it inlines (bag/report_page.py)
    package_data={f"{PACKAGE}.bag": ["report.js", "vendor/uPlot.iife.min.js", "vendor/uPlot.min.css",
                                     "vendor/uPlot.LICENSE"],
                  # the shipped model files (core/problem/models.py)
                  PACKAGE: ["models/*.yaml"]},
    data_files=[
        ("share/ament_index/resource_index/packages", [f"resource/{PACKAGE}"]),
        (f"share/{PACKAGE}", ["package.xml"]),
        (f"share/{PACKAGE}/config", glob("config/*.yaml") + glob("config/*.rviz") + glob("config/*.json")),
        (f"share/{PACKAGE}/config/scenes", glob("config/scenes/*.yaml")),
        (f"share/{PACKAGE}/config/worlds", glob("config/worlds/*.yaml") + glob("config/worlds/*.pgm")),
        (f"share/{PACKAGE}/launch", glob("launch/*.launch.py")),
    ],
    install_requires=["setuptools"],
    zip_safe=True,
    maintainer="nmpc_avoid_ros developers",
    maintainer_email="dev@nmpc-avoid.local",
    description="Avoidance-aware set-point NMPC for ROS 2 with CasADi",
    license="Apache-2.0",
    tests_require=["pytest"],
    entry_points={
        "console_scripts": [f"{name} = {PACKAGE}.cli:{name}_main" for name in EXECUTABLES],
    },
)
