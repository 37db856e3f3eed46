"""rclpy glue shared by the nodes. This module imports rclpy at its top: node modules import it
only inside functions, so they stay importable (and testable) where ROS 2 is not installed."""
from __future__ import annotations

import array
import os
import sys
import threading
import time
from types import SimpleNamespace
from typing import Any, Callable, NoReturn

import numpy as np
import rclpy
from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor, SetParametersResult
from rclpy.clock import Clock, ClockType
from rclpy.exceptions import NameValidationException, ParameterException
from rclpy.logging import get_logger
from rclpy.node import Node
from rclpy.qos import (DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy, qos_policy_name_from_kind,
                       qos_profile_system_default)

from ..bridge.config import PwsConfig, check_consistency, config_from_params
from ..bridge.params import SPECS, ParamSpec, spec_table, validate_param
from ..bridge.msgtypes import MESSAGE_TYPES
from ..core.errors import PwsError
from ._base import TF_MESSAGE_TYPE, ShutdownSafePublisher, ignore_further_interrupts, quiet_teardown, still_running_workers

try:  # Iron and later
    from rclpy.event_handler import PublisherEventCallbacks, SubscriptionEventCallbacks
except ImportError:  # pragma: no cover - Humble
    from rclpy.qos_event import PublisherEventCallbacks, SubscriptionEventCallbacks  # type: ignore

try:
    from rclpy.qos_overriding_options import QoSOverridingOptions
except ImportError:  # pragma: no cover
    QoSOverridingOptions = None  # type: ignore


# ---- message classes ----------------------------------------------------------------------

def rclpy_types() -> SimpleNamespace:
    """The ``types`` namespace of :mod:`pws_ros.bridge.msgtypes` from the installed ROS 2 packages."""
    import importlib

    ns = SimpleNamespace(flavour="rclpy")
    for attr, full in {**MESSAGE_TYPES, "TFMessage": TF_MESSAGE_TYPE}.items():  # + /tf_static, read by the nodes
        pkg, _, name = full.split("/")
        try:
            setattr(ns, attr, getattr(importlib.import_module(f"{pkg}.msg"), name))
        except (ImportError, AttributeError):
            pass  # e.g. MeshFile on older distros: builders skip what is missing
    ns.u8 = lambda a: array.array("B", np.ascontiguousarray(np.asarray(a, dtype=np.uint8)).tobytes())
    ns.f64 = lambda a: array.array("d", np.ascontiguousarray(np.asarray(a, dtype=np.float64)).tobytes())
    ns.f64fixed = lambda a: np.ascontiguousarray(np.asarray(a, dtype=np.float64).reshape(-1))
    return ns


# ---- QoS ----------------------------------------------------------------------------------

def qos(kind: str, depth: int) -> QoSProfile:
    """``sensor_data`` (best effort, volatile: matches reliable and best-effort publishers),
    ``reliable``, ``best_effort``, ``system_default`` or ``tf_static`` (reliable, transient local: what
    tf2's static broadcaster latches) with a KEEP_LAST ``depth``."""
    if kind == "tf_static":
        return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=int(depth), reliability=ReliabilityPolicy.RELIABLE,
                          durability=DurabilityPolicy.TRANSIENT_LOCAL)
    if kind == "system_default":
        p = QoSProfile(depth=int(depth))
        p.reliability = qos_profile_system_default.reliability
        p.durability = qos_profile_system_default.durability
        return p
    rel = ReliabilityPolicy.RELIABLE if kind == "reliable" else ReliabilityPolicy.BEST_EFFORT
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=int(depth), reliability=rel, durability=DurabilityPolicy.VOLATILE)


def _overrides() -> dict[str, Any]:
    if QoSOverridingOptions is None:
        return {}
    return {"qos_overriding_options": QoSOverridingOptions.with_default_policies()}


# ---- parameters ---------------------------------------------------------------------------

def descriptor(spec: ParamSpec) -> ParameterDescriptor:
    d = ParameterDescriptor(description=spec.description, read_only=bool(spec.read_only))
    if spec.choices is not None:
        d.additional_constraints = ("one of: " if spec.kind == "str" else "each one of: ") + ", ".join(spec.choices)
    if spec.range is not None:
        lo, hi = spec.range
        if spec.kind == "int":
            d.integer_range = [IntegerRange(from_value=int(lo), to_value=int(hi), step=1)]
        else:
            d.floating_point_range = [FloatingPointRange(from_value=float(lo), to_value=float(hi), step=0.0)]
            d.dynamic_typing = True  # accept "sigma: 1" (an integer) from YAML; validated by the table
    if spec.unit:
        d.additional_constraints = (d.additional_constraints + "; " if d.additional_constraints else "") + f"unit: {spec.unit}"
    return d


