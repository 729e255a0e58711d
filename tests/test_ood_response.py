"""The policy's response to a chunk whose final energy exceeds the calibrated OOD threshold.

The MetaWorld tests run lerobot-eval's own `rollout` on `--env.type=metaworld_ebvla` with a tiny untrained
policy loaded from a checkpoint folder, as lerobot-eval loads it. The trigger is made deterministic by the
calibration: its threshold lies below (or above) every energy the policy can produce.
"""

import dataclasses
import math

import pytest
import torch
from lerobot.configs.types import FeatureType, PolicyFeature
from lerobot.utils.constants import ACTION, OBS_STATE

from lerobot_policy_ebvla import EBVLAPolicy, make_ebvla_pre_post_processors
from lerobot_policy_ebvla.configuration_ebvla import MonitorConfig
from lerobot_policy_ebvla.runtime import (
    EnergyOODError,
    EnergyOODResponse,
    EnergyReadout,
    OODCalibration,
    PhaseStatistics,
)
from lerobot_policy_ebvla.runtime.scores import ContextPhaseEnergy
from tests.conftest import tiny_batch, tiny_config

BELOW_ALL_ENERGIES = OODCalibration(mu_v=-1e6, sigma_v=0.0)
ABOVE_ALL_ENERGIES = OODCalibration(mu_v=1e6, sigma_v=0.0)
# Non-zero means, so that a zero raw action is not a zero normalized action.
ACTION_MEAN, ACTION_STD = [0.3, -0.2, 0.1, 0.5], [0.5, 2.0, 1.5, 0.25]
STATE_MEAN, STATE_STD = [0.0, 0.6, 0.2, 0.4], [0.3, 0.2, 0.1, 0.5]


def save_checkpoint(path, config, calibration: OODCalibration | None, action_dim: int, state_dim: int):
    """Saves a tiny random policy, its pre/post-processors with fixed statistics, and a calibration."""
    torch.manual_seed(0)
    stats = {
        ACTION: {
            "mean": torch.tensor(ACTION_MEAN[:action_dim]),
            "std": torch.tensor(ACTION_STD[:action_dim]),
        },
        OBS_STATE: {"mean": torch.tensor(STATE_MEAN[:state_dim]), "std": torch.tensor(STATE_STD[:state_dim])},
    }
    policy = EBVLAPolicy(config)
    preprocessor, postprocessor = make_ebvla_pre_post_processors(config, dataset_stats=stats)
    for saved in (policy, preprocessor, postprocessor):
        saved.save_pretrained(path)
    if calibration is not None:
        calibration.save(path)
    return path


def load(path, **monitor):
    """Loads policy and processors as lerobot-eval does, with `--policy.monitor.<field>` overrides."""
    from lerobot.configs import PreTrainedConfig
    from lerobot.policies import make_pre_post_processors

    config = PreTrainedConfig.from_pretrained(path)
    config = dataclasses.replace(config, monitor=dataclasses.replace(config.monitor, **monitor))
    policy = EBVLAPolicy.from_pretrained(path, config=config)
    preprocessor, postprocessor = make_pre_post_processors(policy.config, pretrained_path=str(path))
    return policy, preprocessor, postprocessor


# MetaWorld rollouts.

EPISODE_STEPS = 8
CHUNK = 4


def metaworld_config():
    return tiny_config(
        input_features={
            "observation.image": PolicyFeature(FeatureType.VISUAL, (3, 480, 480)),
            "observation.state": PolicyFeature(FeatureType.STATE, (4,)),
        },
        output_features={"action": PolicyFeature(FeatureType.ACTION, (4,))},
        resnet={"resize_shape": (64, 64)},
        chunk_size=CHUNK,
        n_action_steps=CHUNK,
        inference_mcmc_steps=3,
    )


@pytest.fixture(scope="module")
def metaworld_env():
    pytest.importorskip("metaworld")
    from lerobot.envs.factory import make_env, make_env_pre_post_processors

    from lerobot_policy_ebvla.envs import MetaworldEBVLAEnv

    env_cfg = MetaworldEBVLAEnv(task="reach-v3", fast_render=True, max_episode_steps=EPISODE_STEPS)
    env = next(iter(next(iter(make_env(env_cfg, n_envs=1).values())).values()))
    env_processors = make_env_pre_post_processors(env_cfg, metaworld_config())
    yield env, env_processors
    env.close()


@pytest.fixture(scope="module")
def checkpoints(tmp_path_factory):
    """One checkpoint whose threshold is below every energy, one above every energy, one uncalibrated."""
    root = tmp_path_factory.mktemp("checkpoints")
    return {
        name: save_checkpoint(root / name, metaworld_config(), calibration, action_dim=4, state_dim=4)
        for name, calibration in (
            ("below", BELOW_ALL_ENERGIES),
            ("above", ABOVE_ALL_ENERGIES),
            ("uncalibrated", None),
        )
    }


