"""Local-minimum escape (core/sample/candidates.py) and the fallback choice (core/sample/fallback.py).

The regression scenes come from the campaign (docs/campaign): an ellipse across the steady states
between y_a and the target, where the shifted warm start rested in front of it, and vdp-0012,
where u = 0 after a failed cold start drove van der Pol to |x1 x2| - 2 = 4.11.
"""

from __future__ import annotations

import numpy as np
import pytest
from conftest import PAPER_STEPS, PAPER_TARGET, PAPER_X0

from nmpc_avoid_ros.core.config.settings import ControllerSettings
from nmpc_avoid_ros.core.errors import InputError
from nmpc_avoid_ros.core.loop.closed_loop import run_closed_loop
from nmpc_avoid_ros.core.nlp.search import Candidate, Outcome, SearchReport, plan_cost, search
from nmpc_avoid_ros.core.problem.regions import Ellipse
from nmpc_avoid_ros.core.sample.candidates import Guess
from nmpc_avoid_ros.core.sample.controller import NmpcController
from nmpc_avoid_ros.core.sample.guess_starts import escape_admission, guess_start

#: an ellipse across x2 = 0 (steady states x1 in [2.95, 3.45]) whose top is only 0.05 above the
#: axis: from x0 = (-5, 0) towards y_t = 7.9 (best reachable 5.94) the loop rested at x1 = 2.95
BLOCKER = Ellipse((3.2, -0.5), (0.6, 0.55))

#: campaign vdp-0012 (seed 0): the first solve fails (IPOPT iteration budget) from this state
VDP_0012 = {"x0": [3.612622975901772, -0.2557715699357259], "target": [-3.8509723195550993],
            "ellipses": [((-5.59769407385972, 0.7514897718812881), (0.4315736358819213, 0.7611778116913936),
                          0.9707573865612938),
                         ((1.2891068448049152, -1.0404584763788542), (1.1592269895894767, 0.6158543360680077),
                          0.55044698684034),
                         ((1.533889411453755, 1.133193542806174), (1.236436510084207, 0.5170351578878774),
                          2.1357439901144017)]}


def keep_in_penetration(x: np.ndarray) -> float:
    return float(np.max(np.abs(x[:, 0] * x[:, 1])) - 2.0)


def test_an_ellipse_across_the_steady_states_is_passed_not_rested_in_front_of():
    controller = NmpcController(ControllerSettings(max_solve_time=2.0))
    results = []
    run = run_closed_loop(controller, [-5.0, 0.0], [7.9], 60, regions=lambda k: [BLOCKER] if k == 0 else None,
                          on_step=lambda k, res: results.append(res))
    best = 6.0 * controller.settings.steady_state_scale
    assert run.x[-1, 0] == pytest.approx(best, abs=0.05), "rested in front of the ellipse (today's x1 = 2.95)"
    assert max(BLOCKER.depth(x) for x in run.x) <= 1e-3
    escapes = [r.search.kept for r in results if r.search.guesses_tried]
    assert escapes and escapes[0].startswith("beyond"), escapes
    assert set(run.status) == {"ok"}


#: campaign vdp-0079 (seed 0): classified 'local_minimum' (rested at x1 = -2.899 instead of -3.493)
VDP_0079 = {"x0": [0.7781711002665253, 1.9193882725293236], "target": [-3.4931632816011557],
            "ellipses": [((-2.6436468312843604, 0.49702687896775144), (0.9726206021818167, 0.1627745497466755),
                          0.8520174526282402),
                         ((2.1703360475329188, 0.8434551236070367), (1.0745344566557002, 0.531707395506517),
                          1.2475413533251438),
                         ((-0.9565638954995075, 1.1147243426397264), (1.124870941552013, 0.2701970797567176),
                          2.7740103985630418)]}


