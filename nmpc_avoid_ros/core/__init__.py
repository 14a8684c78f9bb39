"""The controller's core: numpy + CasADi only, no ROS (test/test_core_layering.py keeps it so).

Rooms, each importing only the ones above it (problem <- perception <- config <- nlp <- sample <- loop):

* problem/  what is controlled and avoided: the model type (model.py), model files (model_files.py)
  and the names a config can use (models.py), regions and their penalties, motion of moving
  regions, algebraic expressions (parsed, never eval'd).
* perception/  obstacle regions from what a robot senses: a laser scan or an occupancy grid and the
  robot's pose -> clusters -> circles and wall boxes -> tracks with velocities (sensing.py runs it).
* config/   the settings: one declaration per setting (schema.py), ControllerSettings and the
  params-file format (params_file.py).
* nlp/      the optimisation problem and how it is solved: the multiple-shooting NLP (tracking.py),
  the stage-wise form for FATROP / SQP (stagewise.py), compiled oracles (codegen.py), the ellipse
  tiers (tiers.py), the target's projection onto Y_r (projection.py), the one search over starts
  (search.py) and the child process that lets a solver call be abandoned (worker.py).
* sample/   one controller sample: NmpcController (controller.py), its memory between samples,
  warm start, escape guesses (candidates.py), passage mode, fallback, the result and its status.
* loop/     closed loops offline: plants and run_closed_loop (closed_loop.py), the stability
  certificate, metrics, scene files.

errors.py (the NmpcError family) is shared by every room.

Where to extend it (each is a change in one place):

* a model: a model file (docs/own_model.md): in nmpc_avoid_ros/models/ to ship it, else named by its
  path or registered by another package under the entry points `nmpc_avoid_ros.models`.
* a region kind: a class in problem/regions.py with its slot layout and depth (SlotLayout packs it).
* a setting: one `setting(...)` field in config/settings.py (config/schema.py explains; `make readme`).
* a solver path: SOLVER_PATHS in config/settings.py and its options in nlp/tracking.py make_solver.
* a kind of start for the search: a list of `Start`s in sample/controller.py's `_regular_starts` or
  a phase like `_escape`, solved by nlp/search.py's `search` (never a loop of its own).
"""
