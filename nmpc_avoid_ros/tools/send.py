"""`send`: a target, an obstacle change or a run-time parameter to a running controller, without the
`ros2` CLI (it is not among the PyPI wheels).

    python -m nmpc_avoid_ros send target 5                 # y_t on `target` (p values: send target 8 6)
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

A message is published once on the latched QoS the package's publishers use (reliable, transient
local, depth 1) after a subscription of the controller (`--node`, default `controller`) matched,
and every other subscription the graph shows (a recorder's), with the graph unchanged for
GRAPH_SETTLE s (up to GRAPH_GRACE s more); `send` returns only when every matched reader
acknowledged it, so the process may exit at once without losing it (the line printed names the
nodes). A parameter goes through the node's
`<node>/set_parameters` service with the type the node declared (`mu 0` is sent as 0.0). Each wait
is bounded by `--timeout` s, except for a controller that is starting: the node is in the graph (it
is created before its solver is built) but has no subscription yet or does not answer (a first start
compiles its solver's code for a minute or two and logs so); `send` says so on stderr and waits for
it up to STARTING_TIMEOUT s.

`send` knows the controller's answer (tools/send_verdict.py): before a target goes out, its size is
checked against the controller's model (its `model` parameter, p values; `--no-check` skips this);
after the publish, `send` waits (up to `--timeout` s) until the controller's /diagnostics count the
message and reads its verdict there (`target_verdict`, `obstacles_verdict`, with the reason). A
controller that publishes no diagnostics (inactive, or lockstep without a plant) gives no verdict:
one line on stderr says so and the message counts as delivered.

Exit codes: 0 delivered and accepted (or set; or delivered with no verdict to read, said on stderr);
1 no controller listening (another reader is not enough), no acknowledgement, or the controller
refused it: the message (its reason from the diagnostics) or the parameter (one line on stderr says
why); 2 bad arguments, among them a target of the wrong size for the controller's model (the line
names the size it takes).
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from collections.abc import Sequence
from typing import Any

from ..core.errors import NmpcError
from .send_verdict import ControllerWatch

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
#: s `send` waits at most for a node that is in the graph but not serving yet (a first start compiles)
STARTING_TIMEOUT = 300.0
_noted_starting: set[str] = set()  # nodes `starting` said it waits for
#: ns of the markers `send` makes unless --ns
DEFAULT_NS = "send"


class SendError(NmpcError):
    """Nothing to send to, no acknowledgement, or a refused parameter: the one line `send` prints."""


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
    commands = parser.add_subparsers(dest="what", required=True, metavar="{target,obstacle,delete,clear,param}")
    target = commands.add_parser("target", parents=[common], help="a target y_t on `target`")
    target.add_argument("values", type=finite, nargs="+", metavar="Y", help="the target's p values")

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
    if args.what == "obstacle":
        return "obstacles", obstacle_message(args), f"{args.shape} (ns {args.ns!r}, id {args.id})"
    if args.what == "delete":
        return "obstacles", delete_message(args.ns, args.id), f"DELETE (ns {args.ns!r}, id {args.id})"
    return "obstacles", clear_message(), "DELETEALL"


# --- parameter values ------------------------------------------------------------------------------

_TRUE, _FALSE = ("true", "yes", "on"), ("false", "no", "off")


def _scalar(text: str, kind: str, name: str) -> Any:
    """One value of a parameter of `kind` ('double', 'integer', 'bool', 'string')."""
    if kind == "string":
        return text
    if kind == "bool":
        if text.lower() in _TRUE or text.lower() in _FALSE:
            return text.lower() in _TRUE
        raise NmpcError(f"{name} is a bool: true or false, got {text!r}")
    try:
        value = int(text) if kind == "integer" else float(text)
    except ValueError:
        raise NmpcError(f"{name} takes {'integers' if kind == 'integer' else 'numbers'}, got {text!r}") from None
    if kind == "double" and not math.isfinite(value):
        raise NmpcError(f"{name} must be finite, got {text!r}")
    return value


def _infer(texts: Sequence[str]) -> str:
    """The kind of untyped values, as YAML reads them (ros2 param set does the same)."""
    def kind(text: str) -> str:
        if text.lower() in _TRUE + _FALSE:
            return "bool"
        for k, convert in (("integer", int), ("double", float)):
            try:
                convert(text)
                return k
            except ValueError:
                pass
        return "string"

    kinds = {kind(t) for t in texts}
    if kinds == {"integer", "double"}:
        return "double"
    return kinds.pop() if len(kinds) == 1 else "string"


def _items(values: Sequence[str]) -> list[str]:
    """The values of an array: several arguments, or one '[a, b]' / 'a,b'."""
    if len(values) == 1:
        text = values[0].strip()
        if text.startswith("[") and text.endswith("]"):
            text = text[1:-1]
        return [v.strip() for v in text.split(",") if v.strip()] if ("," in text or values[0].strip() != text) \
            else [text] if text else []
    return list(values)


def parameter_value(name: str, type_: int, values: Sequence[str]) -> Any:
    """The rclpy Parameter `name` from command-line texts, in the declared ParameterType `type_` (0:
    not set, inferred); NmpcError with the reason for a wrong number or kind of value."""
    from rclpy.parameter import Parameter

    T = Parameter.Type
    scalars = {T.DOUBLE: "double", T.INTEGER: "integer", T.BOOL: "bool", T.STRING: "string"}
    arrays = {T.DOUBLE_ARRAY: "double", T.INTEGER_ARRAY: "integer", T.BOOL_ARRAY: "bool", T.STRING_ARRAY: "string"}
    declared = T(type_)
    if declared == T.NOT_SET:  # untyped: one value is a scalar, several (or [..]) an array
        items = _items(values)
        kind = _infer(items)
        is_array = len(values) > 1 or values[0].strip().startswith("[")
        declared = {v: k for k, v in (arrays if is_array else scalars).items()}[kind]
    if declared in scalars:
        if len(values) != 1:
            raise NmpcError(f"{name} takes one value, got {len(values)}: {' '.join(values)}")
        return Parameter(name, declared, _scalar(values[0], scalars[declared], name))
    if declared in arrays:
        return Parameter(name, declared, [_scalar(v, arrays[declared], name) for v in _items(values)])
    raise NmpcError(f"{name} has type {declared.name}, which send cannot set")


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
                    check: Any = None) -> tuple[str, list[str]]:
    """Publish `message` once on `topic` (LATCHED_QOS) once a subscription of the node `reader` (fully
    qualified) matched, and wait until every matched reader acknowledged it: (the resolved topic, the
    subscribing nodes). SendError otherwise.

    Another reader (a recorder) matching first is not enough: the message must reach `reader`, and a
    latched message is gone for a late reader once this process exits. `check()`, if given, runs just
    before the publish (the controller is configured then); what it raises stops the send."""
    from rclpy.duration import Duration

    from ..ros.parameters import LATCHED_QOS

    publisher = node.create_publisher(type(message), topic, LATCHED_QOS)
    name = publisher.topic_name
    end = time.monotonic() + timeout

    def readers() -> list[str]:
        return [f"{i.node_namespace.rstrip('/')}/{i.node_name}" for i in node.get_subscriptions_info_by_topic(name)
                if i.node_name != node.get_name()]

    begin = time.monotonic()
    while reader not in readers() or publisher.get_subscription_count() == 0:
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
        print(f"send: {name}: {matched} of the {listed} subscriptions the graph lists matched; the others may "
              f"not get this message", file=sys.stderr)
    if check is not None:
        check()
    publisher.publish(message)
    if not publisher.wait_for_all_acked(Duration(seconds=timeout)):
        raise SendError(f"{name}: the subscribers did not acknowledge the message in {timeout:.1f} s")
    return name, sorted(set(readers()))


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
                name, nodes = publish_latched(node, topic, msg, watch.reader, args.timeout,
                                              lambda: watch.prepare(args, args.timeout))
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
