"""Which topics of a bag are the camera input (by message type unless given), and the depth -> colour extrinsic."""
from __future__ import annotations

from typing import Any

from ..bagio import BagReader
from ..bridge import msgconv, outputs
from ..bridge.config import PwsConfig, depth_info_topic
from ..core.errors import PwsError, require
from ..core.registration import Extrinsic, chain_transform
from .options import (COLOR_ENCODINGS, DEPTH_ENCODINGS, GROUND_TRUTH_TOPIC, REALSENSE_STREAM, T_CAMERA_INFO, T_DIAGNOSTIC_ARRAY,
                      T_IMAGE, T_POINTCLOUD2, T_TF_MESSAGE, T_TRANSFORM, TF_STATIC_TOPIC, InputTopics)


def _path_parts(topic: str) -> list[str]:
    return [p for p in topic.split("/") if p]


def _common_prefix(a: str, b: str) -> int:
    n = 0
    for x, y in zip(_path_parts(a), _path_parts(b)):
        if x != y:
            break
        n += 1
    return n


def _resolve_topic(bag: BagReader, name: str, msgtype: str, flag: str) -> str:
    cand = [name, "/" + name.lstrip("/")]
    found = next((c for c in cand if c in bag.topics), None)
    require(found is not None, f"{flag} {name}: no such topic in {bag.path} (it holds: {bag.describe()})")
    info = bag.topics[found]
    require(info.msgtype == msgtype, f"{flag} {found} is a {info.msgtype} topic, expected {msgtype}")
    require(info.decodable, f"{flag} {found} cannot be decoded: {info.skip_reason}")
    return found


def _config_topic(bag: BagReader, name: str, msgtype: str) -> str:
    """A config topic name if the bag has it with that type (relative names match the root namespace)."""
    if not name:
        return ""
    for c in (name, "/" + name.lstrip("/")):
        info = bag.topics.get(c)
        if info is not None and info.msgtype == msgtype and info.decodable:
            return c
    return ""


