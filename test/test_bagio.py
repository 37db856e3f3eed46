"""pws_ros.bagio: robust rosbag2 reading (MCAP / sqlite3, directories, bare files, split, zstd,
damaged files, custom / service / unparseable types) and MCAP writing that other readers open."""
from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest

from conftest import shared_path
from pws_ros.bagio import BagReader, BagWriter, mcap_decoded_messages, prepare_output
from pws_ros.core.errors import PwsError

STRING = "std_msgs/msg/String"


def _jazzy():
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS2_JAZZY)


def _string(ts, text):
    return ts.types[STRING](data=text)


def write_rosbags(path: Path, items, *, storage: str = "mcap", compression: str | None = None, version: int = 9,
                  extra_types: dict | None = None):
    """``items``: (topic, msgtype, log_time, msg or raw bytes); ``extra_types``: msgtype -> definition text."""
    from rosbags.rosbag2 import Writer
    from rosbags.rosbag2.enums import CompressionFormat, CompressionMode, StoragePlugin
    from rosbags.typesys import get_types_from_msg

    ts = _jazzy()
    for name, text in (extra_types or {}).items():
        ts.register(get_types_from_msg(text, name))
    w = Writer(path, version=version, storage_plugin=StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3)
    if compression:
        w.set_compression({"file": CompressionMode.FILE, "message": CompressionMode.MESSAGE, "storage": CompressionMode.STORAGE}[compression],
                          CompressionFormat.ZSTD)
    conns = {}
    with w:
        for topic, msgtype, t, msg in items:
            if topic not in conns:
                conns[topic] = w.add_connection(topic, msgtype, typestore=ts)
            data = msg if isinstance(msg, (bytes, bytearray)) else ts.serialize_cdr(msg, msgtype)
            w.write(conns[topic], t, data)
    return path


def write_mcap_file(path: Path, items, *, chunk_size: int = 1024, schemas: dict | None = None):
    """A bare MCAP file written with the independent ``mcap`` writer: (topic, msgtype, log_time, cdr)."""
    from mcap.writer import CompressionType, Writer

    ts = _jazzy()
    with path.open("wb") as f:
        w = Writer(f, chunk_size=chunk_size, compression=CompressionType.ZSTD)
        w.start(profile="ros2", library="pws_ros-test")
        sids, cids = {}, {}
        for topic, msgtype, t, data in items:
            if msgtype not in sids:
                text = (schemas or {}).get(msgtype) or ts.generate_msgdef(msgtype, ros_version=2)[0]
                sids[msgtype] = w.register_schema(name=msgtype, encoding="ros2msg", data=text.encode())
            if topic not in cids:
                cids[topic] = w.register_channel(topic=topic, message_encoding="cdr", schema_id=sids[msgtype])
            w.add_message(channel_id=cids[topic], log_time=t, data=bytes(data), publish_time=t)
        w.finish()
    return path


def strings(n: int, topic: str = "/chatter", t0: int = 1_000, dt: int = 10):
    ts = _jazzy()
    return [(topic, STRING, t0 + i * dt, _string(ts, f"hello {i}")) for i in range(n)]


def read_all(path, **kw):
    warnings = []
    with BagReader(path, warn=warnings.append, **kw) as bag:
        out = [(m.topic, m.log_time_ns, bag.deserialize(m)) for m in bag.messages()]
        return out, warnings, bag


# ---- round trips -----------------------------------------------------------------------------

@pytest.mark.parametrize("storage,compression", [("mcap", None), ("mcap", "storage"), ("sqlite3", None),
                                                 ("sqlite3", "message"), ("mcap", "file")])
def test_directory_round_trip_all_storages_and_compressions(tmp_path, storage, compression):
    items = strings(7) + strings(3, "/other", t0=1_005)
    write_rosbags(tmp_path / "bag", items, storage=storage, compression=compression)
    got, warnings, bag = read_all(tmp_path / "bag")
    assert warnings == []
    expect = sorted(((t, lt, m.data) for t, _ty, lt, m in items), key=lambda x: x[1])
    assert [(t, lt, m.data) for t, lt, m in got] == expect
    assert bag.topics["/chatter"].count == 7 and bag.topics["/other"].count == 3
    assert bag.layout == "directory" and bag.backend == "rosbags"