def test_campaign_local_minimum_scene_reaches_the_target():
    """vdp-0079 of the campaign: the shifted warm start rested at x1 = -2.899 (target -3.493, free)."""
    regions = [Ellipse(c, a, yaw) for c, a, yaw in VDP_0079["ellipses"]]
    controller = NmpcController(ControllerSettings(max_solve_time=2.0))
    run = run_closed_loop(controller, VDP_0079["x0"], VDP_0079["target"], 40,
                          regions=lambda k: regions if k == 0 else None)
    # the escape (in the step's search report): a guess beyond the ellipse, cheaper than the stalled
    # shifted plan and no deeper, is applied; a guess that predicts more penetration is refused
    escapes = [report for report in run.searches if report.phase == "escape"]
    assert escapes and escapes[0].guess_taken, [r.render() for r in escapes]
    lines = {t.label: t for t in escapes[0].tried}
    kept, base = lines[escapes[0].kept], lines["shifted"]
    assert (kept.outcome, base.outcome) == (Outcome.KEPT, Outcome.WORSE), escapes[0]
    assert kept.cost < base.cost and kept.depth <= base.depth + 1e-4, escapes[0]
    assert any(t.outcome is Outcome.REFUSED and t.refusal == "penetrates more" for t in escapes[0].tried), escapes[0]
    assert run.x[-1, 0] == pytest.approx(VDP_0079["target"][0], abs=0.05)
    assert max(e.depth(x) for e in regions for x in run.x) <= 1e-3
    assert keep_in_penetration(run.x) <= 1e-3


@pytest.mark.parametrize("escape_horizon", [0, 10])
@pytest.mark.parametrize("mu,plant", [(0.0, "euler"), (1e8, "euler"), (0.0, "continuous"), (1e8, "continuous")])
def test_the_paper_loops_never_trigger_an_escape_or_a_fallback(paper, mu, plant, escape_horizon):
    """Step-for-step the paper's loops, also with the passage mode on (the shipped van_der_pol.yaml's 10)."""
    controller = NmpcController(ControllerSettings(mu=mu, escape_horizon=escape_horizon))
    results = []
    run = run_closed_loop(controller, PAPER_X0, PAPER_TARGET, PAPER_STEPS, plant,
                          on_step=lambda k, res: results.append(res))
    assert not any(r.search.guesses_tried or r.is_fallback for r in results)
    assert all(r.horizon == 5 for r in results)
    np.testing.assert_array_equal(run.x, paper(mu, plant).x)


def solved(label: str, nlp, w: np.ndarray, cost: float, depth: float) -> Candidate:
    """A plan as a search candidate (solved, usable) with the given cost and predicted depth."""
    return Candidate(label, nlp, w, np.zeros(nlp.layout.n_w), np.zeros(nlp.lbg.size), "Solve_Succeeded", 1, 0.0,
                     True, True, False, True, cost, depth)


def escape(nlp, x, par, base, guesses, time_left):
    """`search` (core/nlp/search.py) over the guesses, `base` competing, under the escape's admission
    (guess_starts.escape_admission: no deeper than the base)."""
    report = SearchReport()
    best, _, spent = search([guess_start(nlp, x, par, g) for g in guesses], par, time_left, report, "escape", 1e-6,
                            base=base, admit=escape_admission(base))
    return best, report.tried, spent


