"""The demo's bags: read back independently, analysed, re-solved; broken files give clear errors."""

from __future__ import annotations

import io
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from rosbags.highlevel import AnyReader
from rosgraph import ros_env

from nmpc_avoid_ros.bag.analysis import load_run
from nmpc_avoid_ros.bag.mcap_io import load_bag

RUNS = {"with_avoidance": 1e8, "without_avoidance": 0.0}


def cli(*args: str, env: dict | None = None, timeout: float = 300) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "nmpc_avoid_ros", *args], capture_output=True, text=True,
                          timeout=timeout, env=env)


@pytest.fixture(scope="module")
def demo_out(tmp_path_factory):
    """`demo --lockstep` once for the module: two recorded paper runs, analysed."""
    out = tmp_path_factory.mktemp("demo")
    env = ros_env(60 + (hash(str(out)) % 30), out / "ros_logs")
    res = cli("demo", "--out", str(out), "--lockstep", env=env, timeout=600)
    assert res.returncode == 0, res.stdout + res.stderr
    (out.parent / f"{out.name}.stdout").write_text(res.stdout)  # beside the folder: not one of its files
    return out


@pytest.mark.slow
@pytest.mark.dds
def test_demo_leaves_bags_metrics_and_figures(demo_out):
    for name in ("with_avoidance.mcap", "without_avoidance.mcap", "metrics.json", "phase_portrait.png",
                 "time_series.png", "value_function.png", "report.html"):
        assert (demo_out / name).stat().st_size > 1000, name
    # its last line names every file it left in the folder (report.html and value_function.png were missing)
    last = (demo_out.parent / f"{demo_out.name}.stdout").read_text().strip().splitlines()[-1]
    files = sorted(f.name for f in demo_out.iterdir() if f.is_file())
    assert last == f"demo: wrote {', '.join(files)} in {demo_out}/", (last, files)


@pytest.mark.slow
@pytest.mark.dds
@pytest.mark.parametrize("name", RUNS)
def test_bags_read_back_with_rosbags_hold_every_topic_and_the_plants_states(demo_out, name, shipped_paper):
    with AnyReader([demo_out / f"{name}.mcap"]) as reader:
        types = {c.topic: c.msgtype for c in reader.connections}
        counts = {c.topic: c.msgcount for c in reader.connections}
        states = [list(reader.deserialize(raw, c.msgtype).data) for c, _, raw in reader.messages()
                  if c.topic == "/state"]
    assert types == {
        "/state": "std_msgs/msg/Float64MultiArray", "/command": "std_msgs/msg/Float64MultiArray",
        "/target": "std_msgs/msg/Float64MultiArray", "/obstacles": "visualization_msgs/msg/MarkerArray",
        "/diagnostics": "diagnostic_msgs/msg/DiagnosticArray", "/controller/prediction": "nav_msgs/msg/Path",
        "/controller/certificate": "std_msgs/msg/Float64MultiArray", "/clock": "rosgraph_msgs/msg/Clock"}
    assert counts["/target"] == 1 and counts["/obstacles"] == 1
    # lockstep: one command, one prediction, one diagnostic per state answered, one clock tick per state
    # (plus, on /command, the deactivate_command the controller publishes when it is stopped: test_stop_dds)
    assert counts["/command"] - 1 == counts["/controller/prediction"] == counts["/diagnostics"] == \
        counts["/controller/certificate"]
    # the lockstep plant stops after the demo's 50 samples (max_steps): x(0..50), a clock tick for each,
    # and nothing in flight when the nodes are stopped
    assert counts["/state"] == 51 and counts["/clock"] == counts["/state"]
    # the demo stops the nodes only once the recorder holds every message it heard (processes.settle):
    # the answer to x(50) is in too, nothing is lost at the stop
    assert counts["/command"] - 1 == counts["/state"]
    # the decoded states are what the plant published: the offline loop of the same configuration
    np.testing.assert_allclose(np.array(states[:51]), shipped_paper(RUNS[name], "euler").x, atol=1e-12)