def declare_from_table(node: Node, node_kind: str) -> PwsConfig:
    """Declare every parameter ``node_kind`` uses (descriptions, ranges, read-only) and return the
    validated config (PwsError naming the bad parameter)."""
    specs = spec_table([node_kind])
    values: dict[str, Any] = {}
    for spec in specs:
        default = list(spec.default) if isinstance(spec.default, (list, tuple)) else spec.default
        param = node.declare_parameter(spec.name, default, descriptor(spec))
        values[spec.name] = param.value
    return config_from_params(values)


class ParamWatcher:
    """Validates every parameter change with the table (and cross-parameter rules) and hands the new
    config to ``on_change``; rejected changes are answered with the one-line reason."""

    def __init__(self, node: Node, node_kind: str, config: PwsConfig, on_change: Callable[[PwsConfig], None]):
        self.node = node
        self.config = config
        self.on_change = on_change
        self._lock = threading.Lock()
        self._pending: PwsConfig | None = None
        node.add_on_set_parameters_callback(self._validate)
        if hasattr(node, "add_post_set_parameters_callback"):
            node.add_post_set_parameters_callback(self._applied)
            self._post = True
        else:  # pragma: no cover - Humble
            self._post = False

    def _validate(self, params: list) -> SetParametersResult:
        changes = {}
        try:
            for p in params:
                if p.name not in SPECS:
                    continue  # use_sim_time, qos_overrides..., other parts of the node
                changes[p.name] = validate_param(p.name, p.value)
            new = self.config.with_params(changes) if changes else self.config
            check_consistency(new)
        except PwsError as exc:
            return SetParametersResult(successful=False, reason=str(exc))
        if changes:
            with self._lock:
                self._pending = new
            if not self._post:
                self._applied(params)
        return SetParametersResult(successful=True, reason="")

    def _applied(self, _params: list) -> None:
        with self._lock:
            new, self._pending = self._pending, None
        if new is None:
            return
        old, self.config = self.config, new
        diff = [f"{s.name}={getattr(new, s.attr)!r}" for s in SPECS.values() if getattr(new, s.attr) != getattr(old, s.attr)]
        if diff:
            self.node.get_logger().info("parameters changed: " + ", ".join(diff))
        self.on_change(new)


# ---- node context -------------------------------------------------------------------------

