"""`ebvla-policy-server`: LeRobot's async inference server serving an ebvla checkpoint to LeRobot's client.

The round trip runs on 127.0.0.1 with LeRobot's `RobotClient` driving the simulated `SimArm`, and stops
itself once the robot has executed a few actions (or after a bounded wait).
"""

import socket
import threading
import time

import numpy as np
import pytest

pytest.importorskip("grpc", reason="the async policy server needs gRPC: install `lerobot[async]`")

from tests.test_rollout import JOINT_POSITIONS, SimArm, SimArmConfig, save_sim_arm_checkpoint  # noqa: E402

MIN_ACTIONS = 6
TIMEOUT_S = 60


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture
def in_tmp_path(tmp_path, monkeypatch):
    # LeRobot's async inference loggers write `logs/*.log` into the working directory.
    monkeypatch.chdir(tmp_path)
    return tmp_path


def round_trip(tmp_path, monkeypatch, **server_flags):
    """Serves a checkpoint to LeRobot's RobotClient until the robot executed MIN_ACTIONS actions."""
    from lerobot.async_inference import robot_client
    from lerobot.async_inference.configs import RobotClientConfig

    from lerobot_policy_ebvla.serving import EBVLAPolicyServerConfig, start_server

    robots = []
    monkeypatch.setattr(
        robot_client, "make_robot_from_config", lambda cfg: robots.append(SimArm(cfg)) or robots[-1]
    )
    checkpoint = save_sim_arm_checkpoint(tmp_path / "checkpoint")
    port = free_port()
    server, policy_server = start_server(
        EBVLAPolicyServerConfig(host="127.0.0.1", port=port, fps=30, inference_latency=0.0, **server_flags),
        max_workers=4,
    )
    client = robot_client.RobotClient(
        RobotClientConfig(
            policy_type="ebvla",
            pretrained_name_or_path=str(checkpoint),
            robot=SimArmConfig(calibration_dir=tmp_path / "calibration"),
            actions_per_chunk=4,
            server_address=f"127.0.0.1:{port}",
            fps=30,
        )
    )
    (robot,) = robots
    threads = []
    try:
        assert client.start(), "the client could not hand the policy instructions to the server"
        threads = [
            threading.Thread(target=client.receive_actions, daemon=True),
            threading.Thread(target=client.control_loop, kwargs={"task": "reach the goal"}, daemon=True),
        ]
        for thread in threads:
            thread.start()
        deadline = time.monotonic() + TIMEOUT_S
        while len(robot.sent_actions) < MIN_ACTIONS and time.monotonic() < deadline:
            time.sleep(0.1)
    finally:
        client.shutdown_event.set()
        for thread in threads:
            thread.join(timeout=10)
        client.stop()
        policy_server.stop()
        server.stop(grace=None).wait()
    return robot, policy_server


def test_lerobot_client_runs_an_ebvla_checkpoint_and_the_server_keeps_each_chunks_energy(
    in_tmp_path, monkeypatch
):
    robot, policy_server = round_trip(in_tmp_path, monkeypatch)
    assert len(robot.sent_actions) >= MIN_ACTIONS
    assert all(set(action) == set(robot.joints) for action in robot.sent_actions)
    served = list(policy_server.served_chunks)
    assert served, "the server refined no chunk"
    assert all(np.isfinite(c.final_energy) and np.isfinite(c.initial_energy) for c in served)
    assert served[-1].final_energy == float(policy_server.policy.last_energy.final_energy[0])
    # Calibrated below every energy, with the checkpoint's default "continue": flagged, executed, not held.
    assert all(c.flagged and not c.held for c in served)


def test_server_holds_the_robots_joint_positions_when_told_to(in_tmp_path, monkeypatch):
    robot, policy_server = round_trip(
        in_tmp_path, monkeypatch, ood_response="hold", hold_action="current_state"
    )
    assert policy_server.served_chunks and all(c.held for c in policy_server.served_chunks)
    for action in robot.sent_actions:
        np.testing.assert_allclose([action[j] for j in robot.joints], JOINT_POSITIONS, atol=1e-3)


def test_ebvla_is_added_once_to_the_list_lerobots_server_checks(in_tmp_path):
    from lerobot.async_inference import policy_server

    from lerobot_policy_ebvla.serving import allow_ebvla_in_policy_server

    allow_ebvla_in_policy_server()
    allow_ebvla_in_policy_server()
    assert policy_server.SUPPORTED_POLICIES.count("ebvla") == 1