@pytest.mark.slow
@pytest.mark.dds
def test_analyze_of_the_paper_bags_matches_simulate(demo_out, shipped_paper, tmp_path):
    res = cli("analyze", str(demo_out / "with_avoidance.mcap"), str(demo_out / "without_avoidance.mcap"),
              "--out", str(tmp_path))
    assert res.returncode == 0, res.stderr
    metrics = {b["bag"].rsplit("/", 1)[-1]: b for b in json.loads((tmp_path / "metrics.json").read_text())["bags"]}
    for name, mu in RUNS.items():
        offline = shipped_paper(mu, "euler")
        from nmpc_avoid_ros.core.loop.closed_loop import max_abs_product, settling_step

        m = metrics[f"{name}.mcap"]
        assert m["settling_step"] == settling_step(offline.x[:, 0], 5.0, 0.05)
        assert m["clearance"]["at_samples"]["max_abs_x1x2"] == pytest.approx(max_abs_product(offline.x), abs=1e-9)
        # lockstep: the plant publishes exactly the states solved on (and the one after the last)
        assert m["clearance"]["recorded_states"]["max_abs_x1x2"] == m["clearance"]["at_samples"]["max_abs_x1x2"]
        assert m["fallbacks"] == 0 and m["finished"] is True and len(m["segments"]) == 1
        assert m["config"]["closest_shipped"]["file"] == "config/van_der_pol.yaml"
    assert metrics["with_avoidance.mcap"]["clearance"]["at_samples"]["max_penetration"] < 1e-3
    assert metrics["without_avoidance.mcap"]["clearance"]["at_samples"]["max_penetration"] > 7
    for name in RUNS:
        m = metrics[f"{name}.mcap"]
        assert m["certificate_violations"] == 0 and m["certificate_checked"] >= 49
        # the dense check holds the samples themselves, so it sees at least what they show
        clearance = m["clearance"]
        assert clearance["resimulated_between_samples"]["max_penetration"] >= \
            clearance["at_samples"]["max_penetration"] - 1e-12
    # the honest status: the run without avoidance plans through |x1 x2| > 2 and says so
    assert metrics["with_avoidance.mcap"]["alarm_samples"] == 0
    assert metrics["without_avoidance.mcap"]["alarm_samples"] >= 5
    assert (tmp_path / "phase_portrait.png").stat().st_size > 10_000
    assert (tmp_path / "value_function.png").stat().st_size > 10_000


@pytest.mark.slow
@pytest.mark.dds
@pytest.mark.parametrize("name", RUNS)
def test_lockstep_certificate_is_the_offline_loops(demo_out, name, shipped_paper):
    """The node's per-sample certificate (diagnostics) equals the offline loop's, with no violation."""
    run = load_run(demo_out / f"{name}.mcap")
    offline = shipped_paper(RUNS[name], "euler").certificate
    assert run.counters["certificate_violations"] == 0
    values = run.certificate["value_function"][:50]
    np.testing.assert_allclose(values, [c["value_function"] for c in offline], rtol=1e-12)
    bounds = run.certificate["decrease_bound"][1:50]
    np.testing.assert_allclose(bounds, [c["decrease_bound"] for c in offline[1:]], rtol=1e-9, atol=1e-9)


@pytest.mark.slow
@pytest.mark.dds
def test_replay_resolve_reproduces_the_recorded_commands_and_reports_a_new_tuning(demo_out, tmp_path):
    res = cli("replay", str(demo_out / "with_avoidance.mcap"), "--resolve", "--json", str(tmp_path / "same.json"))
    assert res.returncode == 0, res.stderr
    same = json.loads((tmp_path / "same.json").read_text())["summary"]
    assert same["samples"] >= 50 and same["max_abs_diff"] <= 1e-6
    res = cli("replay", str(demo_out / "with_avoidance.mcap"), "--resolve", "--mu", "0", "--json",
              str(tmp_path / "mu0.json"))
    assert res.returncode == 0, res.stderr
    other = json.loads((tmp_path / "mu0.json").read_text())["summary"]
    assert other["steps_differing"] > 5 and other["max_abs_diff"] > 0.1
    assert "differ beyond" in res.stdout and "step" in res.stdout


@pytest.mark.slow
@pytest.mark.dds
def test_truncated_bag_is_recovered_and_said_to_be_unfinished(demo_out, tmp_path):
    data = (demo_out / "with_avoidance.mcap").read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: len(data) * 2 // 3])
    bag = load_bag(cut)
    assert not bag.finished and any("not finished" in w for w in bag.warnings)
    full = load_bag(demo_out / "with_avoidance.mcap")
    assert 0 < bag.message_count <= full.message_count
    recovered = [list(m.data) for _, m in bag.topics["/state"]]
    assert recovered == [list(m.data) for _, m in full.topics["/state"]][: len(recovered)]
    res = cli("analyze", str(cut), "--out", str(tmp_path / "o"))
    assert res.returncode == 0 and "not finished" in res.stderr + res.stdout
    # a clear partial result: the recovered samples are replayed, and the output says so
    res = cli("replay", str(cut), "--closed-loop", "--json", str(tmp_path / "cut.json"))
    assert res.returncode == 0 and "not finished" in res.stdout, res.stderr
    partial = json.loads((tmp_path / "cut.json").read_text())
    assert partial["replay"]["finished"] is False and len(partial["u"]) == len(load_run(cut).x)
    assert partial["replay"]["max_state_error"] <= 1e-6


@pytest.mark.parametrize("content", [b"", b"not an mcap at all\n" * 10, b"\x89MCAP0\r\n\x01\x02"])
@pytest.mark.parametrize("tool", ["analyze", "replay"])
def test_broken_files_get_a_clear_error_not_a_traceback(tmp_path, content, tool):
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(content)
    args = ["analyze", str(bad), "--out", str(tmp_path / "o")] if tool == "analyze" else ["replay", str(bad),
                                                                                          "--resolve"]
    res = cli(*args)
    assert res.returncode == 1
    assert f"{tool}: error:" in res.stderr and "Traceback" not in res.stderr


