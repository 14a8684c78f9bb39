"""ROS layer: the only code that touches message fields (conversions, validation, markers)."""
