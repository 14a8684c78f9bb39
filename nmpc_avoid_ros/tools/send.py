"""`send`: a target, a goal pose, an obstacle change or a run-time parameter to a running controller,
without the `ros2` CLI (it is not among the PyPI wheels).

    python -m nmpc_avoid_ros send target 5                 # y_t on `target` (p values: send target 8 6)
    python -m nmpc_avoid_ros send goal 3 2 [1.57]          # PoseStamped on `goal_pose` (robot interface), yaw rad
    python -m nmpc_avoid_ros send obstacle ellipse --center 2 -0.5 --axes 0.4 0.2 [--yaw 0] [--id 1]
    python -m nmpc_avoid_ros send obstacle box --center 1 1 --size 0.6 0.4 [--yaw 0.3]
    python -m nmpc_avoid_ros send obstacle polygon --vertices 0 0 1 0 1 1
    python -m nmpc_avoid_ros send delete 1                 # DELETE the region (ns, id)
    python -m nmpc_avoid_ros send clear                    # DELETEALL: every region, whatever its ns
    python -m nmpc_avoid_ros send param mu 0               # ros2 param set /controller mu 0.0
    python -m nmpc_avoid_ros send target 5 --ros-args -r __ns:=/robot1      # or --namespace /robot1

Obstacles are one-marker MarkerArrays on `obstacles` with the controller's conventions
(ros/markers.py): an ellipse is a CYLINDER with scale = 2 x semi-axes, a box a CUBE (scale = its
sides), a polygon a closed LINE_STRIP; `--ns` (default `send`) and `--id` (default 1) name the
region, `--frame` its plane (`state` or `output`). A new marker under the same (ns, id) replaces
the old one.

A goal is a geometry_msgs/PoseStamped on `goal_pose` (what RViz's "2D Goal Pose" sends): position
(X, Y, 0), the orientation the rotation by YAW about z (default 0), header.frame_id the controller's
`odom_frame` parameter (read just before the publish; `odom` if it has none; `--frame` sets it), the
stamp now. Only the robot interface (`interface: robot`) subscribes `goal_pose`; a controller of the
array interface is recognised once the graph shows its `target` subscription without a `goal_pose`
one and its `interface` parameter says so: `send goal` then fails at once (exit 1) naming the interface.
Both interfaces subscribe `target` (nodes/controller.py), so `send target` reaches either.

A message is published once on the latched QoS the package's publishers use (reliable, transient local,
depth 1) after a subscription of the controller (`--node`, default `controller`) matched, and every
other subscription the graph shows (a recorder's), with the graph unchanged for GRAPH_SETTLE s (up to
GRAPH_GRACE s more); `send` returns only when every matched reader acknowledged it, so the process may
exit at once without losing it (the line printed names the nodes). It lives at least DISCOVERY_WINDOW s:
a participant that was running is found up to one Fast DDS announcement period (3 s) after `send`
starts, and a reader found after the publish gets the latched message from `send`'s writer and is waited
for too. A reader that does not acknowledge it within `--timeout` s is named in the one line on stderr
(exit 1): the controller, if its diagnostics did not count the message, else the other readers (a
recorder), while the line says the controller had it and its verdict. A parameter goes through the
node's `<node>/set_parameters` service with the type the node declared (`mu 0` is sent as 0.0). Each
wait is bounded by `--timeout` s, except for a controller that is starting: the node is in the graph (it
is created before its solver is built) but has no subscription yet or does not answer (a first start
compiles its solver's code for a minute or two and logs so); `send` says so on stderr and waits for it
up to STARTING_TIMEOUT s.

`send` knows the controller's answer (tools/send_verdict.py): before a target goes out, its size is
checked against the controller's model (its `model` parameter, p values; `--no-check` skips this);
after the publish, `send` waits (up to `--timeout` s) until the controller's /diagnostics count the
message and reads its verdict there (`target_verdict`, `goal_pose_verdict`, `obstacles_verdict`, with
the reason). A controller that publishes no diagnostics (inactive, or lockstep without a plant) gives
no verdict: one line on stderr says so and the message counts as delivered.

Exit codes: 0 delivered and accepted (or set; or delivered with no verdict to read, said on stderr);
1 no controller listening (another reader is not enough; a goal to a controller without `goal_pose`),
a reader that did not acknowledge it, or the controller refused it: the message (its reason from the
diagnostics) or the parameter (one line on stderr says why); 2 bad arguments, among them a target of
the wrong size for the controller's model (the line names the size it takes).
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from collections.abc import Sequence
from typing import Any

from ..core.errors import NmpcError
from .send_params import parameter_value
from .send_verdict import ControllerWatch, SendError, Verdict

PROG = "python -m nmpc_avoid_ros send"
#: default --timeout, s
DEFAULT_TIMEOUT = 5.0
#: after the controller's match: s to wait at most for the rest of the subscriptions the graph lists (a
#: reader of incompatible QoS never matches, and must not cost the whole timeout)
GRAPH_GRACE = 4.0
#: s the graph's readers and matches must stay unchanged before the message goes out: a new participant
#: finds the others one by one, measured up to 1.1 s apart on one machine (a recorder found after the
#: controller missed messages in test/test_send_dds.py with 0 and with 0.5 s)
GRAPH_SETTLE = 1.5
#: s from `send`'s start within which it finds every participant that was running before it: Fast DDS
#: announces a participant again every 3 s, and a fresh one found the recorder up to 3.0 s after the
#: controller (3 of 20 `send goal` calls before this waited missed the recorder with nothing said; issue
#: 33). A latched message reaches a reader found late only while `send` lives: it stays that long.
DISCOVERY_WINDOW = 3.5
#: the node name rmw reports for an endpoint whose participant's node list has not arrived yet
UNKNOWN_NODE = "_NODE_NAME_UNKNOWN_"
#: s `send` waits at most for a node that is in the graph but not serving yet (a first start compiles)
STARTING_TIMEOUT = 300.0
_noted_starting: set[str] = set()  # nodes `starting` said it waits for
#: ns of the markers `send` makes unless --ns
DEFAULT_NS = "send"


# --- arguments -------------------------------------------------------------------------------------

def finite(text: str) -> float:
    """argparse type: a finite number (NaN and infinities refused)."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"must be finite, got {text!r}")
    return value