@pytest.mark.slow
@pytest.mark.dds
def test_a_bag_without_controller_topics_gets_a_clear_error(demo_out, tmp_path):
    from nmpc_avoid_ros.bag.mcap_writer import Ros2McapWriter

    only_state = tmp_path / "state_only.mcap"
    from std_msgs.msg import Float64MultiArray

    with Ros2McapWriter(only_state) as writer:
        writer.add_topic("/state", "std_msgs/msg/Float64MultiArray")
        writer.write_message("/state", Float64MultiArray(data=[1.0, 2.0]), 1)
    with pytest.raises(Exception, match="no controller samples"):
        load_run(only_state)
    for args in (["analyze", str(only_state), "--out", str(tmp_path / "o")],
                 ["replay", str(only_state), "--closed-loop"]):
        res = cli(*args)
        assert res.returncode == 1 and "no controller samples" in res.stderr and "Traceback" not in res.stderr
        assert len([line for line in res.stderr.splitlines() if "error" in line]) == 1


def test_a_controller_sample_with_an_unknown_status_gets_a_clear_error(tmp_path):
    from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue

    from nmpc_avoid_ros.bag.mcap_writer import Ros2McapWriter

    def sample(status: str) -> DiagnosticArray:
        values = {"state": "[1.0, 0.0]", "command": "[0.0]", "y_a": "[0.0]", "solve_time_ms": "1.0",
                  "status": status}
        return DiagnosticArray(status=[DiagnosticStatus(values=[KeyValue(key=k, value=v)
                                                                for k, v in values.items()])])

    bag = tmp_path / "odd_status.mcap"
    with Ros2McapWriter(bag) as writer:
        for k, status in enumerate(["ok", "fallback_recovery", "panic"]):
            writer.write_message("/diagnostics", sample(status), k + 1)
    with pytest.raises(Exception, match="unknown status.*panic.*known: ok, truncated, unconverged, fallback_shift"):
        load_run(bag)
    res = cli("analyze", str(bag), "--out", str(tmp_path / "o"))
    assert res.returncode == 1 and "panic" in res.stderr and "Traceback" not in res.stderr


@pytest.mark.slow
@pytest.mark.dds
def test_closed_loop_replay_reproduces_the_lockstep_bags_and_mu_0_is_the_offline_mu_0_loop(demo_out, shipped_paper,
                                                                                           tmp_path):
    from nmpc_avoid_ros.tools.demo import LOCKSTEP_INTEGRATION
    from nmpc_avoid_ros.tools.replay import main as replay_main  # in process: no interpreter start per call

    for name in RUNS:
        out = tmp_path / f"{name}.json"
        assert replay_main([str(demo_out / f"{name}.mcap"), "--closed-loop", "--json", str(out)]) == 0
        same = json.loads((tmp_path / f"{name}.json").read_text())
        assert same["replay"]["max_state_error"] <= 1e-6 and len(same["u"]) >= 50
        # with no flag: the plant and the settings the bag recorded (a lockstep plant: no real-time timing)
        assert (same["replay"]["plant"], same["replay"]["plant_source"], same["replay"]["timing"]) == \
            (LOCKSTEP_INTEGRATION, "the bag's /plant parameters", None)
        assert same["replay"]["settings_source"] == "the bag's /controller parameters"
        assert same["summary"]["certificate_violations"] == 0
    assert replay_main([str(demo_out / "with_avoidance.mcap"), "--closed-loop", "--mu", "0", "--json",
                        str(tmp_path / "mu0.json"), "--out", str(tmp_path / "mu0")]) == 0
    mu0 = json.loads((tmp_path / "mu0.json").read_text())
    offline = shipped_paper(0.0, "euler")
    np.testing.assert_allclose(np.array(mu0["x"])[:51], offline.x, atol=1e-9)
    assert mu0["summary"]["settling_step"] == 18
    assert mu0["summary"]["max_abs_x1x2"] == pytest.approx(10.0, abs=1e-3)
    metrics = json.loads((tmp_path / "mu0" / "metrics.json").read_text())
    assert metrics["recorded"]["settling_step"] == 33 and metrics["runs"][0]["metrics"]["settling_step"] == 18
    for figure in ("phase_portrait.png", "time_series.png", "value_function.png"):
        assert (tmp_path / "mu0" / figure).stat().st_size > 10_000, figure