def test_the_escape_keeps_the_cheaper_plan_and_refuses_one_that_buys_progress_with_penetration():
    controller = NmpcController(ControllerSettings())
    controller.set_regions([BLOCKER])
    x, y_t = np.array([2.95, 0.0]), np.array([7.9])
    nlp, par = controller.nlp, controller.parameters(x, y_t)
    # the stalled plan: solved from a guess resting in front of the ellipse
    w0 = nlp.fill_slacks(nlp.layout.join_w(np.zeros((5, 1)) + 2.95, np.tile(x, (5, 1)), np.array([2.95]), None), par)
    w = nlp.solve(w0, par, np.zeros(nlp.layout.n_w), np.zeros(nlp.lbg.size))[0]
    base = solved("shifted", nlp, w, plan_cost(nlp, w, par), nlp.max_depth(w, par))
    stalled_y_a = nlp.layout.y_a(w)
    assert stalled_y_a[0] < 2.96
    beyond = controller.escape.guesses(x, stalled_y_a, y_t, par, controller.regions)
    assert [g.label for g in beyond][:1] == ["beyond0"] and beyond[0].y_a[0] > 3.45
    best, tried, _ = escape(nlp, x, par, base, beyond[:1], 1.0)
    assert best is not base and best.cost < base.cost and best.depth <= base.depth + 1e-4, tried
    # a guess straight through the ellipse with a penalty weight too small to keep out: cheaper,
    # but it penetrates, so it is refused
    par_cheap = par.copy()
    par_cheap[4] = 1.0  # mu
    through = Guess("through", np.array([5.0]), np.column_stack([np.linspace(3.2, 5.0, 5), np.full(5, 0.5)]),
                    np.zeros((5, 1)))
    base_cheap = solved("shifted", nlp, w, plan_cost(nlp, w, par_cheap), base.depth)
    kept, tried, _ = escape(nlp, x, par_cheap, base_cheap, [through], 1.0)
    assert kept is base_cheap and tried[-1].outcome is Outcome.REFUSED and tried[-1].refusal == "penetrates more", tried
    # no time left: the first guess is solved (the budget rule starts one), no further one
    kept, tried, spent = escape(nlp, x, par, base, beyond, 0.0)
    assert len(beyond) > 1 and all(t.outcome is Outcome.NOT_TRIED for t in tried[1:]), tried


def test_no_escape_without_a_region_across_the_way():
    controller = NmpcController(ControllerSettings())
    x, y_t = np.array([-5.0, 0.0]), np.array([5.0])
    controller.set_regions([Ellipse((0.0, 1.5), (0.5, 0.3))])  # above the axis: no steady state inside
    par = controller.parameters(x, y_t)
    assert controller.escape.beyond_blocks(np.array([-5.0]), y_t, par) == []
    assert not controller.escape.should_try(np.array([-5.0]), np.array([-5.0]), y_t, par)


def vdp_0012_regions() -> list[Ellipse]:
    return [Ellipse(c, a, yaw) for c, a, yaw in VDP_0012["ellipses"]]


def test_failed_cold_start_applies_the_recovery_input_not_u0_and_stays_inside():
    """vdp-0012: u = 0 after the failed cold start reached |x1 x2| - 2 = 4.11; now <= 1e-3."""
    controller = NmpcController(ControllerSettings(max_solve_time=5.0))
    results = []
    run = run_closed_loop(controller, VDP_0012["x0"], VDP_0012["target"], 20,
                          regions=lambda k: vdp_0012_regions() if k == 0 else None,
                          on_step=lambda k, res: results.append(res))
    first = results[0]
    assert first.status == "fallback_recovery", first.fallback_reason
    assert first.fallback_predicted["safe"] == pytest.approx(4.11, abs=5e-3) and first.predicted_violation <= 1e-3
    assert keep_in_penetration(run.x) <= 1e-3
    assert all(r.status == "ok" for r in results[1:])