@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
def test_bare_file_without_metadata(tmp_path, storage):
    items = strings(5)
    write_rosbags(tmp_path / "bag", items, storage=storage)
    f = next(p for p in (tmp_path / "bag").iterdir() if p.suffix in (".mcap", ".db3"))
    bare = tmp_path / f.name
    shutil.copy(f, bare)
    got, warnings, bag = read_all(bare)
    assert [m.data for _t, _lt, m in got] == [f"hello {i}" for i in range(5)]
    assert bag.layout == "file"
    # a directory whose metadata.yaml is missing is read file by file, with a warning
    (tmp_path / "bag" / "metadata.yaml").unlink()
    got2, warnings2, _ = read_all(tmp_path / "bag")
    assert [m.data for _t, _lt, m in got2] == [f"hello {i}" for i in range(5)]
    assert any("no metadata.yaml" in w for w in warnings2)


def test_files_are_merged_in_log_time_order(tmp_path):
    """Several storage files (a split bag without metadata) come out merged by log time."""
    ts = _jazzy()
    d = tmp_path / "split"
    d.mkdir()
    a = [("/a", STRING, t, ts.serialize_cdr(_string(ts, f"a{t}"), STRING)) for t in range(0, 100, 7)]
    b = [("/b", STRING, t, ts.serialize_cdr(_string(ts, f"b{t}"), STRING)) for t in range(3, 100, 5)]
    write_mcap_file(d / "part_0.mcap", a)
    write_mcap_file(d / "part_1.mcap", b)
    got, _w, _bag = read_all(d)
    times = [lt for _t, lt, _m in got]
    assert times == sorted(times) and len(got) == len(a) + len(b)
    assert {m.data for _t, _lt, m in got} == {f"a{t}" for t in range(0, 100, 7)} | {f"b{t}" for t in range(3, 100, 5)}


def test_truncated_mcap_keeps_the_complete_prefix(tmp_path):
    ts = _jazzy()
    items = [("/chatter", STRING, 1000 + i, ts.serialize_cdr(_string(ts, f"message number {i:04d} " + "x" * 64), STRING))
             for i in range(300)]
    f = write_mcap_file(tmp_path / "full.mcap", items, chunk_size=2048)
    data = f.read_bytes()
    for frac in (0.35, 0.8):
        cut = tmp_path / f"cut_{int(frac * 100)}.mcap"
        cut.write_bytes(data[: int(len(data) * frac)])
        got, warnings, bag = read_all(cut)
        assert any("truncated or corrupt" in w for w in warnings), warnings
        assert 0 < len(got) < 300
        # exactly the first k messages, intact
        assert [m.data for _t, _lt, m in got] == [f"message number {i:04d} " + "x" * 64 for i in range(len(got))]
        assert bag.recovered == [cut.name] and bag.files == [cut.name]
    # more of the file -> at least as many messages
    n35 = len(read_all(tmp_path / "cut_35.mcap")[0])
    n80 = len(read_all(tmp_path / "cut_80.mcap")[0])
    assert n80 > n35


def test_truncated_file_inside_a_bag_directory(tmp_path):
    ts = _jazzy()
    items = [("/chatter", STRING, 1000 + i, _string(ts, "y" * 4000 + str(i))) for i in range(600)]
    write_rosbags(tmp_path / "bag", items)  # > 1 MiB: several chunks
    f = next((tmp_path / "bag").glob("*.mcap"))
    f.write_bytes(f.read_bytes()[: int(f.stat().st_size * 0.7)])
    got, warnings, _bag = read_all(tmp_path / "bag")
    assert any("reading its storage files one by one" in w for w in warnings)
    assert 0 < len(got) < 600
    assert [m.data for _t, _lt, m in got] == ["y" * 4000 + str(i) for i in range(len(got))]


