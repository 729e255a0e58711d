"""`ebvla-policy-server`: LeRobot's async inference policy server, able to serve `ebvla` checkpoints.

LeRobot 0.6.1's `lerobot.async_inference.policy_server` refuses every policy type outside the list
`SUPPORTED_POLICIES` of `lerobot/async_inference/constants.py`, and it does not load plugins. This entry point
imports the plugin (which registers `ebvla`), adds "ebvla" to that list at run time (LeRobot's files are not
touched), and runs LeRobot's `PolicyServer` with the same flags:

    ebvla-policy-server --host=127.0.0.1 --port=8080 --fps=30 --inference_latency=0.033 --obs_queue_timeout=1

The robot side is LeRobot's own client, unchanged:

    python -m lerobot.async_inference.robot_client --policy_type=ebvla \\
        --pretrained_name_or_path=outputs/train/ebvla/checkpoints/last/pretrained_model --robot.type=... ...

The server logs the final energy of every chunk it refines, with the OOD decision of the policy's
response (the checkpoint's `monitor` config, or from `--ood_response`/`--hold_action`/`--ood_threshold_k`
here), and keeps the latest ones in `EBVLAPolicyServer.served_chunks`. With the response "raise", LeRobot's
server catches the `EnergyOODError`, logs it and sends the client no actions for that observation, so the
robot runs out of actions and stops; with "hold" it receives the hold action.
"""

import dataclasses
import logging

import draccus
from lerobot.utils.import_utils import register_third_party_plugins

from lerobot_policy_ebvla.serving import EBVLAPolicyServerConfig, start_server


@draccus.wrap()
def serve(cfg: EBVLAPolicyServerConfig) -> None:
    """Runs the policy server until it is interrupted."""
    logging.info(dataclasses.asdict(cfg))
    server, policy_server = start_server(cfg)
    server.wait_for_termination()
    policy_server.logger.info("Server terminated")


def main() -> None:
    register_third_party_plugins()  # as LeRobot's scripts do, for plugins other than this one
    serve()


if __name__ == "__main__":
    main()