@pytest.mark.slow
@pytest.mark.dds
def test_closed_loop_sweep_gives_a_table_and_a_figure_and_refuses_what_cannot_be_swept(demo_out, tmp_path, capsys):
    from nmpc_avoid_ros.tools.replay import main as replay_main  # in process: no interpreter start per call

    bag = str(demo_out / "with_avoidance.mcap")
    assert replay_main([bag, "--closed-loop", "--sweep", "mu=0,1e8", "--out", str(tmp_path / "s")]) == 0
    assert "| mu=0 | 18 |" in capsys.readouterr().out
    rows = [line for line in (tmp_path / "s" / "sweep.md").read_text().splitlines() if line.startswith("| mu=")]
    assert [r.split("|")[1].strip() for r in rows] == ["mu=0", "mu=1e+08"]
    assert rows[0].split("|")[2].strip() == "18" and rows[1].split("|")[2].strip() == "33"
    assert (tmp_path / "s" / "sweep.png").stat().st_size > 10_000
    for sweep, words in (("foo=1,2", "unknown setting"), ("horizon=5,10", "structural"), ("mu=1,x", "numbers"),
                         ("mu=-1", "mu")):
        assert replay_main([bag, "--closed-loop", "--sweep", sweep]) == 1
        err = capsys.readouterr().err
        assert err.startswith("replay: error:") and words in err and len(err.strip().splitlines()) == 1, (sweep, err)


@pytest.mark.slow
@pytest.mark.dds
def test_replay_republishes_the_recorded_topics_with_their_timing(demo_out, ros_graph):
    _, _, start, probe = ros_graph
    p = probe()
    from std_msgs.msg import Float64MultiArray

    from nmpc_avoid_ros.ros.parameters import STREAM_QOS

    got: list[tuple[float, list[float]]] = []
    p.node.create_subscription(Float64MultiArray, "state", lambda m: got.append((time.monotonic(), list(m.data))),
                               STREAM_QOS)
    bag = load_bag(demo_out / "without_avoidance.mcap")
    recorded = [list(m.data) for _, m in bag.topics["/state"]]
    span = (bag.topics["/state"][-1][0] - bag.topics["/state"][0][0]) * 1e-9
    replay = start("replay", str(demo_out / "without_avoidance.mcap"), "--rate", "0.5", "--wait", "2.0")
    assert p.spin_until(lambda: len(got) >= len(recorded), 60 + 3 * span), (len(got), replay.output())
    assert [d for _, d in got] == recorded
    # rate 0.5: the republished stream takes about twice as long as the recording
    assert (got[-1][0] - got[0][0]) == pytest.approx(2 * span, rel=0.3, abs=0.1)
    assert replay.proc.wait(60) == 0 and "published" in replay.output()


def chromium() -> str:
    """Debian's chromium; a visible skip where there is none, a failure in CI (.ci/run installs it)."""
    path = shutil.which("chromium") or shutil.which("chromium-browser")
    if path:
        return path
    if os.environ.get("CI"):
        pytest.fail("chromium is missing in CI (.ci/run installs Debian's chromium)")
    pytest.skip("no chromium on this machine: `apt-get install chromium` to run the HTML report's browser test")


def rgb_of(png: bytes) -> np.ndarray:
    """A screenshot as [rows, columns, 3] ints 0..255."""
    from matplotlib.image import imread

    return (imread(io.BytesIO(png))[:, :, :3] * 255).astype(int)


def red_pixels(png: bytes) -> np.ndarray:
    """Mask of the prediction's red (#d62728) in a screenshot."""
    rgb = rgb_of(png)
    return (np.abs(rgb[:, :, 0] - 214) < 30) & (rgb[:, :, 1] < 80) & (rgb[:, :, 2] < 80)


def keep_in_pixels(png: bytes) -> np.ndarray:
    """Mask of the keep-in grid's pink (rgba(244,182,182,0.8) over white) in a screenshot."""
    rgb = rgb_of(png)
    return (np.abs(rgb[:, :, 0] - 245) < 8) & (np.abs(rgb[:, :, 1] - 197) < 12) & (np.abs(rgb[:, :, 2] - 197) < 12)


def cursor_column(png: bytes) -> float:
    """The median column of the reddish pixels: the sample's cursor line on a chart without red series
    (anti-aliased, so not always the exact #d62728)."""
    rgb = rgb_of(png)
    columns = np.nonzero((rgb[:, :, 0] > 150) & (rgb[:, :, 0] - rgb[:, :, 1] > 60))[1]
    assert len(columns) > 20, "no cursor line drawn"
    return float(np.median(columns))


def test_the_report_page_inlines_the_pinned_vendored_uplot_and_setup_ships_it(tmp_path):
    from nmpc_avoid_ros.bag import report_page

    vendor = Path(report_page.__file__).parent / "vendor"
    script = (vendor / "uPlot.iife.min.js").read_text()
    # the first line names the version: a replaced file without a new pin fails here
    assert script.splitlines()[0] == f"/*! https://github.com/leeoniya/uPlot (v{report_page.UPLOT_VERSION}) */"
    assert "</script" not in script.lower() and "</style" not in (vendor / "uPlot.min.css").read_text().lower()
    assert "MIT License" in (vendor / "uPlot.LICENSE").read_text()
    text = report_page.write_report(tmp_path / "r.html", []).read_text()
    assert script in text and (vendor / "uPlot.min.css").read_text() in text and report_page.SCRIPT in text
    # the library before the glue that calls it
    assert text.index(script) < text.index(report_page.SCRIPT)
    setup_py = (Path(report_page.__file__).parents[2] / "setup.py").read_text()
    for f in sorted(vendor.iterdir()):  # every vendored file is package data (an installed report needs them)
        assert f'"vendor/{f.name}"' in setup_py, f.name


