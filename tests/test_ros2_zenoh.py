"""ROS 2 over Zenoh the way rmw_zenoh speaks it (slam.io.ros2): type hashes, keys, liveliness tokens and attachments,
and a live agent seen by a client nobody here wrote, `zenoh-ros2-sdk`, over real Zenoh on localhost: it publishes
the camera topics and subscribes to everything the agent publishes, with the message definitions shipped in
tests/ros2_definitions (no network); its graph query shows the node and its publishers. Bad camera input is one
line naming the topic. Skipped without eclipse-zenoh / rosbags (and the third-party test without the SDK)."""

from __future__ import annotations

import socket
import threading
import time
import warnings
from pathlib import Path

import numpy as np
import pytest

zenoh = pytest.importorskip("zenoh")
pytest.importorskip("rosbags")

from swarmsplat.slam.io.ros2 import keys, type_hash  # noqa: E402
from swarmsplat.slam.io.ros2.types import MSG_DIR, dds_name, store  # noqa: E402

DEFINITIONS = Path(__file__).resolve().parent / "ros2_definitions"
FRAMES = 10


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_type_hashes_are_those_of_ros2_jazzy():
    # published by ROS 2 Jazzy (`ros2 interface` / rmw_zenoh keys); computed here from the shipped definitions
    assert type_hash("geometry_msgs/msg/PoseStamped") == \
        "RIHS01_10f3786d7d40fd2b54367835614bff85d4ad3b5dab62bf8bca0cc232d73b4cd8"
    assert type_hash("sensor_msgs/msg/Image") == \
        "RIHS01_d31d41a9a4c4bc8eae9be757b0beed306564f7526c88ea6a4588fb9582527d47"
    from rosbags.typesys import Stores, get_typestore

    jazzy = get_typestore(Stores.ROS2_JAZZY)  # rosbags' own copy of the Jazzy definitions
    shipped = sorted(f"{p.parent.name}/msg/{p.stem}" for p in MSG_DIR.glob("*/*.msg"))
    assert len(shipped) >= 20
    for name in shipped:
        assert type_hash(name) == jazzy.hash_rihs01(name), name
    assert dds_name("visualization_msgs/msg/MarkerArray") == "visualization_msgs::msg::dds_::MarkerArray_"


def test_keys_tokens_and_attachments_follow_rmw_zenoh():
    h = type_hash("geometry_msgs/msg/PoseStamped")
    key = keys.topic_key(3, "/swarmsplat/a/pose", "geometry_msgs/msg/PoseStamped", h)
    assert key == f"3/swarmsplat/a/pose/geometry_msgs::msg::dds_::PoseStamped_/{h}"
    assert keys.parse_topic_key(key) == (3, "/swarmsplat/a/pose", "geometry_msgs/msg/PoseStamped", h)
    assert keys.parse_topic_key("camera/color/image_raw") is None  # a bridge key
    assert keys.node_token(0, "abc", 2, "/", "swarmsplat_a") == "@ros2_lv/0/abc/2/2/NN/%/%/swarmsplat_a"
    tok = keys.endpoint_token(0, "abc", 2, 7, "MP", "/robots/r1", "swarmsplat_a", "/swarmsplat/a/pose",
                              "geometry_msgs/msg/PoseStamped", h, keys.Qos(reliable=False, depth=5))
    assert tok == (f"@ros2_lv/0/abc/2/7/MP/%/%robots%r1/swarmsplat_a/%swarmsplat%a%pose/"
                   f"geometry_msgs::msg::dds_::PoseStamped_/{h}/2::,5:,:,:,,")
    assert keys.Qos().text() == "::,10:,:,:,,"  # ROS 2's default profile
    gid = bytes(range(16))
    att = keys.attachment(41, 1_700_000_000_123_456_789, gid)
    assert len(att) == 33 and att[16] == 16
    assert keys.parse_attachment(att) == (41, 1_700_000_000_123_456_789, gid)


# ---- bad input: one line naming the topic, valid frames still come ------------------------------------------------