def test_fallback_candidates_are_chosen_by_predicted_violation():
    controller = NmpcController(ControllerSettings())
    fallback = controller.fallback
    par = controller.parameters(np.zeros(2), np.array([5.0]))
    # at the origin u = 0 keeps van der Pol at rest: the safe input, no recovery solve
    choice = fallback.choose(np.zeros(2), par, None, None, False)
    assert choice.kind == "safe" and choice.violation == 0.0 and choice.solve_time == 0.0
    # a plan whose inputs leave the region is kept over a steady input that does not
    x = np.array([3.6, -0.3])
    leaving = fallback.recover(x, par, np.zeros((5, 1)))[0]
    choice = fallback.choose(x, par, leaving, np.array([0.0]), True)
    assert choice.kind == "shift" and choice.violation <= 1e-3, choice.reason
    # with the plan used up, the steady input (which predicts a violation) loses to the recovery
    choice = fallback.choose(x, par, leaving, np.array([0.0]), False)
    assert choice.kind == "recovery" and choice.violation < fallback.predict(x, np.zeros((5, 1)), par)[1]
    # a configured safe input that holds the state is preferred to a steady input that does not
    controller.set_safe_input(leaving[0])
    choice = fallback.choose(x, par, None, np.array([6.0]), False)
    assert choice.kind in ("safe", "recovery") and "steady" in choice.reason
    with pytest.raises(InputError, match="input box"):
        controller.set_safe_input([7.0])


def test_robot_escape_guesses_detour_around_an_output_frame_ellipse_and_a_penetrating_plan_is_replaced():
    settings = ControllerSettings(model="double_integrator_2d", sample_time=0.25, horizon=10, discretization="rk4",
                                  state_min=(-10.0, -10.0, -1.5, -1.5), state_max=(10.0, 10.0, 1.5, 1.5),
                                  input_min=(-1.0, -1.0), input_max=(1.0, 1.0), keep_in=(),
                                  state_weights=(1.0, 1.0, 0.1, 0.1), input_weights=(0.5, 0.5), kappa=100.0, mu=1e5)
    controller = NmpcController(settings)
    wall = Ellipse((0.0, 0.0), (0.5, 2.0), 0.0, "output")
    controller.set_regions([wall])
    x, y_t = np.array([-2.0, 0.0, 0.0, 0.0]), np.array([3.0, 0.0])
    par = controller.parameters(x, y_t)
    guesses = controller.escape.guesses(x, np.array([-2.0, 0.0]), y_t, par, controller.regions)
    labels = [g.label for g in guesses]
    assert labels == ["beyond0", "beyond0_left_of_region0", "beyond0_right_of_region0"], labels
    assert guesses[0].y_a[0] > 0.5  # beyond the wall
    detour_y = [g.states[:, 1].max() if "left" in g.label else g.states[:, 1].min() for g in guesses[1:]]
    assert detour_y[0] > 2.0 and detour_y[1] < -2.0  # around either end of the wall
    # a plan heading straight into the wall is replaced by a candidate that avoids it
    inside_soon = np.tile([1.0, 0.0], (10, 1))  # straight into the wall
    choice = controller.fallback.check_plan(x, par, inside_soon)
    assert choice is not None and choice.kind in ("safe", "recovery") and not choice.unavoidable, choice


#: campaign vdp-0097 (seed 0): the first solved plan rests at x1 = -2.84, the centre of ellipse 0,
#: where g = 1 - r^2 has no gradient (predicted depth 0.83); overridden by fallbacks for a few samples,
#: then applied: penetration 0.80 after the first step
VDP_0097 = {"x0": [-0.953040447178152, 1.2391775655029282], "target": [-5.524784058754916],
            "ellipses": [((-3.0814213566820685, -0.11743639460530941), (0.8551149919806487, 0.6216793404971585),
                          2.5198647149193243),
                         ((0.2705538793153215, -1.6127433281940355), (0.3276254175019541, 0.18340382067034627),
                          2.2579828671827036),
                         ((-2.5839069192943676, -0.04142387230021072), (1.2022249840685009, 0.17938126989283573),
                          2.283507788492194)]}


