"""Perception: obstacle regions from a laser scan or an occupancy grid (no ROS here).

Frames (REP 105; there is no tf2 among the wheels, so the chain is fixed): the robot's pose
(x, y, yaw) in `odom` places `base_link`; the laser frame sits at a fixed offset from `base_link`
(zero unless configured); the regions come out in `odom`, which the controller's robot interface
maps to its `output` plane (ros/robot.py). A grid must be given in `odom` (or in a map frame that
coincides with it: no localisation correction is applied).

The path, each step a library call where one does it well:

    scan.py      ranges -> checked, cleaned points in odom (numpy)
    grid.py      occupancy grid -> occupied cell centres in a window around the robot (numpy)
    fitting.py   points -> clusters (scipy.spatial.cKDTree + scipy.sparse.csgraph) -> circles
                 and thin boxes (the controller's Ellipse and rotated_box shapes)
    tracks.py    regions over time -> stable ids and velocities (scipy.optimize.linear_sum_assignment)
    sensing.py   the pipeline a node calls once per scan or grid window
"""