def _image(ty, t: float, w: int, h: int, encoding: str, data: np.ndarray):
    from swarmsplat.slam.io.ros2 import messages as M

    return ty["sensor_msgs/msg/Image"](header=M.header(ty, t, "camera"), height=h, width=w, encoding=encoding,
                                       is_bigendian=0, step=data.size // h, data=data.reshape(-1))


def _info(ty, t: float, w: int, h: int):
    from swarmsplat.slam.io.ros2 import messages as M

    roi = ty["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)
    return ty["sensor_msgs/msg/CameraInfo"](
        header=M.header(ty, t, "camera"), height=h, width=w, distortion_model="plumb_bob", d=np.zeros(5),
        k=np.array([50.0, 0, w / 2, 0, 50.0, h / 2, 0, 0, 1]), r=np.eye(3).reshape(-1), p=np.zeros(12),
        binning_x=0, binning_y=0, roi=roi)


def test_bad_camera_input_is_one_line_naming_the_topic_and_valid_frames_go_on():
    from swarmsplat.slam.io.live import ZenohRos2Source, zenoh_config
    from swarmsplat.slam.io.ros2.types import serialize

    ty = store().types
    port = _free_port()
    src = ZenohRos2Source("", name="live", listen=[f"tcp/127.0.0.1:{port}"], domain=0)
    _, conf = zenoh_config(connect=[f"tcp/127.0.0.1:{port}"])
    robot = zenoh.open(conf)
    w, h = 8, 6
    rgb = np.full((h, w, 3), 100, np.uint8)
    mm = np.full((h, w), 1500, "<u2").view(np.uint8)

    def rmw(topic: str, msgtype: str, hash_: str | None = None) -> str:
        return keys.topic_key(0, topic, msgtype, hash_ or type_hash(msgtype))

    image, info = "sensor_msgs/msg/Image", "sensor_msgs/msg/CameraInfo"
    try:
        t_end = time.time() + 20
        while not list(robot.info.peers_zid()) and time.time() < t_end:
            time.sleep(0.05)
        time.sleep(0.5)
        robot.put(rmw("/camera/color/camera_info", info), serialize(_info(ty, 1.0, w, h)))
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            src.wait_camera(20)
            sends = [  # (time, colour key, colour message)
                (1.0, rmw("/camera/color/image_raw", image), _image(ty, 1.0, w, h, "yuv422", rgb)),  # encoding
                (2.0, rmw("/camera/color/image_raw", image, "RIHS01_" + "0" * 64), _image(ty, 2.0, w, h, "rgb8", rgb)),
                (3.0, rmw("/camera/color/image_raw", image), _image(ty, 3.0, w + 2, h, "rgb8",
                                                                    np.full((h, w + 2, 3), 9, np.uint8))),  # size
                (4.0, rmw("/camera/color/image_raw", image), _image(ty, 4.0, w, h, "rgb8", rgb)),  # valid
            ]
            robot.put(keys.topic_key(7, "/camera/color/image_raw", image, type_hash(image)),  # another domain
                      serialize(_image(ty, 0.5, w, h, "rgb8", rgb)))
            for t, ckey, cmsg in sends:
                robot.put(ckey, serialize(cmsg))
                dmsg = _image(ty, t, cmsg.width, h, "16UC1", np.full((h, cmsg.width), 1500, "<u2").view(np.uint8)
                              if cmsg.width != w else mm)
                robot.put(rmw("/camera/depth/image_raw", image), serialize(dmsg))
                time.sleep(0.05)
            frames = list(src.frames(idle_timeout=3.0, silent_warning=0))
    finally:
        robot.close()
        src.close()
    assert [f.timestamp for f, _, _ in frames] == [4.0]  # the valid frame, after three refused ones
    assert src.stats.samples["color"] == 4  # the sample of domain 7 is another ROS graph's: not read
    lines = [str(c.message) for c in caught]
    assert all("\n" not in m for m in lines)
    assert any(m.startswith("/camera/color/image_raw (Zenoh key 0/camera/color/image_raw/") and
               "colour encoding 'yuv422' is not supported; expected one of rgb8" in m for m in lines), lines
    assert any(m.startswith("/camera/color/image_raw: type hash RIHS01_000") and
               f"expected {type_hash(image)}" in m for m in lines), lines
    assert any(m.startswith("/camera/color/camera_info: camera_info of 8x6 but images of 10x6 on "
                            "/camera/color/image_raw") for m in lines), lines


# ---- a client nobody here wrote --------------------------------------------------------------------------------


@pytest.fixture
def sdk():
    sdk = pytest.importorskip("zenoh_ros2_sdk")
    from zenoh_ros2_sdk import message_registry
    from zenoh_ros2_sdk.session import ZenohSession

    message_registry._registry = message_registry.MessageRegistry(str(DEFINITIONS))  # no download: ours
    yield sdk
    if ZenohSession._instance is not None:
        ZenohSession._instance.close()
    ZenohSession._instance = None
    message_registry._registry = None


@pytest.fixture(scope="module")
def sequence(tmp_path_factory):
    from swarmsplat.slam.io.datasets import load_sequence
    from swarmsplat.slam.synthetic import GeneratorConfig, generate

    root = generate(tmp_path_factory.mktemp("ros2") / "d", GeneratorConfig.preset("tiny", agents=1, frames=FRAMES))
    return load_sequence(root / "agent_0")


SUBSCRIBED = {"pose": ("/swarmsplat/live/pose", "geometry_msgs/msg/PoseStamped"),
              "tf": ("/tf", "tf2_msgs/msg/TFMessage"),
              "path": ("/swarmsplat/live/path", "nav_msgs/msg/Path"),
              "submap": ("/swarmsplat/live/submap", "sensor_msgs/msg/PointCloud2"),
              "map": ("/swarmsplat/live/map", "sensor_msgs/msg/PointCloud2"),
              "loops": ("/swarmsplat/live/loops", "visualization_msgs/msg/MarkerArray")}


def _camera_driver(sdk, port: int, seq, seen: dict, done: threading.Event) -> None:
    """The robot: zenoh-ros2-sdk publishes rgb8 colour, 16UC1 depth and CameraInfo once the agent's node is up,
    then reads the ROS graph."""
    try:
        t_end = time.time() + 120
        while time.time() < t_end:  # the agent listens once it has started
            try:
                socket.create_connection(("127.0.0.1", port), timeout=1).close()
                break
            except OSError:
                time.sleep(0.2)
        Header = sdk.get_message_class("std_msgs/msg/Header")
        Time = sdk.get_message_class("builtin_interfaces/msg/Time")
        ROI = sdk.get_message_class("sensor_msgs/msg/RegionOfInterest")
        pubs = {r: sdk.ROS2Publisher(t, m, node_name="camera_driver", router_port=port)
                for r, t, m in (("color", "/camera/color/image_raw", "sensor_msgs/msg/Image"),
                                ("depth", "/camera/depth/image_raw", "sensor_msgs/msg/Image"),
                                ("info", "/camera/color/camera_info", "sensor_msgs/msg/CameraInfo"))}
        session = sdk.ZenohSession.get_instance(router_port=port)
        for p in pubs.values():  # a reliable camera driver waits rather than drops a frame on a loaded machine
            p.pub.undeclare()  # (the SDK maps reliable to Zenoh's blocking congestion control only on other
            p.pub = session.session.declare_publisher(  # zenoh-python versions)
                p.keyexpr, congestion_control=zenoh.CongestionControl.BLOCK)
        while time.time() < t_end and not list(session.liveliness.get("@ros2_lv/0/*/*/*/NN/%/%/swarmsplat_live",
                                                                      timeout=1.0)):
            time.sleep(0.2)
        time.sleep(0.5)
        cam = seq.camera
        for i in range(len(seq)):
            f = seq[i]
            sec = int(f.timestamp)
            hdr = Header(stamp=Time(sec=sec, nanosec=int(round((f.timestamp - sec) * 1e9))), frame_id="camera")
            pubs["info"].publish(header=hdr, height=cam.height, width=cam.width, distortion_model="plumb_bob",
                                 d=np.zeros(5), k=np.array([cam.fx, 0, cam.cx, 0, cam.fy, cam.cy, 0, 0, 1.0]),
                                 r=np.eye(3).reshape(-1), p=np.zeros(12), binning_x=0, binning_y=0,
                                 roi=ROI(x_offset=0, y_offset=0, height=0, width=0, do_rectify=False))
            pubs["color"].publish(header=hdr, height=cam.height, width=cam.width, encoding="rgb8", is_bigendian=0,
                                  step=3 * cam.width, data=np.ascontiguousarray(f.color).reshape(-1))
            mm = np.rint(f.depth * 1000).astype("<u2")
            pubs["depth"].publish(header=hdr, height=cam.height, width=cam.width, encoding="16UC1", is_bigendian=0,
                                  step=2 * cam.width, data=mm.view(np.uint8).reshape(-1))
            time.sleep(1 / 15)
        seen["topics"] = dict(sdk.get_topic_names_and_types(router_port=port, timeout=2.0))
        seen["nodes"] = [str(r.ok.key_expr) for r in session.liveliness.get("@ros2_lv/0/**/NN/**", timeout=2.0)
                         if r.ok is not None]
        seen["published"] = [str(r.ok.key_expr) for r in session.liveliness.get(
            "@ros2_lv/0/*/*/*/MP/%/%/swarmsplat_live/**", timeout=2.0) if r.ok is not None]
    except Exception as e:  # noqa: BLE001 - reported by the test
        seen["error"] = repr(e)
    finally:
        done.set()


def test_a_ros2_client_sees_everything_a_live_agent_publishes(sequence, tmp_path, sdk):
    from swarmsplat.slam.cli import main
    from swarmsplat.slam.config import SlamConfig
    from swarmsplat.slam.io.ros2.messages import cloud_arrays
    from swarmsplat.slam.io.trajectory import read_tum

    port = _free_port()
    got: dict[str, list] = {r: [] for r in SUBSCRIBED}
    attachments: list = []
    subs = [sdk.ROS2Subscriber(t, m, (lambda msg, r=r: got[r].append(msg)), node_name="ros2_viewer",
                               router_port=port) for r, (t, m) in SUBSCRIBED.items()]
    session = sdk.ZenohSession.get_instance(router_port=port)
    raw = session.session.declare_subscriber(subs[0].keyexpr, lambda s: attachments.append(
        s.attachment.to_bytes() if s.attachment is not None else None))
    seen: dict = {}
    done = threading.Event()
    driver = threading.Thread(target=_camera_driver, args=(sdk, port, sequence, seen, done), daemon=True)
    cfg = SlamConfig().override({"mapping": {"iterations": 4, "first_iterations": 8},
                                 "map_refine": {"iterations_per_keyframe": 0}, "submaps": {"max_keyframes": 1}})
    (tmp_path / "cfg.yaml").write_text(cfg.to_yaml())
    driver.start()
    try:
        code = main(["agent", "zenoh/", "--out", str(tmp_path / "live"), "--listen", f"tcp/127.0.0.1:{port}",
                     "--frames", str(FRAMES), "--idle-timeout", "120", "--camera-timeout", "120", "--config",
                     str(tmp_path / "cfg.yaml"), "--quiet"])
        assert done.wait(120)
        time.sleep(1.0)  # the last messages' way to the subscribers
    finally:
        raw.undeclare()
        for s in subs:
            s.close()
    assert code == 0 and "error" not in seen, seen
    import json

    m = json.loads((tmp_path / "live" / "metrics.json").read_text())
    sent = m["ros2"]["sent"]
    assert m["frames_tracked"] == FRAMES and m["live"]["undecodable"] == 0, m["live"]
    # everything sent arrived: every pose and TF, each path, finished submap, map and loop marker message
    assert sent["pose"] == sent["tf"] == FRAMES and m["ros2"]["failed"] == 0
    assert all(sent.get(r, 0) >= 1 for r in SUBSCRIBED), sent
    assert {r: len(v) for r, v in got.items()} == {r: sent[r] for r in SUBSCRIBED}
    # the poses are the trajectory as tracked; the last path is the keyframes as written
    traj = np.loadtxt(tmp_path / "live" / "trajectory_no_lc.txt")
    pos = np.array([[g.pose.position.x, g.pose.position.y, g.pose.position.z] for g in got["pose"]])
    np.testing.assert_allclose(pos, traj[:, 1:4], atol=1e-6)
    tf = got["tf"][-1].transforms[0]
    assert tf.header.frame_id == "map" and tf.child_frame_id == "live/camera"
    _, T_kf = read_tum(tmp_path / "live" / "keyframes.txt")
    last = got["path"][-1]
    assert len(last.poses) == len(T_kf)
    np.testing.assert_allclose([[p.pose.position.x, p.pose.position.y, p.pose.position.z] for p in last.poses],
                               T_kf[:, :3, 3], atol=1e-6)
    xyz, rgb = cloud_arrays(got["map"][-1])
    assert 0 < len(xyz) <= 100_000 and np.all(np.isfinite(xyz)) and rgb.dtype == np.uint8
    assert {f.name for f in got["map"][-1].fields} == {"x", "y", "z", "rgb"}
    assert got["loops"][-1].markers is not None  # the final loops (none in ten frames)
    # rmw_zenoh's attachment on every pose: sequence 1, 2, ..., the source time, one 16-byte publisher GID
    assert len(attachments) == FRAMES and all(a is not None for a in attachments)
    from zenoh_ros2_sdk.attachment import Attachment

    parsed = [Attachment.from_bytes(a) for a in attachments]
    assert [p.sequence_id for p in parsed] == list(range(1, FRAMES + 1))
    assert len({p.gid for p in parsed}) == 1 and len(parsed[0].gid) == 16
    assert all(abs(p.timestamp_ns / 1e9 - time.time()) < 600 for p in parsed)
    # the ROS graph (what `ros2 topic list -t` / `ros2 node list` read from liveliness) while the agent ran
    topics = seen["topics"]
    for r, (t, mtype) in SUBSCRIBED.items():
        assert mtype in topics.get(t, []), (t, topics)
    assert "sensor_msgs/msg/Image" in topics["/camera/color/image_raw"]
    assert any(k.endswith("/NN/%/%/swarmsplat_live") for k in seen["nodes"]), seen["nodes"]
    # the agent's own publisher tokens: one per topic, with its type and hash
    published = {k.split("/")[9].replace("%", "/"): (k.split("/")[10], k.split("/")[11]) for k in seen["published"]}
    assert published == {t: (dds_name(m), type_hash(m)) for t, m in SUBSCRIBED.values()}, published


def test_the_agent_command_refuses_bad_ros_settings(tmp_path, capsys, monkeypatch):
    from swarmsplat.slam.cli import main

    out = str(tmp_path / "o")
    assert main(["agent", "zenoh/", "--out", out, "--domain-id", "300"]) == 2
    assert "ROS domain id 300: expected 0 .. 232" in capsys.readouterr().err
    monkeypatch.setenv("ROS_DOMAIN_ID", "x")
    assert main(["agent", "zenoh/", "--out", out]) == 2
    assert "ROS_DOMAIN_ID='x': expected an integer 0 .. 232" in capsys.readouterr().err
    monkeypatch.delenv("ROS_DOMAIN_ID")
    assert main(["agent", "zenoh/", "--out", out, "--namespace", "/robots/1st"]) == 2
    assert "namespace '/robots/1st': expected letters, digits and underscores" in capsys.readouterr().err
    assert main(["agent", "zenoh/", "--out", out, "--map-period", "-1"]) == 2
    assert "--map-period must be >= 0, got -1.0" in capsys.readouterr().err
    assert main(["agent", "zenoh/", "--server", "tcp/127.0.0.1:9", "--resume"]) == 2
    assert "--resume continues the team agent whose checkpoint is in --out: give --out" in capsys.readouterr().err


def test_paths_maps_and_loops_are_latched_for_a_late_subscriber():
    """Transient local, as rmw_zenoh offers it: the last path is kept by its publisher, announced with durability
    1 in its token, and a subscriber that comes later gets it by the cache query rmw_zenoh's subscribers make."""
    from swarmsplat.slam.io.live import zenoh_config
    from swarmsplat.slam.io.ros2 import AgentTopics, Ros2Node

    port = _free_port()
    _, conf = zenoh_config(listen=[f"tcp/127.0.0.1:{port}"])
    session = zenoh.open(conf)
    node = Ros2Node(session, "swarmsplat_a")
    topics = AgentTopics(node, "a")
    late = None
    try:
        T = np.stack([np.eye(4)] * 3)
        T[:, 0, 3] = [0.0, 1.0, 2.0]
        topics.path(np.array([1.0, 2.0, 3.0]), T)
        assert topics.flush(10)
        _, conf = zenoh_config(connect=[f"tcp/127.0.0.1:{port}"])
        late = zenoh.open(conf)
        t_end = time.time() + 20
        while not list(late.info.peers_zid()) and time.time() < t_end:
            time.sleep(0.05)
        (token,) = [str(r.ok.key_expr) for r in late.liveliness().get("@ros2_lv/0/*/*/*/MP/**/%swarmsplat%a%path/**",
                                                                      timeout=3.0) if r.ok is not None]
        assert token.endswith("/:1:,1:,:,:,,")  # reliable, transient local, keep last 1
        key = topics._pubs["path"].key
        replies = [r.ok for r in late.get(f"{key}/@adv/pub/**?_anyke;_max=1", timeout=3.0) if r.ok is not None]
        assert len(replies) == 1
        msg = store().deserialize_cdr(replies[0].payload.to_bytes(), "nav_msgs/msg/Path")
        assert [p.pose.position.x for p in msg.poses] == [0.0, 1.0, 2.0]
    finally:
        topics.close()
        node.close()
        session.close()
        if late is not None:
            late.close()