def positive(text: str) -> float:
    """argparse type: a finite number > 0."""
    value = finite(text)
    if value <= 0:
        raise argparse.ArgumentTypeError(f"must be > 0, got {text!r}")
    return value


def marker_id(text: str) -> int:
    """argparse type: a marker id (a 32-bit integer)."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not an integer: {text!r}") from None
    if not -(2**31) <= value < 2**31:
        raise argparse.ArgumentTypeError(f"out of the int32 range: {text!r}")
    return value


def build_parser() -> argparse.ArgumentParser:
    common = argparse.ArgumentParser(add_help=False)
    common.add_argument("--timeout", type=positive, default=DEFAULT_TIMEOUT,
                        help=f"s to wait for a subscriber (or the parameter service) and again for the "
                             f"acknowledgement (default {DEFAULT_TIMEOUT:g})")
    common.add_argument("--namespace", default=None,
                        help="namespace of the controller, e.g. /robot1 (like --ros-args -r __ns:=/robot1)")
    common.add_argument("--no-check", action="store_true",
                        help="send a target unchecked against the controller's model (the controller still "
                             "judges it and send reports its verdict)")
    common.add_argument("--node", default="controller",
                        help="the node that must receive it (its subscription, or its parameter service), "
                             "relative to the namespace or absolute (default controller)")
    marker = argparse.ArgumentParser(add_help=False)
    marker.add_argument("--ns", default=DEFAULT_NS, help=f"marker namespace (default {DEFAULT_NS})")
    marker.add_argument("--id", type=marker_id, default=1, help="marker id (default 1)")

    parser = argparse.ArgumentParser(prog=PROG, description=__doc__.split("\n\n")[0],
                                     epilog="ROS arguments follow --ros-args (e.g. -r __ns:=/robot1).")
    commands = parser.add_subparsers(dest="what", required=True,
                                     metavar="{target,goal,obstacle,delete,clear,param}")
    target = commands.add_parser("target", parents=[common], help="a target y_t on `target`")
    target.add_argument("values", type=finite, nargs="+", metavar="Y", help="the target's p values")
    goal = commands.add_parser("goal", parents=[common],
                               help="a goal pose (PoseStamped) on `goal_pose`: the robot interface's target")
    goal.add_argument("x", type=finite, metavar="X", help="goal position x, m")
    goal.add_argument("y", type=finite, metavar="Y", help="goal position y, m")
    goal.add_argument("yaw", type=finite, nargs="?", default=0.0, metavar="YAW",
                      help="goal heading, rad about z (default 0)")
    goal.add_argument("--frame", default=None,
                      help="header.frame_id (default: the controller's odom_frame parameter, else odom)")

    obstacle = commands.add_parser("obstacle", help="add or replace a region on `obstacles`")
    shapes = obstacle.add_subparsers(dest="shape", required=True, metavar="{ellipse,box,polygon}")
    shape = argparse.ArgumentParser(add_help=False, parents=[common, marker])
    shape.add_argument("--frame", choices=("state", "output"), default="state",
                       help="plane of the region: the controller's `plane` state coordinates or its "
                            "`output_plane` outputs (default state)")
    ellipse = shapes.add_parser("ellipse", parents=[shape], help="an ellipse (CYLINDER marker)")
    ellipse.add_argument("--center", type=finite, nargs=2, required=True, metavar=("X", "Y"))
    ellipse.add_argument("--axes", type=positive, nargs=2, required=True, metavar=("A", "B"), help="semi-axes")
    ellipse.add_argument("--yaw", type=finite, default=0.0, help="rotation of the first axis, rad")
    box = shapes.add_parser("box", parents=[shape], help="a rotated rectangle (CUBE marker)")
    box.add_argument("--center", type=finite, nargs=2, required=True, metavar=("X", "Y"))
    box.add_argument("--size", type=positive, nargs=2, required=True, metavar=("W", "H"), help="full sides")
    box.add_argument("--yaw", type=finite, default=0.0, help="rotation, rad")
    polygon = shapes.add_parser("polygon", parents=[shape], help="a convex polygon (LINE_STRIP marker)")
    polygon.add_argument("--vertices", type=finite, nargs="+", required=True, metavar="XY",
                         help="x1 y1 x2 y2 ... (at least 3 vertices, in order)")

    delete = commands.add_parser("delete", parents=[common], help="remove the region (ns, id) (DELETE)")
    delete.add_argument("id", type=marker_id)
    delete.add_argument("--ns", default=DEFAULT_NS, help=f"marker namespace (default {DEFAULT_NS})")
    commands.add_parser("clear", parents=[common], help="remove every region (DELETEALL)")

    param = commands.add_parser("param", parents=[common], help="set a parameter of the controller")
    param.add_argument("name")
    param.add_argument("values", nargs="+", metavar="VALUE",
                       help="the value: one for a scalar, several (or [a, b]) for an array")
    return parser


def split_ros_args(argv: Sequence[str]) -> tuple[list[str], list[str]]:
    """(send's own arguments, ROS arguments from --ros-args on)."""
    argv = list(argv)
    if "--ros-args" in argv:
        i = argv.index("--ros-args")
        return argv[:i], argv[i:]
    return argv, []


# --- messages --------------------------------------------------------------------------------------

def target_message(values: Sequence[float]) -> Any:
    """The Float64MultiArray of a target y_t."""
    from std_msgs.msg import Float64MultiArray

    return Float64MultiArray(data=[float(v) for v in values])


def goal_message(x: float, y: float, yaw: float) -> Any:
    """The PoseStamped of a goal at (x, y) heading `yaw`; its frame and stamp are set just before the publish."""
    from geometry_msgs.msg import PoseStamped

    from ..ros.markers import yaw_to_quaternion

    msg = PoseStamped()
    msg.pose.position.x, msg.pose.position.y = float(x), float(y)
    msg.pose.orientation = yaw_to_quaternion(float(yaw))
    return msg


def obstacle_message(args: argparse.Namespace) -> Any:
    """The one-marker MarkerArray of `send obstacle ...`; RegionError (an NmpcError) if the shape is invalid."""
    from visualization_msgs.msg import MarkerArray

    from ..core.problem.regions import Ellipse, Polygon, rotated_box
    from ..ros.markers import CUBE, ellipse_marker, polygon_marker, yaw_to_quaternion

    if args.shape == "ellipse":
        marker = ellipse_marker(Ellipse(tuple(args.center), tuple(args.axes), args.yaw, args.frame), args.id, args.ns)
    elif args.shape == "box":
        rotated_box(args.center, args.size, args.yaw, args.frame)  # validates as the controller will
        marker = ellipse_marker(Ellipse(tuple(args.center), (args.size[0] / 2, args.size[1] / 2), args.yaw,
                                        args.frame), args.id, args.ns)
        marker.type = CUBE  # same pose and scale conventions as the cylinder: scale = the full sides
        marker.pose.orientation = yaw_to_quaternion(args.yaw)
    else:
        flat = args.vertices
        if len(flat) % 2:
            raise NmpcError(f"--vertices takes x y pairs, got {len(flat)} numbers")
        points = tuple((flat[i], flat[i + 1]) for i in range(0, len(flat), 2))
        marker = polygon_marker(Polygon(points, args.frame), args.id, args.ns)
    return MarkerArray(markers=[marker])


def delete_message(ns: str, marker_id_: int) -> Any:
    from visualization_msgs.msg import MarkerArray

    from ..ros.markers import delete_marker

    return MarkerArray(markers=[delete_marker(ns, marker_id_)])


def clear_message() -> Any:
    from visualization_msgs.msg import MarkerArray

    from ..ros.markers import delete_all_marker

    return MarkerArray(markers=[delete_all_marker()])


def topic_message(args: argparse.Namespace) -> tuple[str, Any, str]:
    """(topic, message, what it is in words) of a topic command."""
    if args.what == "target":
        return "target", target_message(args.values), f"target {[float(v) for v in args.values]}"
    if args.what == "goal":
        return "goal_pose", goal_message(args.x, args.y, args.yaw), f"goal [{args.x:g}, {args.y:g}] yaw {args.yaw:g}"
    if args.what == "obstacle":
        return "obstacles", obstacle_message(args), f"{args.shape} (ns {args.ns!r}, id {args.id})"
    if args.what == "delete":
        return "obstacles", delete_message(args.ns, args.id), f"DELETE (ns {args.ns!r}, id {args.id})"
    return "obstacles", clear_message(), "DELETEALL"


# --- ROS -------------------------------------------------------------------------------------------

def _spin_until(executor: Any, done: Any, timeout: float) -> bool:
    end = time.monotonic() + timeout
    while not done() and time.monotonic() < end:
        executor.spin_once(timeout_sec=0.05)
    return bool(done())


def node_name(node: Any, relative: str) -> str:
    """The fully qualified name of node `relative` (relative to `node`'s namespace, or absolute): rclpy
    resolves topic and service names only, so one of its services is resolved and cut back to the node."""
    return node.resolve_service_name(f"{relative}/_").rsplit("/", 1)[0]


def starting(node: Any, name: str, begin: float, what: str) -> bool:
    """Whether to go on waiting (since `begin`, monotonic s) for the node `name` (fully qualified): it is
    in the graph, not serving yet, and STARTING_TIMEOUT has not passed. Says so on stderr once."""
    namespace, _, short = name.rpartition("/")
    if time.monotonic() - begin >= STARTING_TIMEOUT or (short, namespace or "/") not in \
            node.get_node_names_and_namespaces():
        return False
    if name not in _noted_starting:
        _noted_starting.add(name)
        print(f"send: {name} is up but has no {what} yet: starting (a first start compiles its solver, its log says "
              f"how long); waiting up to {STARTING_TIMEOUT:.0f} s", file=sys.stderr)
    return True


def publish_latched(node: Any, topic: str, message: Any, reader: str, timeout: float,
                    check: Any = None, absent: Any = None, born: float | None = None) -> tuple[str, list[str], bool]:
    """Publish `message` once on `topic` (LATCHED_QOS) once a subscription of the node `reader` (fully
    qualified) matched, and wait until every matched reader acknowledged it: (the resolved topic, the
    subscribing nodes, whether all of them acknowledged it within `timeout`). SendError if `reader`
    never subscribed.

    Another reader (a recorder) matching first is not enough: the message must reach `reader`, and a
    latched message is gone for a late reader once this process exits. `check()`, if given, runs just
    before the publish (the controller is configured then); what it raises stops the send.
    `absent(topic)`, if given, is asked while `reader` has no subscription: the reason it will have none
    (its interface has no such topic), which ends the wait at once, or None. After the publish it stays
    until DISCOVERY_WINDOW s after `born` (monotonic s, when the node was made; default now), so that a
    reader discovered late still gets the message, and waits for its acknowledgement too."""
    from rclpy.duration import Duration

    from ..ros.parameters import LATCHED_QOS

    publisher = node.create_publisher(type(message), topic, LATCHED_QOS)
    name = publisher.topic_name
    end = time.monotonic() + timeout
    born = time.monotonic() if born is None else born

    def readers() -> list[str]:
        return [f"{i.node_namespace.rstrip('/')}/{i.node_name}" for i in node.get_subscriptions_info_by_topic(name)
                if i.node_name != node.get_name()]

    begin = time.monotonic()
    while reader not in readers() or publisher.get_subscription_count() == 0:
        if absent is not None and (why := absent(name)):
            raise SendError(why)
        if time.monotonic() >= end:
            if not starting(node, reader, begin, f"subscription on {name}"):
                raise SendError(f"no subscriber of {reader} on {name} after {time.monotonic() - begin:.1f} s (is "
                                f"it running? --node names another)")
            end = math.inf  # a starting controller: the bound is STARTING_TIMEOUT
        time.sleep(0.02)
    if end == math.inf:  # the steps after the match keep their own bound
        end = time.monotonic() + timeout
    # every reader the graph knows of (a controller's two, a recorder's) matched, and the graph still for
    # GRAPH_SETTLE s (this process's discovery finds the other nodes one by one); one of incompatible QoS
    # never matches: bounded by GRAPH_GRACE
    grace = min(end, time.monotonic() + GRAPH_GRACE)
    seen, since = None, time.monotonic()
    while (now := time.monotonic()) < grace:
        current = (sorted(readers()), publisher.get_subscription_count())
        if current != seen:
            seen, since = current, now
        elif current[1] >= len(current[0]) and now - since >= GRAPH_SETTLE:
            break
        time.sleep(0.02)
    listed, matched = len(readers()), publisher.get_subscription_count()
    if matched < listed:
        print(f"send: {name}: {matched} of the {listed} subscriptions the graph lists matched "
              f"({unmatched_readers(node, name)}); the others may not get this message", file=sys.stderr)
    if check is not None:
        check()
    publisher.publish(message)
    acknowledged = publisher.wait_for_all_acked(Duration(seconds=timeout))
    # a participant discovered late (up to one announcement period after this one started) takes the
    # message from this writer's history once it matches: stay, then wait for every reader's acknowledgement
    def unsettled() -> bool:
        names = readers()
        return UNKNOWN_NODE in " ".join(names) or publisher.get_subscription_count() < len(names)

    linger = born + DISCOVERY_WINDOW
    while (now := time.monotonic()) < linger or (unsettled() and now < linger + GRAPH_GRACE):
        time.sleep(0.02)
    acknowledged = acknowledged and publisher.wait_for_all_acked(Duration(seconds=timeout))
    return name, sorted(set(readers())), acknowledged


def unmatched_readers(node: Any, topic: str) -> str:
    """Words naming the readers of `topic` that may not have matched: those whose QoS is incompatible
    with LATCHED_QOS, else every reader the graph lists (rclpy does not say which matched)."""
    from rclpy.qos import QoSCompatibility, qos_check_compatible

    from ..ros.parameters import LATCHED_QOS

    infos = [i for i in node.get_subscriptions_info_by_topic(topic) if i.node_name != node.get_name()]
    names = [f"{i.node_namespace.rstrip('/')}/{i.node_name}" for i in infos]
    refused = sorted({n for n, i in zip(names, infos)
                      if qos_check_compatible(LATCHED_QOS, i.qos_profile)[0] == QoSCompatibility.ERROR})
    return f"QoS incompatible: {', '.join(refused)}" if refused else f"among {', '.join(sorted(set(names)))}"


def not_acknowledged(name: str, nodes: list[str], reader: str, verdict: Verdict | None, timeout: float) -> str:
    """The stderr line naming who did not acknowledge the message on `name` in `timeout` s: with the
    controller's `verdict` (it counted the message), the other readers; without it, the controller too."""
    others = [n for n in nodes if n != reader]
    if verdict is not None:
        who = ", ".join(others) or f"a second reader of {reader}"
        return (f"{name}: not acknowledged in {timeout:.1f} s by {who} (it may not have the message); {reader} "
                f"counted it: {verdict.verdict}{f' ({verdict.reason})' if verdict.reason else ''}")
    return f"{name}: not acknowledged in {timeout:.1f} s by {', '.join([reader, *others])} (one or more of them)"


def set_parameter(node: Any, executor: Any, target_node: str, name: str, values: Sequence[str],
                  timeout: float) -> tuple[str, Any]:
    """Set `name` on `target_node` through its parameter services, typed as the node declared it:
    (the node's resolved name, the value set). SendError if unreachable, undeclared or refused."""
    from rclpy.parameter_client import AsyncParameterClient

    client = AsyncParameterClient(node, target_node)
    remote = node_name(node, target_node)
    service = f"{remote}/set_parameters"
    if not client.wait_for_services(timeout_sec=timeout):
        raise SendError(f"no parameter service {service} after {timeout:.1f} s (is the controller running?)")
    future = client.describe_parameters([name])
    begin = time.monotonic()
    while not _spin_until(executor, future.done, timeout):
        if not starting(node, remote, begin, "answer to its parameter services"):
            raise SendError(f"{remote} did not answer describe_parameters in {time.monotonic() - begin:.1f} s")
    descriptors = future.result().descriptors
    if not descriptors:
        raise SendError(f"{remote} has no parameter {name!r}")
    try:
        parameter = parameter_value(name, descriptors[0].type, values)
    except NmpcError as exc:
        raise SendError(str(exc)) from None
    future = client.set_parameters([parameter])
    if not _spin_until(executor, future.done, timeout):
        raise SendError(f"{remote} did not answer set_parameters in {timeout:.1f} s")
    (result,) = future.result().results
    if not result.successful:
        raise SendError(f"{remote} refused {name} = {parameter.value!r}: {result.reason or 'no reason given'}")
    return remote, parameter.value


def send(args: argparse.Namespace, ros_args: Sequence[str]) -> str:
    """Do what `args` says on a fresh rclpy context: the line to print; SendError if it failed."""
    import os

    import rclpy
    from rclpy.executors import SingleThreadedExecutor

    message = None if args.what == "param" else topic_message(args)  # bad shapes fail before any DDS
    born = time.monotonic()
    context = rclpy.Context()
    rclpy.init(args=["send", *ros_args], context=context)
    try:
        node = rclpy.create_node(f"send_{os.getpid()}", namespace=args.namespace, context=context,
                                 start_parameter_services=False)
        executor = SingleThreadedExecutor(context=context)
        executor.add_node(node)
        try:
            if message is not None:
                topic, msg, what = message
                watch = ControllerWatch(node, executor, node_name(node, args.node), topic)
                name, nodes, acknowledged = publish_latched(node, topic, msg, watch.reader, args.timeout,
                                                            lambda: watch.prepare(args, args.timeout, msg),
                                                            lambda name: watch.absent(name, args.timeout), born)
                if not acknowledged:
                    verdict = None if watch.before is None else watch.verdict(watch.before, args.timeout)
                    raise SendError(not_acknowledged(name, nodes, watch.reader, verdict, args.timeout))
                line = f"send: {what} on {name}, acknowledged by {', '.join(nodes) or 'its subscribers'}"
                return line + watch.outcome(what, args.timeout)  # SendError if the controller refused it
            remote, value = set_parameter(node, executor, args.node, args.name, args.values, args.timeout)
            return f"send: {remote} {args.name} = {value!r}"
        finally:
            executor.shutdown(timeout_sec=0)
            node.destroy_node()
    finally:
        rclpy.try_shutdown(context=context)


def main(argv: list[str] | None = None) -> int:
    own, ros_args = split_ros_args(sys.argv[1:] if argv is None else argv)
    parser = build_parser()
    args = parser.parse_args(own)
    try:
        line = send(args, ros_args)
    except SendError as exc:
        print(f"send: {exc}", file=sys.stderr)
        return 1
    except NmpcError as exc:  # a region the controller would refuse: a bad argument
        parser.exit(2, f"{PROG}: error: {exc}\n")
    except KeyboardInterrupt:
        return 130
    print(line)
    return 0


if __name__ == "__main__":
    sys.exit(main())
