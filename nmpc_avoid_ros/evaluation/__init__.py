"""The evaluation layer: Monte Carlo campaigns (and the benchmark beside it, nmpc_avoid_ros/bench).

Layering: core <- ros <- bag <- evaluation. Evaluation code never imports the ROS nodes.
Everything here drives closed loops through the one driver, `core.closed_loop.ClosedLoop`
(any `Stepper`: NmpcController, a benchmark peer), and scores them with the one metrics module,
`core.metrics` (which lives in core so that the bag layer's `analyze` shares it).

    evaluation/campaign/scenarios.py     families and their scenario generators
    evaluation/campaign/reachability.py  Y_r, best reachable/admissible points, passages
    evaluation/campaign/scoring.py       one run -> its record
    evaluation/campaign/summary.py       a family's records -> its summary, definitions
    evaluation/campaign/running.py       where scenarios run (serial, process pool, Dask), resume
    evaluation/campaign/cli.py           `python -m nmpc_avoid_ros campaign`
    evaluation/campaign/sweep.py         --sweep: one run-time setting over several values
    evaluation/campaign/plots.py         the summary figures
"""
