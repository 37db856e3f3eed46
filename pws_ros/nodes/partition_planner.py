"""``partition_planner``: plans, per input frame, the camera poses of every configured axis.

Subscribes (reliable): ``cloud`` (PointCloud2) + ``cloud/camera_info`` from ``cloud_listener``,
paired by exact stamp. Publishes (reliable), per planned frame: ``plan/cloud`` (the cloud that was
planned, as received, for the projector: the camera outruns planning, so the projector must not have
to find it among newer clouds), ``plan`` (std_msgs/String JSON plan bundle: for each axis its
partition grid, or why it could not be planned; see :mod:`pws_ros.bridge.scheme`) and
``plan/poses/<axis>`` (PoseArray of the camera poses in the source optical frame, source stamp,
partition order). Plans are made for the render camera (the model's input size). Method ``pws``
plans on the dense cloud of ``dense_cloud_path``.

Every frame it takes gets a ``plan``: one it cannot convert (a malformed cloud or CameraInfo on its
inputs), or that ``cloud_listener`` reports on ``cloud/errors`` (bad input), gets a plan whose axes
all carry the reason, which the certifier publishes as the frame's ERROR certification. A malformed
message is a throttled WARN naming the topic; no callback raises.
"""
from __future__ import annotations

from typing import Any

from ..bridge import cloudconv, msgbuild, msgconv, scheme
from ..bridge.sync import StampMatcher
from ..core.errors import PwsError, require
from ._common import HealthPublisher, PosePublishers, Throttle, Worker, guarded, jump_logger, stage_engine, entry_point, WorkerNode

NODE_NAME = "partition_planner"


class PartitionPlannerNode(WorkerNode):
    def __init__(self, ctx: Any):
        self.ctx = ctx
        T = ctx.types
        cfg = ctx.config
        self.engine = stage_engine(ctx, input_size=True)
        self.matcher = StampMatcher(("cloud", "info"), tolerance_ns=0, queue_size=cfg.sync_queue_size, on_time_jump=jump_logger(ctx))
        self.pub_plan = ctx.publisher(T.String, "plan")
        self.pub_cloud = ctx.publisher(T.PointCloud2, "plan/cloud")
        self.poses = PosePublishers(ctx)
        ctx.on_change = self.poses.update
        self.planned = 0
        self.failed_inputs = 0
        self.throttle = Throttle()
        self.worker = Worker("pws-planner", self._process, ctx.log)

        def sub(msg_type: Any, topic: str, fn: Any) -> Any:
            return ctx.subscription(msg_type, topic, guarded(ctx, self.throttle, topic, fn), kind=cfg.output_qos, depth=cfg.output_qos_depth)

        self.subs = [
            sub(T.PointCloud2, "cloud", lambda m: self._add("cloud", m)),
            sub(T.CameraInfo, "cloud/camera_info", lambda m: self._add("info", m)),
            sub(T.String, "cloud/errors", self._on_input_error),
        ]
        self.health = HealthPublisher(ctx, self._counters)

    def _add(self, stream: str, msg: Any) -> None:
        got = self.matcher.add(stream, msgconv.header_stamp_ns(msg), msg)
        if got is not None:
            self.worker.submit(got)

    def _on_input_error(self, msg: Any) -> None:
        stamp, frame_id, reason = scheme.parse_input_error(msg)
        self._publish_failed(stamp, frame_id, f"input: {reason}")

    def _publish_failed(self, stamp_ns: int, frame_id: str, reason: str) -> None:
        """A plan giving every configured axis ``reason``: the certifier publishes the frame's ERROR."""
        cfg = self.ctx.config
        bundle = scheme.PlanBundle(int(stamp_ns), str(frame_id), cfg.method, None, list(cfg.axes), errors={a: reason for a in cfg.axes})
        self.pub_plan.publish(scheme.plan_bundle_message(bundle, self.ctx.types))
        self.failed_inputs += 1

    def _process(self, matched: Any) -> None:
        T = self.ctx.types
        self.engine.config = cfg = self.ctx.config
        cloud_msg, info_msg = matched["cloud"], matched["info"]
        try:
            cloud, _ = cloudconv.cloud_from_pointcloud2(cloud_msg)
            require(len(cloud) > 0, "the cloud has no valid point")
            intr = msgconv.intrinsics_from_camera_info(info_msg)
        except PwsError as exc:  # a malformed cloud or CameraInfo on the planner's inputs: the frame's ERROR
            self._publish_failed(matched.stamp_ns, msgconv.frame_id_of(cloud_msg), f"planner input: {exc}")
            raise
        bundle = self.engine.plan_bundle(cloud, intr, matched.stamp_ns, cloud_msg.header.frame_id)
        if cfg.publish_poses:
            for axis, plan in bundle.plans.items():
                self.poses.publish(axis, msgbuild.plan_to_pose_array(cloud_msg.header, plan, T))
        if bundle.plans:  # the projector renders from this very cloud
            self.pub_cloud.publish(cloud_msg)
        self.pub_plan.publish(scheme.plan_bundle_message(bundle, T))
        for axis, reason in bundle.errors.items():
            self.ctx.log("warn", f"frame {matched.stamp_ns} axis {axis}: cannot plan: {reason}")
        self.planned += 1

    def _counters(self) -> dict[str, Any]:
        w = self.worker
        return {"activity": "planned", "rate_hz": w.rate.rate(), "frames_in": self.matcher.matched, "frames_processed": self.planned,
                "frames_dropped": w.slot.dropped + self.matcher.total_dropped(), "device": self.engine.device,
                "last_error": "", "warning": w.last_error, "extra": {"time_jumps_back": self.matcher.time_jumps,
                                                                       "failed_inputs": self.failed_inputs}}


main = entry_point(NODE_NAME, PartitionPlannerNode)


if __name__ == "__main__":
    main()