@pytest.mark.parametrize("content,needle", [(b"", "empty"), (b"\x00" * 2000, "not a readable MCAP"), (b"not a bag at all", "neither")])
def test_unreadable_files_name_the_problem(tmp_path, content, needle):
    f = tmp_path / ("bad.mcap" if needle != "neither" else "bad.bin")
    f.write_bytes(content)
    with pytest.raises(PwsError, match=needle):
        BagReader(f).open()
    with pytest.raises(PwsError, match="bag not found"):
        BagReader(tmp_path / "missing").open()


def test_corrupt_sqlite_is_refused_with_a_message(tmp_path):
    write_rosbags(tmp_path / "bag", strings(20), storage="sqlite3")
    f = next((tmp_path / "bag").glob("*.db3"))
    bare = tmp_path / "broken.db3"
    raw = bytearray(f.read_bytes())
    raw[100:] = b"\xff" * (len(raw) - 100)
    bare.write_bytes(bytes(raw))
    with pytest.raises(PwsError, match="broken.db3"):
        with BagReader(bare) as bag:
            list(bag.messages())
            raise PwsError("read broken.db3 without noticing")  # pragma: no cover


# ---- message definitions ---------------------------------------------------------------------

CUSTOM = "my_pkg/msg/Reading"
CUSTOM_DEF = "string sensor\nfloat64[] values\nuint32 count\n"


def test_custom_types_decode_with_their_own_definition(tmp_path):
    from rosbags.typesys import get_types_from_msg

    ts = _jazzy()
    ts.register(get_types_from_msg(CUSTOM_DEF, CUSTOM))
    R = ts.types[CUSTOM]
    items = [("/reading", CUSTOM, 10 + i, R(sensor=f"s{i}", values=np.arange(i, dtype=np.float64), count=i)) for i in range(4)]
    write_rosbags(tmp_path / "bag", items, extra_types={CUSTOM: CUSTOM_DEF})
    got, warnings, bag = read_all(tmp_path / "bag")
    assert warnings == [] and bag.topics["/reading"].decodable
    for i, (_t, _lt, m) in enumerate(got):
        assert m.sensor == f"s{i}" and m.count == i and np.array_equal(m.values, np.arange(i))


def test_only_the_types_a_bag_uses_are_made_and_jazzy_fills_in_what_it_does_not_define(tmp_path):
    """Registering a type makes a class of it (all of Jazzy's: about a quarter of a second at every bag opened): the
    reader's typestore holds the bag's topic types and what they use, no more; a type the bag's own definitions use
    without defining it comes from ROS 2 Jazzy."""
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    ts = _jazzy()
    empty = set(get_typestore(Stores.EMPTY).types)   # (rosbags' own: builtin_interfaces' Time and Duration)
    got, warnings, bag = read_all(write_rosbags(tmp_path / "plain", strings(3)))
    assert warnings == [] and set(bag.typestore.types) - empty == {STRING} and got[2][2].data == "hello 2"
    # a custom type whose stored definition uses std_msgs/Header without defining it
    stamped = "std_msgs/Header header\nint32 x\n"
    ts.register(get_types_from_msg(stamped, "my_pkg/msg/Stamped"))
    T, H, Time = ts.types["my_pkg/msg/Stamped"], ts.types["std_msgs/msg/Header"], ts.types["builtin_interfaces/msg/Time"]
    msg = T(header=H(stamp=Time(sec=7, nanosec=9), frame_id="cam"), x=-3)
    f = write_mcap_file(tmp_path / "stamped.mcap", [("/s", "my_pkg/msg/Stamped", 1, ts.serialize_cdr(msg, "my_pkg/msg/Stamped"))],
                        schemas={"my_pkg/msg/Stamped": stamped})
    got, warnings, bag = read_all(f)
    assert warnings == [] and bag.topics["/s"].decodable
    assert set(bag.typestore.types) - empty == {"my_pkg/msg/Stamped", "std_msgs/msg/Header"}
    m = got[0][2]
    assert (m.x, m.header.frame_id, m.header.stamp.sec, m.header.stamp.nanosec) == (-3, "cam", 7, 9)


