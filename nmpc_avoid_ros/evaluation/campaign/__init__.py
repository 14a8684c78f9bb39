"""The Monte Carlo campaign (`python -m nmpc_avoid_ros campaign`, see cli.py).

Where to extend it (each is a change in one place):

* a scenario family: one `Family` entry in scenarios.FAMILIES (generator, seed code, params
  file, passage test, optional region schedule for regions that move); the command line
  (`--<key>`, `--<key>-steps`, `--<key>-config`), the summary and the plots pick it up.
* a per-run measure: a field in one of scoring.RECORD_SECTIONS (or a new section function),
  plus its line in summary.DEFINITIONS; a measure derived from stored fields goes in
  scoring.classify so that rebuilt summaries use the current definition.
* a summary key: one entry in summary.summarize (and summary.format_summary to print it;
  sweep.SWEEP_KEYS to compare it across a sweep).
* a closed-loop figure (settling, penetration, clearance, ...): core/loop/metrics.py, shared with
  `analyze` and `bench`.
"""