def run_rollout(metaworld_env, path, **overrides):
    """lerobot-eval's rollout of one seeded episode; returns its actions and the decision of each chunk."""
    from lerobot.scripts.lerobot_eval import rollout

    env, (env_preprocessor, env_postprocessor) = metaworld_env
    policy, preprocessor, postprocessor = load(path, **overrides)
    decisions = []
    predict_action_chunk = policy.predict_action_chunk

    def predict_and_keep_decision(*args, **kwargs):
        try:
            return predict_action_chunk(*args, **kwargs)
        finally:
            decisions.append(policy.last_ood_decision)

    policy.predict_action_chunk = predict_and_keep_decision
    torch.manual_seed(0)
    data = rollout(env, policy, env_preprocessor, env_postprocessor, preprocessor, postprocessor, seeds=[0])
    return data["action"][0], decisions


def test_hold_sends_zero_deltas_to_metaworld_and_counts_each_held_chunk(metaworld_env, checkpoints):
    actions, decisions = run_rollout(
        metaworld_env, checkpoints["below"], response="hold", hold_action="zero_delta"
    )
    assert actions.shape == (EPISODE_STEPS, 4)
    torch.testing.assert_close(actions, torch.zeros_like(actions), atol=1e-5, rtol=0)
    assert len(decisions) == math.ceil(EPISODE_STEPS / CHUNK)
    assert all(d.held.tolist() == [True] and d.flagged.tolist() == [True] for d in decisions)
    assert {d.threshold for d in decisions} == {BELOW_ALL_ENERGIES.threshold}


def test_hold_leaves_chunks_below_the_threshold_untouched(metaworld_env, checkpoints):
    held, decisions = run_rollout(
        metaworld_env, checkpoints["above"], response="hold", hold_action="zero_delta"
    )
    plain, _ = run_rollout(metaworld_env, checkpoints["uncalibrated"])
    assert not any(d.flagged.any() or d.held.any() for d in decisions)
    torch.testing.assert_close(held, plain)
    assert held.abs().max() > 1e-3  # the untrained policy does move: holding would have shown


def test_continue_flags_chunks_but_executes_them_unchanged(metaworld_env, checkpoints):
    flagged, decisions = run_rollout(metaworld_env, checkpoints["below"], response="continue")
    plain, plain_decisions = run_rollout(metaworld_env, checkpoints["uncalibrated"])
    torch.testing.assert_close(flagged, plain)
    assert all(d.flagged.all() and not d.held.any() for d in decisions)
    assert all(d is None for d in plain_decisions)  # no calibration: nothing is checked


def test_raise_stops_the_metaworld_rollout_with_the_energy_and_threshold(metaworld_env, checkpoints):
    with pytest.raises(EnergyOODError, match="above the OOD threshold") as error:
        run_rollout(metaworld_env, checkpoints["below"], response="raise")
    assert error.value.threshold == BELOW_ALL_ENERGIES.threshold
    assert error.value.energy > error.value.threshold
    assert error.value.decision.flagged.all() and not error.value.decision.held.any()


# The hold action, the threshold and the configuration.


def test_current_state_hold_sends_the_observed_state_after_unnormalization(tmp_path):
    config = tiny_config(
        input_features={
            "observation.images.top": PolicyFeature(FeatureType.VISUAL, (3, 64, 64)),
            "observation.state": PolicyFeature(FeatureType.STATE, (3,)),
        },
        output_features={"action": PolicyFeature(FeatureType.ACTION, (3,))},
    )
    save_checkpoint(tmp_path, config, BELOW_ALL_ENERGIES, action_dim=3, state_dim=3)
    policy, preprocessor, postprocessor = load(tmp_path, response="hold", hold_action="current_state")
    raw_state = torch.tensor([[0.7, -1.2, 3.0], [0.0, 0.5, -0.4]])
    observation = {k: v for k, v in tiny_batch(config, with_action=False).items() if k != OBS_STATE}
    batch = preprocessor({**observation, OBS_STATE: raw_state})
    chunk = policy.predict_action_chunk(batch)
    for t in range(chunk.shape[1]):
        torch.testing.assert_close(postprocessor(chunk[:, t]), raw_state, atol=1e-5, rtol=0)
    assert policy.last_ood_decision.held.tolist() == [True, True]


def test_current_state_hold_rejects_state_and_action_of_different_sizes():
    with pytest.raises(ValueError, match="hold_action='current_state'.*same size"):
        EBVLAPolicy(
            tiny_config(monitor=MonitorConfig(response="hold", hold_action="current_state"))
        )  # state 4, action 3


def test_current_state_hold_rejects_differently_named_state_and_action():
    config = tiny_config(
        output_features={"action": PolicyFeature(FeatureType.ACTION, (4,))},
        monitor=MonitorConfig(response="hold", hold_action="current_state"),
    )
    config.set_dataset_feature_metadata(
        {OBS_STATE: {"names": ["x", "y", "z", "gripper"]}, ACTION: {"names": ["dx", "dy", "dz", "gripper"]}}
    )
    with pytest.raises(ValueError, match="state_feature_names"):
        EBVLAPolicy(config)


def test_hold_without_an_explicit_hold_action_is_rejected():
    with pytest.raises(ValueError, match="`monitor.hold_action`.*zero_delta.*current_state"):
        tiny_config(monitor=MonitorConfig(response="hold"))