def test_a_plan_resting_at_an_ellipse_centre_is_replaced_by_a_clear_one_at_once():
    regions = [Ellipse(c, a, yaw) for c, a, yaw in VDP_0097["ellipses"]]
    controller = NmpcController(ControllerSettings(max_solve_time=2.0))
    results = []
    run = run_closed_loop(controller, VDP_0097["x0"], VDP_0097["target"], 30,
                          regions=lambda k: regions if k == 0 else None, on_step=lambda k, res: results.append(res))
    first = results[0]
    assert first.status == "ok" and first.search.guess_taken, first.search
    assert max(e.depth(x) for e in regions for x in first.states) <= 1e-3
    assert max(e.depth(x) for e in regions for x in run.x) <= 1e-3, "today: 0.80 after the first step"
    assert keep_in_penetration(run.x) <= 1e-3
    assert not any(r.is_fallback for r in results)


#: campaign robot-0049 (seed 0): the robot starts below a gap between two ellipses; every solved plan
#: squeezed through it (depth 0.15, with mu = 1e5 or 1e6), so the safe input held it for N samples,
#: then one plan was applied, and so on: 81 fallbacks and penetration 0.166
ROBOT_0049 = {"x0": [-3.790464243694913, 1.1099982604979832, 0.1154911022448991, 0.15450748089762606],
              "target": [-5.741518639362529, 5.965017181961315],
              "ellipses": [((-2.9415523735820113, 3.0871437037003293), (1.3194439879405677, 1.5856281900243618),
                            0.37744803779304426),
                           ((-5.255023735230951, 4.031896750587386), (1.1820124512004153, 1.3017882649598675),
                            0.8753497069895746)]}


def test_a_plan_squeezing_between_two_ellipses_is_replaced_by_a_clear_one_that_makes_progress():
    from rosgraph import ROOT

    from nmpc_avoid_ros.core.config.settings import load_params_file

    params = load_params_file(ROOT / "config" / "mobile_robot.yaml").section("controller")
    controller = NmpcController(ControllerSettings.from_params(params))
    regions = [Ellipse(c, a, yaw, "output") for c, a, yaw in ROBOT_0049["ellipses"]]
    results = []
    run = run_closed_loop(controller, ROBOT_0049["x0"], ROBOT_0049["target"], 40,
                          regions=lambda k: regions if k == 0 else None, on_step=lambda k, res: results.append(res))
    assert max(e.depth(x[:2]) for e in regions for x in run.x) <= 1e-3
    assert sum(r.is_fallback for r in results) <= 1, [r.fallback_reason for r in results if r.is_fallback]
    start, end = (np.linalg.norm(run.x[k, :2] - ROBOT_0049["target"]) for k in (0, -1))
    assert end < start - 1.0, "held still by overrides (today: 39 of the first 40 samples)"


#: campaign robot-0069 (seed 0): the goal lies beyond the box's edge y2 = 9.9, its best admissible
#: point on the edge; the robot drove along the edge and y_a stalled 7.6 m short in front of an
#: ellipse across it. The segment from y_a to the goal left lambda Z at once, so no escape was tried.
ROBOT_0069 = {"x0": [6.488053293800503, 8.794659367935523, -0.5359977622879994, -0.8268521755119755],
              "target": [-7.532243858911283, 10.159135686376622],
              "ellipses": [((4.567690651712065, -6.6083777905296985), (1.0268033834868477, 0.6980784488274356),
                            0.8310443586486108),
                           ((-1.4878951767493411, 9.35884167054966), (1.824560609540367, 1.571886258849624),
                            1.4114670603712256)]}