@pytest.mark.slow
@pytest.mark.dds
def test_html_report_of_the_demo_bags_is_self_contained_renders_and_scrubs_in_headless_chromium(demo_out, tmp_path):
    from playwright.sync_api import sync_playwright

    from nmpc_avoid_ros.bag.report_page import UPLOT_SCRIPT, UPLOT_STYLE

    page_file = tmp_path / "report.html"
    res = cli("analyze", str(demo_out / "with_avoidance.mcap"), str(demo_out / "without_avoidance.mcap"),
              "--out", str(tmp_path / "o"), "--html", str(page_file))
    assert res.returncode == 0, res.stderr
    text = page_file.read_text()
    assert page_file.stat().st_size < 5e6
    assert UPLOT_SCRIPT in text and UPLOT_STYLE in text
    # outside the library as published (whose banner names its home page) nothing points off the file
    ours = text.replace(UPLOT_SCRIPT, "").replace(UPLOT_STYLE, "")
    assert "<script src" not in ours and "<link" not in ours and "http://" not in ours and "https://" not in ours
    executable = chromium()
    offline = load_run(demo_out / "with_avoidance.mcap")
    charts = 1 + 2 + 1 + 3  # the plane; x1, x2 and u over t; solve times, cost terms, certificate over k
    with sync_playwright() as p:
        browser = p.chromium.launch(executable_path=executable, args=["--no-sandbox"])
        try:
            page = browser.new_page(viewport={"width": 1400, "height": 1000})
            errors: list[str] = []
            off_file: list[str] = []
            page.on("pageerror", lambda e: errors.append(str(e)))

            def route(r):  # offline: any network request fails, and the test with it
                if r.request.url.startswith("file:"):
                    return r.continue_()
                off_file.append(r.request.url)
                return r.abort()

            page.route("**/*", route)
            page.goto(page_file.as_uri())
            page.wait_for_function("window.reportReady === true", timeout=15000)
            # uPlot drew them: one root per chart, each with its canvas at its size
            sizes = page.evaluate("[...document.querySelectorAll('#grid .uplot')].map(r => [r.parentElement.id, "
                                  "r.querySelector('canvas').width, r.querySelector('canvas').height])")
            assert [s[0] for s in sizes] == ["plane"] + ["series"] * 3 + ["solve", "costs", "certificate"]
            assert all(w >= 600 and h >= 100 for _, w, h in sizes), sizes
            assert page.locator("#plane .u-legend .u-series").count() == 2 + 4  # both runs; plan, state, x_a, target
            plane = page.locator("#plane")
            first = plane.screenshot()
            assert red_pixels(first).sum() > 100  # the plan of sample 0 is drawn
            # the keep-in grid (drawn in uPlot's hook) covers the corners of the plane, where |x1 x2| > 2
            assert keep_in_pixels(first).sum() > 20000
            assert page.evaluate("window.report.k") == 0
            solve_first = cursor_column(page.locator("#solve").screenshot())
            page.focus("#scrub")
            for _ in range(12):
                page.keyboard.press("ArrowRight")
            drawn = page.evaluate("window.report")
            assert drawn["k"] == 12
            # the drawn plan is the one the controller published at sample 12, from the state it measured
            np.testing.assert_allclose(drawn["prediction"][0], offline.x[12], rtol=1e-6)
            assert len(drawn["prediction"]) == 6
            later = plane.screenshot()
            assert red_pixels(later).sum() > 100 and (red_pixels(later) != red_pixels(first)).sum() > 100
            assert page.locator("#plane .u-title").inner_text() == "plane portrait at sample 12"
            # the cursor on the solve times moved 12 of the 50 samples right (the plot is about 580 px wide)
            assert cursor_column(page.locator("#solve").screenshot()) - solve_first == pytest.approx(
                12 / 50 * 580, rel=0.15)
            page.mouse.move(300, 300)  # uPlot's own hover cursor over the plane
            page.select_option("#run", "1")  # the other bag
            assert page.evaluate("window.report.run") == 1 and page.evaluate("window.report.k") == 12
            # the charts were made anew for it, not added beside the old ones
            assert page.locator("#grid .uplot").count() == charts
            assert red_pixels(plane.screenshot()).sum() > 100
            assert errors == [] and off_file == []
        finally:
            browser.close()


# ------------------------------------------------------------------------------------------------
# what the bag records of its nodes: replay with the plant and settings that made it; overshoot


