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
`ood_response` (taken from the checkpoint's config, or from `--ood_response`/`--hold_action`/`--ood_threshold_k`
here), and keeps the latest ones in `EBVLAPolicyServer.served_chunks`. With `ood_response="raise"`, LeRobot's
server catches the `EnergyOODError`, logs it and sends the client no actions for that observation, so the
robot runs out of actions and stops; with "hold" it receives the hold action.
"""

import dataclasses
import logging
import pickle  # nosec: what LeRobot's server itself uses to read the client's policy instructions
from collections import deque
from concurrent import futures
from dataclasses import dataclass, field

import draccus
import grpc
from lerobot.async_inference import constants
from lerobot.async_inference.configs import PolicyServerConfig
from lerobot.async_inference.helpers import TimedAction, TimedObservation
from lerobot.async_inference.policy_server import PolicyServer
from lerobot.transport import services_pb2_grpc  # type: ignore
from lerobot.utils.import_utils import register_third_party_plugins

from lerobot_policy_ebvla import EnergyReadout  # importing the plugin registers the `ebvla` type
from lerobot_policy_ebvla.ood_response import EnergyOODError, EnergyOODResponse, OODResponseDecision

POLICY_TYPE = "ebvla"
# How many served chunks `served_chunks` keeps, so that a server running for days keeps bounded memory.
MAX_SERVED_CHUNKS = 10_000


def allow_ebvla_in_policy_server() -> None:
    """Adds "ebvla" to LeRobot's `SUPPORTED_POLICIES`; the server module reads this very list object."""
    if POLICY_TYPE not in constants.SUPPORTED_POLICIES:
        constants.SUPPORTED_POLICIES.append(POLICY_TYPE)


@dataclass
class EBVLAPolicyServerConfig(PolicyServerConfig):
    """LeRobot's `PolicyServerConfig`, plus overrides of the served policy's OOD response.

    Args:
        ood_response: Overrides `EBVLAConfig.ood_response` of the checkpoint ("continue", "hold", "raise").
        hold_action: Overrides `EBVLAConfig.hold_action` ("zero_delta", "current_state").
        ood_threshold_k: Overrides `EBVLAConfig.ood_threshold_k`, the multiplier k of T = mu_v + k sigma_v.
    """

    ood_response: str | None = field(default=None, metadata={"help": "continue, hold or raise"})
    hold_action: str | None = field(default=None, metadata={"help": "zero_delta or current_state"})
    ood_threshold_k: float | None = field(default=None, metadata={"help": "k of T = mu_v + k sigma_v"})

    def policy_overrides(self) -> dict:
        names = ("ood_response", "hold_action", "ood_threshold_k")
        return {name: getattr(self, name) for name in names if getattr(self, name) is not None}


@dataclass(frozen=True)
class ServedChunk:
    """Energies of one chunk the server refined, for the observation of client timestep `timestep`."""

    timestep: int
    initial_energy: float
    final_energy: float
    flagged: bool | None
    held: bool | None


class EBVLAPolicyServer(PolicyServer):
    """LeRobot's `PolicyServer`, recording the energy and OOD decision of each chunk it serves."""

    def __init__(self, config: PolicyServerConfig):
        allow_ebvla_in_policy_server()
        super().__init__(config)
        self.served_chunks: deque[ServedChunk] = deque(maxlen=MAX_SERVED_CHUNKS)

    def SendPolicyInstructions(self, request, context):  # noqa: N802 (gRPC method name)
        response = super().SendPolicyInstructions(request, context)
        overrides = getattr(self.config, "policy_overrides", dict)()
        if self.policy is not None and self.policy_type == POLICY_TYPE and overrides:
            # Re-validates the config (a hold needs an explicit hold_action) and reloads the calibration.
            config = dataclasses.replace(self.policy.config, **overrides)
            config.validate_features()
            self.policy.config = config
            path = pickle.loads(request.data).pretrained_name_or_path  # nosec
            self.policy.ood_response = EnergyOODResponse.from_pretrained(config, path)
            self.logger.info(f"EB-VLA OOD response: {overrides}")
        return response

    def _predict_action_chunk(self, observation_t: TimedObservation) -> list[TimedAction]:
        if self.policy_type != POLICY_TYPE:
            return super()._predict_action_chunk(observation_t)
        try:
            chunk = super()._predict_action_chunk(observation_t)
        except EnergyOODError as error:  # LeRobot's GetActions logs it and sends no actions
            self._record(observation_t.get_timestep(), self.policy.last_energy, error.decision)
            raise
        self._record(observation_t.get_timestep(), self.policy.last_energy, self.policy.last_ood_decision)
        return chunk

    def _record(self, timestep: int, readout: EnergyReadout, decision: OODResponseDecision | None) -> None:
        # The client sends one observation at a time: batch element 0 is its chunk.
        served = ServedChunk(
            timestep=timestep,
            initial_energy=float(readout.initial_energy.reshape(-1)[0]),
            final_energy=float(readout.final_energy.reshape(-1)[0]),
            flagged=None if decision is None else bool(decision.flagged[0]),
            held=None if decision is None else bool(decision.held[0]),
        )
        self.served_chunks.append(served)
        self.logger.info(
            f"Chunk for observation #{timestep} | final energy {served.final_energy:.4f}"
            + ("" if decision is None else f" | OOD: {served.flagged} | held: {served.held}")
        )


def start_server(cfg: PolicyServerConfig, max_workers: int = 4) -> tuple[grpc.Server, EBVLAPolicyServer]:
    """Starts LeRobot's gRPC async inference service on `cfg.host:cfg.port`, as LeRobot's `serve` does."""
    policy_server = EBVLAPolicyServer(cfg)
    server = grpc.server(futures.ThreadPoolExecutor(max_workers=max_workers))
    services_pb2_grpc.add_AsyncInferenceServicer_to_server(policy_server, server)
    server.add_insecure_port(f"{cfg.host}:{cfg.port}")
    server.start()
    policy_server.logger.info(f"EB-VLA policy server started on {cfg.host}:{cfg.port}")
    return server, policy_server


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