def test_an_unreachable_goal_beyond_the_box_edge_is_reached_past_an_ellipse_across_the_edge():
    from rosgraph import ROOT

    from nmpc_avoid_ros.core.config.settings import load_params_file

    params = load_params_file(ROOT / "config" / "mobile_robot.yaml").section("controller")
    controller = NmpcController(ControllerSettings.from_params(params).replace(max_solve_time=5.0))
    regions = [Ellipse(c, a, yaw, "output") for c, a, yaw in ROBOT_0069["ellipses"]]
    aim = controller.escape.aim(np.array(ROBOT_0069["target"]))
    lam = controller.settings.steady_state_scale
    # the goal clipped into lambda Z
    assert aim == pytest.approx([ROBOT_0069["target"][0], lam * controller.settings.state_max[1]])
    results = []
    run = run_closed_loop(controller, ROBOT_0069["x0"], ROBOT_0069["target"], 140,
                          regions=lambda k: regions if k == 0 else None, on_step=lambda k, res: results.append(res))
    assert np.linalg.norm(run.x[-1, :2] - aim) < 0.05, f"today: rests at {run.x[-1, :2]}, 7.6 m short"
    # the controller tracks the goal's projection onto Y_r, which is the aim (core/nlp/projection.py): the
    # loop no longer needs an escape guess to leave the edge (it took one while it tracked the goal itself)
    assert all(r.target == pytest.approx(aim, abs=1e-6) for r in results)
    assert max(e.depth(x[:2]) for e in regions for x in run.x[1:]) <= 1e-3


def test_a_clear_plan_beats_a_cheaper_penetrating_base():
    controller = NmpcController(ControllerSettings())
    controller.set_regions([BLOCKER])
    x, y_t = np.array([2.95, 0.0]), np.array([7.9])
    nlp, par = controller.nlp, controller.parameters(x, y_t)
    rest = Guess("rest", np.array([2.95]), np.tile(x, (5, 1)), np.full((5, 1), 2.95))
    # a base that claims to be cheaper than anything but predicts penetration 0.5: the one ranking puts
    # a clear plan first, whatever the costs
    base = solved("shifted", nlp, np.zeros(nlp.layout.n_w), -1.0, 0.5)
    best, tried, _ = escape(nlp, x, par, base, [rest], 1.0)
    assert best is not base and best.label == "rest" and best.depth <= 1e-3 and best.cost > base.cost, tried



def test_an_escape_plan_clear_within_the_tolerance_is_not_refused_for_a_hair_more_depth_than_the_stall():
    """The escape refuses a plan that buys progress with penetration: more depth than the stalled base's + 1e-4. A
    plan clear by the search's own tolerance (1e-3 into the regions as inflated by their margins) buys none. Live
    campaign vdp-0188: the guess over an upright ellipse (depth 3.5e-4, cost 7.0e5 against 9.0e5) was refused
    against the stall's 1.5e-4 in every escape, and the loop rested 9.5 short of y~ = 5.94; admitted, it passes."""
    nlp = NmpcController(ControllerSettings()).nlp
    w = np.zeros(nlp.layout.n_w)
    admit = escape_admission(solved("shifted", nlp, w, 9.0e5, 1.5e-4))
    assert admit(solved("beyond0_left_of_region0", nlp, w, 7.0e5, 3.5e-4)) == ""
    assert admit(solved("beyond0", nlp, w, 7.5e5, 1.19e-2)) == "penetrates more"  # the same stall's deep guess
    # a base that penetrates itself (an escape from a penetrating plan): deeper is refused, shallower admitted
    deep = escape_admission(solved("shifted", nlp, w, 9.0e5, 0.2))
    assert deep(solved("around", nlp, w, 1.0e5, 0.25)) == "penetrates more"
    assert deep(solved("around", nlp, w, 1.0e5, 0.15)) == ""


#: the unicycle of config/unicycle_world.yaml (a 0.2 m body, margin 0.05 m, rate limits, 50 ms input delay) with
#: its body 2 cm into a pillar (radius 0.12 m) that stands on its way to the goal: where a CI run's robot stopped
#: after touching a pillar in real time (test_world_dds, 0.204 m from a wall cell's centre)
PILLAR = Ellipse((0.3 * np.cos(0.6), 0.3 * np.sin(0.6)), (0.12, 0.12), 0.0, "output")