def test_unknown_responses_are_rejected():
    with pytest.raises(ValueError, match="`monitor.response`"):
        tiny_config(monitor=MonitorConfig(response="stop"))
    with pytest.raises(ValueError, match="`monitor.hold_action`"):
        tiny_config(monitor=MonitorConfig(response="hold", hold_action="home"))
    with pytest.raises(ValueError, match="`monitor.threshold_k`"):
        tiny_config(monitor=MonitorConfig(threshold_k=-1.0))


def test_threshold_multiplier_of_the_config_replaces_the_calibrations(tmp_path):
    save_checkpoint(tmp_path, tiny_config(), OODCalibration(mu_v=2.0, sigma_v=0.5, k=1.0), 3, 4)
    assert load(tmp_path)[0].ood_response.threshold == 2.5
    assert load(tmp_path, threshold_k=3.0)[0].ood_response.threshold == 3.5


def test_raise_and_hold_need_a_calibration(tmp_path):
    save_checkpoint(tmp_path, tiny_config(), None, 3, 4)
    with pytest.raises(FileNotFoundError, match="ood_calibration.json"):
        load(tmp_path, response="raise")
    torch.manual_seed(0)
    policy = EBVLAPolicy(
        tiny_config(monitor=MonitorConfig(response="raise"))
    )  # built in memory: no calibration
    with pytest.raises(ValueError, match="needs the threshold of an OOD calibration"):
        policy.predict_action_chunk(tiny_batch(policy.config, with_action=False))


def test_non_finite_energy_is_held_whatever_the_threshold():
    config = tiny_config(monitor=MonitorConfig(response="hold", hold_action="zero_delta"))
    response = EnergyOODResponse(config, ABOVE_ALL_ENERGIES, hold_action=_zeros())
    actions = torch.ones(2, 3, 2)
    held, decision = response(actions, EnergyReadout(None, torch.tensor([1.0, math.inf])), {})
    assert decision.held.tolist() == [False, True]
    assert torch.equal(held[0], actions[0]) and torch.equal(held[1], torch.zeros(3, 2))


def _zeros():
    """A hold action that is zero in normalized space (identity normalization)."""
    from lerobot.configs import NormalizationMode
    from lerobot.processor import NormalizerProcessorStep

    from lerobot_policy_ebvla.runtime import HoldAction

    features = {ACTION: PolicyFeature(FeatureType.ACTION, (2,))}
    normalizer = NormalizerProcessorStep(features, {FeatureType.ACTION: NormalizationMode.IDENTITY}, stats={})
    return HoldAction("zero_delta", normalizer)


@pytest.mark.parametrize(("checkpoint", "held"), [("below", True), ("above", False)])
def test_energy_records_count_the_held_chunks(metaworld_env, checkpoints, checkpoint, held):
    from lerobot.scripts.lerobot_eval import rollout

    from lerobot_policy_ebvla.monitoring import EnergyRecorder

    env, (env_preprocessor, env_postprocessor) = metaworld_env
    policy, preprocessor, postprocessor = load(
        checkpoints[checkpoint], response="hold", hold_action="zero_delta"
    )
    torch.manual_seed(0)
    with EnergyRecorder(policy) as recorder:
        watched = recorder.watch(env, task_group="reach-v3", task_id=0)
        rollout(watched, policy, env_preprocessor, env_postprocessor, preprocessor, postprocessor, seeds=[0])
    records = recorder.records_from_successes({("reach-v3", 0): [False]}, n_episodes=1)
    assert len(records) == math.ceil(EPISODE_STEPS / CHUNK)
    assert all(record.held is held for record in records)


def test_a_phase_calibration_compares_each_chunk_with_the_vanilla_energy_at_its_index():
    # Vanilla E_c falls from 0 at the first chunk to -10 at the second: -5 is normal early, not late.
    phase = ContextPhaseEnergy(PhaseStatistics((0.0, -10.0), (1.0, 1.0)))
    calibration = OODCalibration(mu_v=0.0, sigma_v=1.0, k=1.0, score=phase)
    response = EnergyOODResponse(tiny_config(monitor=MonitorConfig(response="raise")), calibration)
    actions, energy = torch.zeros(1, 3, 2), torch.tensor([0.0])
    chunk = EnergyReadout(None, energy, context_energy=torch.tensor([-5.0]), chunk_index=0)
    _, decision = response(actions, chunk, {})
    assert not decision.flagged.any()
    with pytest.raises(EnergyOODError, match="context_phase_energy 5"):
        response(actions, dataclasses.replace(chunk, chunk_index=1), {})


def test_the_policy_counts_its_chunks_per_episode():
    torch.manual_seed(0)
    policy = EBVLAPolicy(tiny_config())
    batch = tiny_batch(policy.config, with_action=False)
    policy.predict_action_chunk(batch)
    first = policy.last_energy
    policy.predict_action_chunk(batch)
    assert (first.chunk_index, policy.last_energy.chunk_index, policy.chunk_index) == (0, 1, 2)
    policy.reset()
    assert policy.chunk_index == 0