@pytest.mark.slow
@pytest.mark.dds
@pytest.mark.parametrize("name", RUNS)
def test_the_demo_bags_hold_the_plants_and_the_controllers_parameters(demo_out, name):
    from nmpc_avoid_ros.bag.analysis import controller_samples
    from nmpc_avoid_ros.bag.node_parameters import recorded_setup
    from nmpc_avoid_ros.core.config.settings import ControllerSettings, default_config_path, load_params_file
    from nmpc_avoid_ros.tools.demo import LOCKSTEP_INTEGRATION

    bag = load_bag(demo_out / f"{name}.mcap")
    setup = recorded_setup(bag, controller_samples(bag)[1])
    assert (setup.controller_node, setup.plant_node, setup.notes) == ("/controller", "/plant", [])
    params = load_params_file(default_config_path())
    assert setup.plant["integration"] == LOCKSTEP_INTEGRATION and setup.plant["lockstep"] is True
    assert setup.plant["initial_state"] == params.section("plant")["initial_state"]
    # the demo's controller: the shipped file with its mu override, setting for setting
    shipped = ControllerSettings.from_params(params.section("controller")).replace(mu=RUNS[name])
    assert ControllerSettings.from_params(setup.controller) == shipped


PLANT_RATE = 20.0  # Hz, the plant node's default publish_rate


def _real_time_loop(settings, x0, target, samples, late_every=0, held=3):
    """The controller against a plant run as the real-time plant node runs (nodes/plant.py): steps of
    1 / PLANT_RATE s, each under the command held when it is due, x0 held `held` steps before the
    first command; the command of every `late_every`-th sample reaches the plant a step late.
    Returns the published states [(log time ns, x)] and the samples [(log time ns, StepResult, s)]."""
    from nmpc_avoid_ros.core.loop.closed_loop import ContinuousPlant
    from nmpc_avoid_ros.core.problem.models import make_model
    from nmpc_avoid_ros.core.sample.controller import NmpcController

    controller, plant = NmpcController(settings), ContinuousPlant(make_model(settings.model))
    period_ns, per_sample = round(1e9 / PLANT_RATE), round(settings.sample_time * PLANT_RATE)
    x, previous = np.asarray(x0, float), np.zeros(1)
    states = [(j * period_ns, x) for j in range(held)]
    solved = []
    for k in range(samples):
        now = states[-1][0]
        result = controller.step(x, target)
        solved.append((now + 1, result, now * 1e-9))
        late = 1 if late_every and k % late_every == late_every - 1 else 0
        for step in range(per_sample):
            x = plant.advance(x, previous if step < late else result.u, 1.0 / PLANT_RATE)
            states.append((states[-1][0] + period_ns, x))
        previous = result.u
    return states, solved


