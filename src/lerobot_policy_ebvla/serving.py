"""Serving `ebvla` with LeRobot's async inference server: the server class the `ebvla-policy-server` CLI runs.

LeRobot 0.6.1's `lerobot.async_inference.policy_server` refuses every policy type outside the list
`SUPPORTED_POLICIES` of `lerobot/async_inference/constants.py`, and it does not load plugins:
`allow_ebvla_in_policy_server` adds "ebvla" to that list at run time (LeRobot's files are not touched).
`EBVLAPolicyServer` is LeRobot's `PolicyServer` that logs the final energy and OOD decision of every chunk it
serves and keeps the latest ones in `served_chunks`.
"""

import pickle  # nosec: what LeRobot's server itself uses to read the client's policy instructions
from collections import deque
from concurrent import futures
from dataclasses import dataclass, field

import grpc
from lerobot.async_inference import constants
from lerobot.async_inference.configs import PolicyServerConfig
from lerobot.async_inference.helpers import TimedAction, TimedObservation
from lerobot.async_inference.policy_server import PolicyServer
from lerobot.transport import services_pb2_grpc  # type: ignore

from .runtime import EnergyOODError, OODDecision
from .runtime.readout import EnergyReadout

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
        ood_response: Overrides the checkpoint's `monitor.response` ("continue", "hold", "raise").
        hold_action: Overrides its `monitor.hold_action` ("zero_delta", "current_state").
        ood_threshold_k: Overrides its `monitor.threshold_k`, the multiplier k of T = mu_v + k sigma_v.
    """

    ood_response: str | None = field(default=None, metadata={"help": "continue, hold or raise"})
    hold_action: str | None = field(default=None, metadata={"help": "zero_delta or current_state"})
    ood_threshold_k: float | None = field(default=None, metadata={"help": "k of T = mu_v + k sigma_v"})

    def policy_overrides(self) -> dict:
        # This server's flag -> the `MonitorConfig` field it overrides.
        names = {"ood_response": "response", "hold_action": "hold_action", "ood_threshold_k": "threshold_k"}
        return {
            field: getattr(self, flag) for flag, field in names.items() if getattr(self, flag) is not None
        }


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
            path = pickle.loads(request.data).pretrained_name_or_path  # nosec
            self.policy.configure_ood_response(path, **overrides)
            self.logger.info(f"EB-VLA OOD response: {overrides}")
        return response

    # LeRobot private hook (`lerobot_private.POLICY_SERVER_CHUNK_METHOD`, checked by tests/test_lerobot_private.py).
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

    def _record(self, timestep: int, readout: EnergyReadout, decision: OODDecision | None) -> None:
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