class NodeContext:
    """An rclpy node with the table's parameters, QoS helpers, message classes and a logger bridge.

    The node logic classes use only this interface (``types``, ``config``, ``on_change``, ``name``,
    ``log``, ``now_ns``, ``publisher``, ``subscription``, ``timer``, ``resolve``, ``qos_events``), so
    they are exercised without ROS by an in-memory context in the tests.
    """

    def __init__(self, node: Node, node_kind: str):
        self.node = node
        self.kind = node_kind
        self.name = node.get_name()
        self.types = rclpy_types()
        self.config = declare_from_table(node, node_kind)
        self.qos_events = 0
        self.closing = False  # set by run() before the node is torn down
        self.on_change: Callable[[PwsConfig], None] | None = None
        self.watcher = ParamWatcher(node, node_kind, self.config, self._changed)

    def ok(self) -> bool:
        """False once shutdown began (SIGINT shut the context down, or run() is tearing the node down)."""
        return not self.closing and self.node.context.ok()

    def _changed(self, cfg: PwsConfig) -> None:
        self.config = cfg
        if self.on_change is not None:
            self.on_change(cfg)

    def timer(self, period_s: float, callback: Callable[[], None]) -> Any:
        """A timer on the steady (wall) clock, not the node clock: with use_sim_time the node clock
        stops when `ros2 bag play --clock` pauses or ends, and health reports and the certifier's
        hand-over of assembled frames must go on then."""
        return self.node.create_timer(float(period_s), callback, clock=Clock(clock_type=ClockType.STEADY_TIME))

    def resolve(self, topic: str) -> str:
        return self.node.resolve_topic_name(topic)

    # logging with the (level, message) signature of the bridge
    def log(self, level: str, message: str) -> None:
        # one call site per severity: rclpy remembers the severity of each calling line and raises
        # "Logger severity cannot be changed between calls" if one line logs at two levels
        logger = self.node.get_logger()
        if level == "error":
            logger.error(message)
        elif level == "warn":
            logger.warning(message)
        else:
            logger.info(message)

    def now_ns(self) -> int:
        """Node clock now (sim time when use_sim_time is set)."""
        try:
            return int(self.node.get_clock().now().nanoseconds)
        except Exception:  # the node is being torn down under a busy worker
            if self.ok():
                raise
            return time.time_ns()  # nothing is published any more: any clock will do

    def _incompatible(self, what: str, topic: str) -> Callable[[Any], None]:
        def cb(event: Any) -> None:
            self.qos_events += 1
            try:
                policy = qos_policy_name_from_kind(event.last_policy_kind)
            except Exception:  # pragma: no cover
                policy = str(getattr(event, "last_policy_kind", "?"))
            self.node.get_logger().warning(
                f"incompatible QoS on {what} '{topic}' (policy {policy}, {getattr(event, 'total_count', '?')} so far): "
                f"no messages will flow; adjust input_qos/output_qos or qos_overrides")
        return cb

    def subscription(self, msg_type: Any, topic: str, callback: Callable[[Any], None], *, kind: str | None = None,
                     depth: int | None = None) -> Any:
        cfg = self.config
        profile = qos(kind or cfg.input_qos, depth or cfg.input_qos_depth)
        return self.node.create_subscription(
            msg_type, topic, callback, profile,
            event_callbacks=SubscriptionEventCallbacks(incompatible_qos=self._incompatible("subscription", topic)),
            **_overrides())

    def publisher(self, msg_type: Any, topic: str, *, kind: str | None = None, depth: int | None = None) -> Any:
        cfg = self.config
        profile = qos(kind or cfg.output_qos, depth or cfg.output_qos_depth)
        pub = self.node.create_publisher(
            msg_type, topic, profile,
            event_callbacks=PublisherEventCallbacks(incompatible_qos=self._incompatible("publisher", topic)),
            **_overrides())
        # a worker still busy with a frame when SIGINT shuts the context down publishes nothing
        return ShutdownSafePublisher(pub, self.ok)


# ---- running ------------------------------------------------------------------------------

def run(node_name: str, factory: Callable[[Node], Any], args: list[str] | None = None) -> NoReturn:
    """``rclpy.init``, create the node, build the logic with ``factory(node)``, spin, shut down, and end
    the process (``os._exit`` with the exit status: a node executable's ``main`` only).

    A PwsError at start-up (bad parameter, missing model ...) is logged as FATAL; exit status 2.
    """
    from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor

    rclpy.init(args=args)
    node = Node(node_name)
    logic = None
    code = 0
    try:
        logic = factory(node)
        executor = SingleThreadedExecutor()
        executor.add_node(node)
        executor.spin()
    except (PwsError, ParameterException, NameValidationException) as exc:
        node.get_logger().fatal(" ".join(str(exc).split()))
        code = 2
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        # Ctrl-C in a terminal: SIGINT reaches every process of the group, then ros2 launch sends its own;
        # that second SIGINT raised KeyboardInterrupt inside destroy_node. Shutting down already: ignore it,
        # and run every step even if one is interrupted before the handler is in place.
        ignore_further_interrupts()
        ctx = getattr(logic, "ctx", None)

        def mark_closing() -> None:
            if ctx is not None:
                ctx.closing = True  # a worker still busy publishes nothing from now on

        def close_logic() -> None:
            if logic is not None and hasattr(logic, "close"):
                logic.close()

        def say_busy() -> None:
            busy = still_running_workers()
            if busy:  # said by name after destroy_node: rosout cannot publish once SIGINT shut the context down
                get_logger(node_name).info(f"shutdown: the frame in flight is abandoned ({', '.join(busy)} still busy)")

        quiet_teardown([mark_closing, close_logic, node.destroy_node, say_busy, rclpy.try_shutdown],
                       lambda _level, text: get_logger(node_name).info(text))
    # The node's process ends here, without the interpreter's teardown: with a worker still inside torch
    # (shutdown is polled between axes) that teardown aborts ("terminate called without an active
    # exception", SIGABRT), and on a loaded machine it can outlast the 5 s ros2 launch grants after
    # SIGINT before escalating to SIGTERM (both logged as ERROR). Nothing is left to flush but stdio.
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(code)