def discover_inputs(bag: BagReader, config: PwsConfig, overrides: dict[str, str] | None = None) -> InputTopics:
    """Choose the camera topics of ``bag``: ``overrides`` (``cloud``, ``depth``, ``color``, ``info``,
    ``depth_info``, ``truth``) first, then the config's topic names when the bag has them, then by
    message type (an organized PointCloud2; a depth + colour Image pair, preferring registered /
    aligned depth of the colour's size; the CameraInfo closest to the colour topic by name; a separate
    depth CameraInfo; for depth that is not registered, the depth -> colour extrinsic from the
    RealSense recorder's ``.../tf/<group>`` topics or ``/tf_static``, without which it is refused). An
    empty ``depth_info`` override, or an empty ``depth_camera_info_topic`` in the config, turns that check
    off (no depth CameraInfo)."""
    ov = {k: v for k, v in (overrides or {}).items() if v}
    no_depth_info = (overrides or {}).get("depth_info") == "" or ("depth_info" not in ov and config.depth_camera_info_topic == "")
    flags = {"cloud": "--cloud-topic", "depth": "--depth-topic", "color": "--color-topic", "info": "--info-topic",
             "depth_info": "--depth-info-topic", "truth": "--truth-topic"}
    types = {"cloud": T_POINTCLOUD2, "depth": T_IMAGE, "color": T_IMAGE, "info": T_CAMERA_INFO, "depth_info": T_CAMERA_INFO,
             "truth": T_DIAGNOSTIC_ARRAY}
    chosen: dict[str, str] = {}
    for role, name in ov.items():
        require(role in flags, f"unknown input role {role!r}")
        chosen[role] = _resolve_topic(bag, name, types[role], flags[role])
    notes: list[str] = []
    for role, name in (("cloud", config.points_topic), ("depth", config.depth_topic), ("color", config.color_topic),
                       ("info", config.camera_info_topic), ("depth_info", depth_info_topic(config))):
        if role not in chosen and not (role == "depth_info" and no_depth_info):
            t = _config_topic(bag, name, types[role])
            if t:
                chosen[role] = t
    if "cloud" in ov:
        mode = "pointcloud2"
    elif "depth" in ov or "color" in ov:
        mode = "rgbd"
    else:
        mode = config.input_mode

    clouds = bag.topics_of_type(T_POINTCLOUD2)
    images = bag.topics_of_type(T_IMAGE)
    infos = bag.topics_of_type(T_CAMERA_INFO)
    images = [t for t in images if not t.endswith("/" + outputs.PREVIEW)]
    peek_topics = [t for t in clouds + images + infos if bag.topics[t].count != 0]
    first = bag.first_messages(peek_topics, max_scan=20_000) if peek_topics else {}
    decoded: dict[str, Any] = {}
    for t, msgs in first.items():
        if msgs:
            try:
                decoded[t] = bag.deserialize(msgs[0])
            except PwsError as exc:
                notes.append(f"cannot decode the first message of {t}: {exc}")

    def size(t: str) -> tuple[int, int] | None:
        m = decoded.get(t)
        return (int(m.height), int(m.width)) if m is not None else None

    # -- point clouds --
    if "cloud" not in chosen and mode in ("auto", "pointcloud2"):
        organized = [t for t in clouds if t in decoded and int(decoded[t].height) > 1]

        def cscore(t: str) -> tuple:
            name = t.lower()
            return (-("registered" in name) - ("points" in name) - ("depth" in name), t)

        if organized:
            chosen["cloud"] = sorted(organized, key=cscore)[0]
            if len(organized) > 1:
                notes.append(f"several organized PointCloud2 topics ({', '.join(organized)}): using {chosen['cloud']} (--cloud-topic to choose)")
        elif mode == "pointcloud2" and clouds:
            chosen["cloud"] = sorted(clouds)[0]
            notes.append(f"no organized PointCloud2: using the unorganized {chosen['cloud']} (needs a CameraInfo)")

    # -- depth + colour --
    def encoding(t: str) -> str:
        m = decoded.get(t)
        return str(getattr(m, "encoding", "")).lower() if m is not None else ""

    if mode in ("auto", "rgbd") and not ("depth" in chosen and "color" in chosen):
        depths = [t for t in images if encoding(t) in DEPTH_ENCODINGS]
        colors = [t for t in images if encoding(t) in COLOR_ENCODINGS]
        if "depth" in chosen:
            depths = [chosen["depth"]]
        if "color" in chosen:
            colors = [chosen["color"]]
        best = None
        for d in depths:
            for c in colors:
                if d == c:
                    continue
                name = d.lower()
                score = (4 * (size(d) == size(c) and size(d) is not None) + 2 * ("aligned" in name or "registered" in name)
                         + 0.01 * _common_prefix(d, c))
                key = (-score, d, c)
                if best is None or key < best[0]:
                    best = (key, d, c)
        if best is not None:
            chosen.setdefault("depth", best[1])
            chosen.setdefault("color", best[2])
        elif mode == "rgbd" or not chosen.get("cloud"):
            if depths and not colors:
                notes.append(f"depth image {depths[0]} has no colour image topic beside it")
            elif colors and not depths:
                notes.append(f"colour image {colors[0]} has no depth image topic beside it")

    # -- camera info --
    ref = chosen.get("color") or chosen.get("cloud", "")
    if "info" not in chosen and ref and infos:
        want = size(ref)
        cands = [t for t in infos if t != chosen.get("depth_info")]
        cands.sort(key=lambda t: (-(size(t) == want and want is not None), -_common_prefix(t, ref), t))
        if cands and (chosen.get("color") or size(cands[0]) == want):
            chosen["info"] = cands[0]
        elif cands:
            notes.append(f"no CameraInfo of the cloud's size {want[1] if want else '?'}x{want[0] if want else '?'}: "
                         f"intrinsics are estimated from the organized cloud")
    if "depth_info" not in chosen and chosen.get("depth") and chosen.get("info") and not no_depth_info:
        d, c = chosen["depth"], chosen["color"]
        cands = [t for t in infos if t != chosen["info"] and _common_prefix(t, d) > _common_prefix(t, c)]
        cands.sort(key=lambda t: (-_common_prefix(t, d), t))
        if cands:
            chosen["depth_info"] = cands[0]

    # -- depth -> colour extrinsic, for depth that is not registered --
    extrinsic, extrinsic_from = None, ""
    if mode != "pointcloud2" and all(chosen.get(k) in decoded for k in ("depth", "color", "info")):
        extrinsic, extrinsic_from = _find_extrinsic(bag, chosen, decoded, config, notes)

    # -- ground truth --
    if "truth" not in chosen:
        diag = bag.topics_of_type(T_DIAGNOSTIC_ARRAY)
        if GROUND_TRUTH_TOPIC in diag:
            chosen["truth"] = GROUND_TRUTH_TOPIC
        else:
            gt = [t for t in diag if t.rstrip("/").endswith("ground_truth")]
            if gt:
                chosen["truth"] = gt[0]

    has_cloud = bool(chosen.get("cloud"))
    has_rgbd = bool(chosen.get("depth") and chosen.get("color"))
    if mode == "auto":
        mode = "auto" if (has_cloud and has_rgbd) else ("pointcloud2" if has_cloud else "rgbd")
    if mode == "pointcloud2":
        require(has_cloud, _no_input_message(bag, "no PointCloud2 topic", notes))
    else:
        require(has_rgbd or has_cloud, _no_input_message(bag, "no organized PointCloud2 and no depth + colour Image pair", notes))
        require(has_rgbd, _no_input_message(bag, "no depth + colour Image pair", notes))
        require(bool(chosen.get("info")), f"no sensor_msgs/CameraInfo for the colour camera {chosen['color']} in {bag.path} "
                                          f"(it holds: {bag.describe()}); give one with --info-topic")
    return InputTopics(mode, chosen.get("cloud", ""), chosen.get("depth", "") if mode != "pointcloud2" else "",
                       chosen.get("color", "") if mode != "pointcloud2" else "", chosen.get("info", ""),
                       chosen.get("depth_info", "") if mode != "pointcloud2" else "", chosen.get("truth", ""), notes,
                       extrinsic, extrinsic_from)