def _loop_bag(path, settings, states, solved, *, records: bool = True, clock: bool = False):
    """A bag as the recorder writes one: the target, the plant's `states`, the controller's diagnostics of
    `solved` (nodes/controller_views.diagnostic_array), a /clock tick per state with `clock`, and with
    `records` the controller's and the real-time plant's parameters as the recorder keeps them."""
    from builtin_interfaces.msg import Time
    from diagnostic_msgs.msg import DiagnosticStatus
    from rosgraph_msgs.msg import Clock
    from std_msgs.msg import Float64MultiArray

    from nmpc_avoid_ros.bag.mcap_writer import Ros2McapWriter
    from nmpc_avoid_ros.bag.node_parameters import PARAMETERS_RECORD, parameters_record
    from nmpc_avoid_ros.nodes.controller_views import diagnostic_array

    with Ros2McapWriter(path) as bag:
        if records:
            fields = {k: (list(v) if isinstance(v, tuple) else v) for k, v in vars(settings).items()}
            bag.add_metadata(PARAMETERS_RECORD, parameters_record("/controller", fields, 0))
            plant = {"model": settings.model, "integration": "continuous", "sample_time": settings.sample_time,
                     "lockstep": clock, "publish_rate": PLANT_RATE, "initial_state": states[0][1].tolist()}
            bag.add_metadata(PARAMETERS_RECORD, parameters_record("/plant", plant, 0))
        bag.write_message("/target", Float64MultiArray(data=[5.0]), 0)
        for t, x in states:
            bag.write_message("/state", Float64MultiArray(data=x.tolist()), t)
            if clock:
                bag.write_message("/clock", Clock(clock=Time(sec=t // 10**9, nanosec=t % 10**9)), t)
        for t, result, state_time in solved:
            values = {"command": str(result.u.tolist()), "mu": f"{settings.mu:g}", "kappa": f"{settings.kappa:g}"}
            bag.write_message("/diagnostics", diagnostic_array("/controller", Time(), DiagnosticStatus.OK, "ok",
                                                               values, result, 0.0, state_time, None), t)


@pytest.fixture(scope="module")
def real_time_bags(tmp_path_factory):
    """The shipped config's paper loop against the real-time continuous plant (every third command a plant
    step late), written as the recorder would with its parameter records (`records`), without them (`old`:
    bags made before), and without them but with /clock (`old_clock`)."""
    from nmpc_avoid_ros.core.config.settings import ControllerSettings, default_config_path, load_params_file

    settings = ControllerSettings.from_params(load_params_file(default_config_path()).section("controller"))
    states, solved = _real_time_loop(settings, [-5.0, 0.0], [5.0], 40, late_every=3)
    folder = tmp_path_factory.mktemp("real_time")
    paths = {"records": folder / "records.mcap", "old": folder / "old.mcap", "old_clock": folder / "old_clock.mcap"}
    _loop_bag(paths["records"], settings, states, solved)
    _loop_bag(paths["old"], settings, states, solved, records=False)
    _loop_bag(paths["old_clock"], settings, states, solved, records=False, clock=True)
    return paths


@pytest.mark.slow
def test_closed_loop_replay_takes_the_plant_its_timing_and_the_settings_from_the_bag(real_time_bags, tmp_path,
                                                                                      capsys):
    from nmpc_avoid_ros.tools.replay import main as replay_main

    paths = real_time_bags
    assert replay_main([str(paths["records"]), "--closed-loop", "--json", str(tmp_path / "same.json")]) == 0
    out = capsys.readouterr().out
    same = json.loads((tmp_path / "same.json").read_text())["replay"]
    # nothing changed, nothing given: the continuous plant the bag recorded, with the loop's timing
    assert same["plant"] == "continuous" and same["plant_source"] == "the bag's /plant parameters"
    assert same["settings_source"] == "the bag's /controller parameters"
    per_sample = round(0.5 * PLANT_RATE)
    assert same["timing"].startswith(f"the recorded timing: plant steps of {1e3 / PLANT_RATE:g} ms, {per_sample} to "
                                     f"{per_sample} per sample, "), same
    # the late ones found (a late command equal to its predecessor, once settled, cannot be told apart)
    assert 0 < same["timing_late_commands"] <= len(range(2, 40, 3)), same
    assert same["max_state_error"] <= 1e-6, same
    assert "plant: continuous integration of van_der_pol (the bag's /plant parameters)" in out
    # ideal samples miss the late commands and the held start; the Euler plant is another loop altogether
    assert replay_main([str(paths["records"]), "--closed-loop", "--timing", "ideal", "--json",
                        str(tmp_path / "ideal.json")]) == 0
    ideal = json.loads((tmp_path / "ideal.json").read_text())["replay"]
    assert ideal["timing"] is None and ideal["max_state_error"] > 1e-3
    assert replay_main([str(paths["records"]), "--closed-loop", "--plant", "euler", "--json",
                        str(tmp_path / "euler.json")]) == 0
    euler = json.loads((tmp_path / "euler.json").read_text())["replay"]
    assert euler["plant"] == "euler" and euler["plant_source"] == "--plant"
    assert euler["max_state_error"] > ideal["max_state_error"]


@pytest.mark.slow
def test_a_bag_without_parameter_records_is_replayed_on_what_it_implies_and_says_so(real_time_bags, tmp_path,
                                                                                      capsys):
    from nmpc_avoid_ros.tools.replay import main as replay_main

    paths = real_time_bags
    assert replay_main([str(paths["old"]), "--closed-loop", "--json", str(tmp_path / "old.json")]) == 0
    out = capsys.readouterr().out
    old = json.loads((tmp_path / "old.json").read_text())["replay"]
    # no /clock: the plant ran in real time, which only the continuous integration can
    assert old["plant"] == "continuous" and old["plant_source"].startswith("assumed: the bag records no plant")
    assert "no /clock" in old["plant_source"] and "--plant" in old["plant_source"]
    assert old["settings_source"].startswith("assumed: the bag holds no usable controller parameters")
    assert "van_der_pol.yaml" in old["settings_source"] and old["max_state_error"] <= 1e-6
    assert "replay --closed-loop: plant: continuous integration of van_der_pol (assumed:" in out
    assert replay_main([str(paths["old"]), "--resolve"]) == 0
    assert "replay --resolve: controller settings: assumed: the bag holds no usable controller parameters" in \
        capsys.readouterr().out
    # /clock: a lockstep plant, taken to be the lockstep demo's Euler step
    assert replay_main([str(paths["old_clock"]), "--closed-loop", "--json", str(tmp_path / "clock.json")]) == 0
    clocked = json.loads((tmp_path / "clock.json").read_text())["replay"]
    assert clocked["plant"] == "euler" and "lockstep (the bag has /clock)" in clocked["plant_source"]


def test_overshoot_is_the_excursion_beyond_the_target_along_the_step_as_a_fraction_of_it():
    from nmpc_avoid_ros.core.loop.metrics import SETTLING_TOLERANCE, overshoot, tracking

    y = np.array([[-5.0], [0.0], [5.6], [4.9], [5.0]])
    value, note = overshoot(y, [5.0])
    assert note is None and value == pytest.approx((5.6 - 5.0) / (5.0 - -5.0))
    down = 10.0 - y  # the same response to a step down
    assert overshoot(down, [5.0])[0] == pytest.approx(value)
    assert overshoot(y[[0, 1, 4]], [5.0]) == (0.0, None)  # never beyond: none
    # two outputs: only the excursion along the step counts (the one across it is no overshoot)
    plane = np.array([[0.0, 0.0], [3.0, 1.0], [2.0, 0.0]])
    assert overshoot(plane, [2.0, 0.0])[0] == pytest.approx(1.0 / 2.0)
    # a step below the settling tolerance: left out, and the metrics say why
    start = np.array([[5.0 + 1e-9], [5.02], [5.0]])
    value, note = overshoot(start, [5.0])
    assert value is None and "below" in note and f"{SETTLING_TOLERANCE:g}" in note
    quality = tracking(start, [5.0], 0.5)
    assert quality["overshoot"] is None and quality["overshoot_note"] == note and quality["settling_step"] == 0


def test_analyze_of_a_bag_that_starts_at_its_target_leaves_the_overshoot_out(tmp_path):
    from nmpc_avoid_ros.core.config.settings import ControllerSettings, default_config_path, load_params_file
    from nmpc_avoid_ros.tools.analyze import main as analyze_main

    settings = ControllerSettings.from_params(load_params_file(default_config_path()).section("controller"))
    _loop_bag(tmp_path / "at_target.mcap", settings, *_real_time_loop(settings, [5.0, 0.0], [5.0], 6))
    assert analyze_main([str(tmp_path / "at_target.mcap"), "--out", str(tmp_path / "o")]) == 0
    (metrics,) = json.loads((tmp_path / "o" / "metrics.json").read_text())["bags"]
    assert metrics["overshoot"] is None and "below" in metrics["overshoot_note"], metrics
    assert metrics["settling_step"] == 0


def test_recorded_setup_finds_the_controller_and_its_plant_and_says_what_it_cannot_use(tmp_path):
    from nmpc_avoid_ros.bag.mcap_io import Bag
    from nmpc_avoid_ros.bag.node_parameters import PARAMETERS_RECORD, parameters_record, recorded_setup

    def bag(*records):
        return Bag(tmp_path / "b.mcap", {}, {}, True, [], [(PARAMETERS_RECORD, r) for r in records])

    plant = {"model": "van_der_pol", "integration": "rk4"}
    controller = {"model": "van_der_pol", "mu": 0.0, "lockstep": True, "target": None}
    records = [parameters_record("/vdp/controller", controller, 1), parameters_record("/vdp/plant", plant, 2),
               parameters_record("/other/plant", {**plant, "integration": "euler"}, 3)]
    setup = recorded_setup(bag(*records), "/vdp/controller")
    # the controller's core settings only (lockstep, target: the node's own); the plant in its namespace
    assert setup.controller == {"model": "van_der_pol", "mu": 0.0} and setup.plant_node == "/vdp/plant"
    assert setup.plant["integration"] == "rk4" and setup.notes == []
    assert "several plants in the bag (/other/plant, /vdp/plant): none taken" in recorded_setup(bag(*records),
                                                                                              None).notes
    broken = {"node": "/vdp/plant", "parameters": "{not json", "time_ns": "0"}
    empty = parameters_record("/vdp/controller", {}, 0)  # what rclpy's service gives for an unset name
    setup = recorded_setup(bag(empty, broken), "/vdp/controller")
    assert setup.controller is None and setup.plant is None
    assert any("do not parse" in n for n in setup.notes) and any("lack its model" in n for n in setup.notes)


def test_the_interface_of_a_bag_without_the_controllers_parameters_is_inferred_from_its_topics():
    """A planar model's plant publishes Odometry on odom for the views on the array interface too: a bag whose
    controller parameters were not recorded is the array interface when its command or state carries arrays
    (the moving-walker scene demo's bag was once read as a robot's: its 3-value poses for a 4-state model)."""
    from pathlib import Path

    from nmpc_avoid_ros.bag.mcap_io import Bag
    from nmpc_avoid_ros.bag.timeline import ARRAY_TYPE, ODOMETRY_TYPE, controller_interface

    def bag(**topics):
        return Bag(Path("x.mcap"), {name: [(1, object())] for name in topics},
                   {name: kind for name, kind in topics.items()}, True, [])

    odom = {"/odom": ODOMETRY_TYPE}
    array = controller_interface(bag(**odom, **{"/state": ARRAY_TYPE, "/command": ARRAY_TYPE}), None)
    assert array.name == "array" and "/command carries arrays" in array.source
    robot = controller_interface(bag(**odom, **{"/cmd_vel": "geometry_msgs/msg/TwistStamped"}), None)
    assert robot.name == "robot" and "/odom is Odometry" in robot.source
    assert controller_interface(bag(**odom), {"interface": "array"}).name == "array"  # recorded: as recorded
