"""``kmvipe ros2``: the options become the bridge's settings; ``keys`` prints the key expressions; ``bridge`` runs as
its own process (the way ``kmvipe ros2 bridge`` runs it), publishes a pose to a ROS router as a transform and stops
cleanly on SIGTERM."""
from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys

import numpy as np

from services.common import keys
from services.common.bus import Bus
from services.common.config import BusSettings
from services.common.schema import Poses
from services.ros2 import cli
from services.ros2.config import Ros2Settings, RosZenohSettings
from services.ros2.core import messages
from tests.conftest import REPO
from tests.query_api_fixtures import free_port, wait_for
from tests.test_ros2_bridge import Recorder, await_subscriber, ros_router


def parse(*argv: str) -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog="kmvipe")
    cli.register(parser.add_subparsers(dest="command", required=True))
    return parser.parse_args(["ros2", *argv])


def test_bridge_options_become_its_settings(monkeypatch):
    args = parse("bridge", "--stream", "cam7", "--form", "bridge", "--domain-id", "2", "--distro", "humble",
                 "--axes", "optical", "--map-period", "2.5", "--connect", "tcp/10.0.0.1:7447",
                 "--ros-connect", "tcp/10.0.0.2:7447")
    env = cli.bridge_environment(args)
    assert env["KMVIPE_BUS_MODE"] == "client" and json.loads(env["KMVIPE_BUS_CONNECT"]) == ["tcp/10.0.0.1:7447"]
    for name, value in env.items():
        monkeypatch.setenv(name, value)
    cfg, ros = Ros2Settings(_env_file=None), RosZenohSettings(_env_file=None)
    assert (cfg.stream, cfg.form, cfg.domain_id, cfg.distro, cfg.axes, cfg.map_period_s) == (
        "cam7", "bridge", 2, "humble", "optical", 2.5)
    assert ros.connect == ["tcp/10.0.0.2:7447"] and ros.mode == "client"
    assert cli.bridge_environment(parse("bridge")) == {}  # nothing given: the environment's settings stand


def test_keys_prints_each_topic_with_its_key(capsys):
    args = parse("keys", "--domain-id", "5")
    assert args.func(args) == 0
    lines = capsys.readouterr().out.splitlines()
    assert len(lines) == 4
    tf_key = f"5/tf/tf2_msgs::msg::dds_::TFMessage_/{messages.type_hash(messages.TF)}"
    assert lines[0].split() == ["/tf", messages.TF, tf_key]
    assert cli.main(["keys", "--form", "bridge"]) == 0
    assert [line.split()[-1] for line in capsys.readouterr().out.splitlines()] == [
        "tf", "kmvipe/path", "kmvipe/map", "kmvipe/camera_info"]


def test_the_bridge_command_runs_until_sigterm(tmp_path):
    router, ros_endpoint = ros_router()
    recorder = Recorder(router, "**")
    km_endpoint = f"tcp/127.0.0.1:{free_port()}"
    km = Bus(BusSettings(mode="peer", listen=[km_endpoint]), "ba")
    env = {k: v for k, v in os.environ.items() if not k.startswith("KMVIPE_")}
    proc = subprocess.Popen(
        [sys.executable, "-m", "services.ros2.cli", "bridge", "--stream", "cam3", "--connect", km_endpoint,
         "--ros-connect", ros_endpoint, "--map-period", "0"],
        cwd=tmp_path, env={**env, "PYTHONPATH": str(REPO)}, stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
    try:
        await_subscriber(km.session, keys.topic("cam3", keys.POSE))
        pose = np.eye(4)
        pose[:3, 3] = [1.0, 2.0, 3.0]
        km.publish(keys.topic("cam3", keys.POSE), Poses("cam3", 0, 42, frame_seqs=np.array([0]),
                                                        stamps_ns=np.array([42]), poses=pose[None]))
        key = f"0/tf/tf2_msgs::msg::dds_::TFMessage_/{messages.type_hash(messages.TF)}"
        tf = wait_for(lambda: recorder.messages(key, messages.TF), what="a transform")[0].transforms[0]
        assert messages.time_ns(tf.header.stamp) == 42
        t = tf.transform.translation
        np.testing.assert_allclose([t.x, t.y, t.z], messages.map_from_world("flu")[:3, :3] @ [1.0, 2.0, 3.0])
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(20) == 0, proc.stdout.read().decode()
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        km.close()
        router.close()