def test_unparseable_and_service_types_are_skipped_with_a_warning(tmp_path):
    ts = _jazzy()
    text = ts.serialize_cdr(_string(ts, "x"), STRING)
    items = [("/ok", STRING, 1, text), ("/weird", "odd_pkg/msg/Broken", 2, b"\x00\x01\x00\x00"),
             ("/svc/_service_event", "odd_pkg/srv/Thing_Event", 3, b"\x00\x01\x00\x00"),
             ("/dangling", "odd_pkg/msg/Dangling", 4, b"\x00\x01\x00\x00")]
    schemas = {"odd_pkg/msg/Broken": "float64[ x", "odd_pkg/srv/Thing_Event": "int32 a\n---\nint32 b\n",
               "odd_pkg/msg/Dangling": "this is ((( not a message definition"}
    f = write_mcap_file(tmp_path / "mixed.mcap", items, schemas=schemas)
    warnings = []
    with BagReader(f, warn=warnings.append) as bag:
        assert bag.topics["/ok"].decodable
        assert not bag.topics["/weird"].decodable and not bag.topics["/svc/_service_event"].decodable
        assert any("odd_pkg/msg/Broken" in w for w in warnings)
        assert any("odd_pkg/srv/Thing_Event" in w and "service" in w for w in warnings)
        assert not bag.topics["/dangling"].decodable and any("undefined type" in w for w in warnings)
        msgs = list(bag.messages())
        assert len(msgs) == 4  # still read (e.g. to copy), only not decoded
        assert bag.deserialize(msgs[0]).data == "x"
        with pytest.raises(PwsError, match="/weird"):
            bag.deserialize(msgs[1])


def test_truncated_message_payload_is_a_clear_error(tmp_path):
    ts = _jazzy()
    img = ts.types["sensor_msgs/msg/Image"]
    hdr = ts.types["std_msgs/msg/Header"](stamp=ts.types["builtin_interfaces/msg/Time"](sec=1, nanosec=2), frame_id="f")
    good = ts.serialize_cdr(img(header=hdr, height=2, width=2, encoding="mono8", is_bigendian=0, step=2,
                                data=np.arange(4, dtype=np.uint8)), "sensor_msgs/msg/Image")
    f = write_mcap_file(tmp_path / "img.mcap", [("/img", "sensor_msgs/msg/Image", 5, good[:20])])
    with BagReader(f) as bag:
        m = next(bag.messages())
        with pytest.raises(PwsError, match="cannot decode a sensor_msgs/msg/Image message on /img"):
            bag.deserialize(m)


# ---- writing -----------------------------------------------------------------------------------

def test_writer_output_opens_with_rosbags_and_the_mcap_reader(tmp_path):
    from pws_ros.bridge import msgbuild

    T = msgbuild.rosbags_types()
    out = tmp_path / "out"
    with BagWriter(out) as w:
        for i in range(3):
            h = msgbuild.make_header(T, 10**9 + i, "cam")
            w.write("/image", msgbuild.image_from_numpy(h, np.full((4, 5, 3), i, np.uint8), T), 10**9 + i)
            w.write("/text", T.String(data=f"t{i}"), 10**9 + i)
    assert w.counts == {"/image": 3, "/text": 3}
    got, warnings, _ = read_all(out)
    assert warnings == [] and len(got) == 6
    dec = list(mcap_decoded_messages(out))
    assert [(t, lt) for t, _s, lt, _d in dec] == [(t, lt) for t, lt, _m in got]
    imgs = [d for t, _s, _lt, d in dec if t == "/image"]
    assert [bytes(d.data)[0] for d in imgs] == [0, 1, 2] and imgs[0].encoding == "rgb8"


def test_prepare_output_never_deletes_what_is_not_a_bag(tmp_path):
    write_rosbags(tmp_path / "old", strings(2))
    with pytest.raises(PwsError, match="already exists"):
        prepare_output(tmp_path / "old")
    prepare_output(tmp_path / "old", overwrite=True)
    assert not (tmp_path / "old").exists()
    other = tmp_path / "photos"
    other.mkdir()
    (other / "holiday.jpg").write_bytes(b"jpg")
    with pytest.raises(PwsError, match="not a rosbag2 bag directory"):
        prepare_output(other, overwrite=True)
    assert (other / "holiday.jpg").exists()
    f = tmp_path / "file.txt"
    f.write_text("x")
    with pytest.raises(PwsError, match="not a bag directory"):
        prepare_output(f, overwrite=True)
    assert prepare_output(tmp_path / "a" / "b" / "new") == tmp_path / "a" / "b" / "new"
    assert (tmp_path / "a" / "b").is_dir()


