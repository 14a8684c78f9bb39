"""`python -m nmpc_avoid_ros <command>`: every executable of the package, with or without ROS."""

import sys

from .cli import main

sys.exit(main())