def _find_extrinsic(bag: BagReader, chosen: dict[str, str], decoded: dict[str, Any], config: PwsConfig,
                    notes: list[str]) -> tuple[Extrinsic | None, str]:
    """The depth -> colour extrinsic when the first depth + colour pair is not registered: from the
    RealSense recorder's ``.../tf/<group>`` topics of both streams, else from ``/tf_static`` between
    the two images' frame ids. ``(None, "")`` when the pair is registered or nothing is found."""
    d, c = chosen["depth"], chosen["color"]
    dinfo = decoded.get(chosen.get("depth_info", ""))
    try:
        problem = msgconv.registration_problem(decoded[d], decoded[c], decoded[chosen["info"]], dinfo,
                                               require_same_frame=config.require_same_frame)
    except PwsError:
        return None, ""   # a bad CameraInfo: the input check says so
    if not problem:
        return None, ""
    if dinfo is None:
        notes.append(f"{problem}; registering it needs the depth camera's CameraInfo: none was found (--depth-info-topic)")
        return None, ""
    tried = []
    md, mc = REALSENSE_STREAM.match(d), REALSENSE_STREAM.match(c)
    if md and mc:
        tf_topics = set(bag.topics_of_type(T_TRANSFORM))
        for t_d in sorted(t for t in tf_topics if t.startswith(md.group(1) + "/tf/")):
            t_c = mc.group(1) + "/tf/" + t_d.rsplit("/", 1)[1]
            if t_c not in tf_topics:
                continue
            first = bag.first_messages([t_d, t_c], max_scan=20_000)
            try:
                ref_to_d, ref_to_c = (msgconv.extrinsic_from_transform(bag.deserialize(first[t][0])) for t in (t_d, t_c))
            except (PwsError, KeyError, IndexError) as exc:
                notes.append(f"cannot read the extrinsics {t_d} / {t_c}: {exc}")
                continue
            return ref_to_d.inverse().then(ref_to_c), f"{t_d} and {t_c} (RealSense recorder)"
        tried.append(f"no {md.group(1)}/tf/N + {mc.group(1)}/tf/N topics")
    dframe = str(decoded[d].header.frame_id or "").lstrip("/")
    cframe = str(decoded[c].header.frame_id or "").lstrip("/")
    if not (dframe and cframe and dframe != cframe):
        tried.append(f"the images' frame ids {dframe!r} and {cframe!r} do not name two frames to look up in TF")
    elif TF_STATIC_TOPIC not in bag.topics_of_type(T_TF_MESSAGE):
        tried.append(f"no {TF_STATIC_TOPIC} topic")
    else:
        edges = []
        for m in bag.messages([TF_STATIC_TOPIC]):
            try:
                edges += msgconv.transforms_from_tf_message(bag.deserialize(m))
            except (PwsError, AttributeError) as exc:
                notes.append(f"skipping a {TF_STATIC_TOPIC} message: {exc}")
        found = chain_transform(edges, dframe, cframe) if edges else None
        if found is not None:
            return found, f"{TF_STATIC_TOPIC} ({dframe!r} -> {cframe!r})"
        tried.append(f"no transform between {dframe!r} and {cframe!r} on {TF_STATIC_TOPIC}")
    notes.append(f"{problem}, and no depth -> colour extrinsic was found to register it ({'; '.join(tried)})")
    return None, ""


def _no_input_message(bag: BagReader, what: str, notes: list[str]) -> str:
    extra = f" ({'; '.join(notes)})" if notes else ""
    return (f"no camera input in {bag.path}: {what}{extra}; expected an organized sensor_msgs/PointCloud2, or a depth Image "
            f"(16UC1/mono16/32FC1) + a colour Image + a CameraInfo; the bag holds: {bag.describe()} "
            f"(choose topics with --cloud-topic, or --depth-topic --color-topic --info-topic)")