# ---- real recordings made by other people's software ------------------------------------------


@pytest.mark.parametrize("path", [
    ("rosbag2_written", "rosbag2_py_test_resources_mcap_talker"),
    ("rosbag2_written", "rosbag2_py_test_resources_sqlite3_talker"),
    ("rosbag2_written", "rosbag2_py_test_resources_mcap_talker", "talker.mcap"),
    ("rosbag2_written", "rosbag2_py_test_resources_sqlite3_talker", "talker.db3"),
])
def test_real_talker_bags(path):
    """rosbag2's own talker bags: rosbags' Reader.messages() yields nothing for them (QoS text differs
    between metadata.yaml and the file); the sqlite3 one stores a wrong definition of rcl_interfaces/Log."""
    got, warnings, bag = read_all(shared_path(*path))
    topic = [m.data for t, _lt, m in got if t == "/topic"]
    assert topic == [f"Hello, world! {i}" for i in range(10)]
    assert len(got) == 20
    logs = [m.msg for t, _lt, m in got if t == "/rosout"]
    assert logs == [f"Publishing: 'Hello, world! {i}'" for i in range(10)]


def test_real_split_bag_is_read_in_order():
    got, warnings, bag = read_all(shared_path("rosbag2_written", "rosbag2_py_test_resources_mcap_wbag"))
    assert len(bag.files) == 5 and len(got) == 6074 == bag.message_count
    times = [lt for _t, lt, _m in got]
    assert times == sorted(times)
    assert {t for t, _lt, _m in got} == {"AAA", "BBB", "CCC", "DDD", "EEE", "FFF", "GGG", "HHH"}


@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
def test_real_cdr_test_bag_with_test_msgs(storage):
    got, warnings, bag = read_all(shared_path("rosbag2_written", f"rosbag2_tests_resources_{storage}_cdr_test"))
    assert warnings == [] and len(got) == 7
    basic = [m for t, _lt, m in got if t == "/test_topic"]
    arrays = [m for t, _lt, m in got if t == "/array_topic"]
    assert len(basic) == 3 and len(arrays) == 4
    assert [m.int32_value for m in basic] == [123, 123, 123]
    assert all(list(m.bool_values) == [True, False, True] for m in arrays)
    assert all(m.string_values == ["Complex Hello1", "Complex Hello2", "Complex Hello3"] for m in arrays)
    assert all(m.constants_values[0].INT32_CONST == -30000 for m in arrays)


def test_real_bag_with_service_events():
    from rosbags.highlevel import AnyReader

    path = shared_path("rosbag2_written", "rosbag2_tests_resources_mcap_bag_with_topics_and_service_events")
    with pytest.raises(Exception, match="Could not parse"):
        with AnyReader([path]):
            pass
    got, warnings, bag = read_all_decodable(path)
    assert any("test_msgs/srv/BasicTypes_Event" in w for w in warnings)
    assert sorted(t for t, _m in got) == ["/test_topic1", "/test_topic2"]
    assert all(isinstance(m.string_value, str) for _t, m in got)


def read_all_decodable(path):
    warnings = []
    with BagReader(path, warn=warnings.append) as bag:
        out = [(m.topic, bag.deserialize(m)) for m in bag.messages() if bag.topics[m.topic].decodable]
        return out, warnings, bag


def test_real_kinect_cloud_and_realsense_images_decode():
    with BagReader(shared_path("kinect_organized_cloud")) as bag:
        (m,) = list(bag.messages())
        pc = bag.deserialize(m)
        assert (pc.height, pc.width, pc.point_step) == (480, 640, 32)
    with BagReader(shared_path("realsense_single_rgbd")) as bag:
        enc = {bag.deserialize(m).encoding for m in bag.messages(bag.topics_of_type("sensor_msgs/msg/Image"))}
        assert enc == {"mono16", "rgb8"}