@pytest.mark.parametrize("yaw", [0.0, 1.2])  # 0.6, facing the pillar head-on: still stands (docs/design.md)
def test_a_unicycle_whose_body_touches_a_pillar_turns_away_after_n_samples_and_reaches_its_goal(yaw):
    """Every candidate predicts a violation from inside the pillar's planned band; by the largest one (the first
    rows', which no input changes) the stop won or tied, and the robot stood there for good. After N such samples in
    a row the summed squared violation (the recovery's measure) ranks: a way out wins."""
    from rosgraph import ROOT

    from nmpc_avoid_ros.core.config.settings import load_params_file

    params = load_params_file(ROOT / "config" / "unicycle_world.yaml").section("controller")
    params.update(codegen=False, codegen_background=False)
    controller = NmpcController(ControllerSettings.from_params(params))
    N = controller.settings.horizon
    results = []
    run = run_closed_loop(controller, [0.0, 0.0, yaw], [3.0, 2.0], N + 45,
                          regions=lambda k: [PILLAR] if k == 0 else None, on_step=lambda k, res: results.append(res))
    assert results[0].region_unavoidable  # the case in question: inside the band, every candidate violates
    distance = np.hypot(*(run.x[:, :2] - PILLAR.center).T)
    planned_radius = 0.12 + 0.2 + 0.05  # the pillar, the body, region_margin
    out = np.flatnonzero(distance > planned_radius)
    assert len(out) and out[0] <= N + 12, distance  # out of the planned band within ~2 s of the N samples
    assert distance.min() >= distance[0] - 0.015, distance  # measured 0.011 m closer while it turns
    assert np.hypot(*(run.x[-1, :2] - [3.0, 2.0])) <= 0.15, run.x[-1]


#: campaign robot-0199 (seed 0, config/mobile_robot_live.yaml): the target lies inside an ellipse; y_a slid along its
#: rim and rested at (5.76, 6.19), 1.47 from the best admissible output (7.01, 6.95) the campaign computes, with no
#: stretch of the segment to the target's far side to pass (it ends in the next ellipse): no escape was tried
ROBOT_0199 = {"target": [6.141711229554431, 7.213940843037509], "rest": [5.760927806, 6.186718225],
              "best": [7.014, 6.952],
              "ellipses": [((5.6379331667806145, 7.009863696576955), (1.9833208392865842, 0.691545653795471),
                            2.7028100501526393),
                           ((5.669812534975128, 8.17160428965466), (1.7753062072296673, 1.8478745957062617),
                            0.09411224837137927),
                           ((6.027725348336729, 2.2327155008825237), (1.681898743056664, 1.1756424941680885),
                            1.2953530440764653)]}


def test_a_stall_on_the_rim_of_a_region_over_the_target_aims_at_the_nearest_admissible_output():
    from rosgraph import ROOT

    from nmpc_avoid_ros.core.config.settings import load_params_file

    params = load_params_file(ROOT / "config" / "mobile_robot_live.yaml").section("controller")
    params.update(codegen=False, codegen_background=False, feedback=False)
    controller = NmpcController(ControllerSettings.from_params(params))
    controller.set_regions([Ellipse(c, a, yaw, "output") for c, a, yaw in ROBOT_0199["ellipses"]])
    escape, rest, best = controller.escape, np.array(ROBOT_0199["rest"]), np.array(ROBOT_0199["best"])
    target = np.array(ROBOT_0199["target"])
    par = controller.parameters(np.array([*rest, 0.0, 0.0]), target)
    aim = escape.aim(target)
    [nearest] = escape.beyond_blocks(rest, aim, par)
    # the campaign's best admissible output is the regions' own; the controller's is theirs inflated by its margins
    assert np.linalg.norm(nearest - best) < 0.15 and np.linalg.norm(nearest - aim) < np.linalg.norm(best - aim) + 0.1
    assert escape.should_try(rest, rest, target, par)
    assert escape.beyond_blocks(nearest, aim, par) == []  # there: nothing nearer, no stall to escape
    assert not escape.should_try(nearest, nearest, target, par)
