"""The phase energy E_tau(C, t) = -log p(t | C): the module, its fit, the policy's readout of it, the score that reads
it beside the joint energy's two terms, its records, and `ebvla-fit-phase-energy` on a saved checkpoint."""

import json

import numpy as np
import pytest
import torch

from lerobot_policy_ebvla import EBVLAPolicy
from lerobot_policy_ebvla.monitoring.records import EnergyRecord, record_from_json, record_to_json
from lerobot_policy_ebvla.phase_energy import PhaseEnergy, fit_phase_energy
from lerobot_policy_ebvla.runtime.readout import EnergyReadout
from lerobot_policy_ebvla.runtime.scores import ChunkInputs, JointPhaseTimeEnergy, VanillaRollouts

from .conftest import tiny_batch, tiny_config, write_tiny_dataset

OWN_ENCODER = {"weight": 0.1, "target": "observation"}


def phase_frames(n_episodes=200, n_chunks=10, dim=4, seed=0):
    """Contexts whose first dimension grows with the chunk index (plus noise), as a task's progress shows in them."""
    rng = np.random.default_rng(seed)
    chunk = np.tile(np.arange(n_chunks), n_episodes)
    episode = np.repeat(np.arange(n_episodes), n_chunks)
    features = rng.normal(scale=0.3, size=(chunk.size, dim)).astype(np.float32)
    features[:, 0] += chunk
    return features, chunk, episode


def test_e_tau_is_an_energy_over_the_chunk_bins_normalized_per_context():
    torch.manual_seed(0)
    phase = PhaseEnergy(dim=4, bins=5, hidden=8)
    features = torch.randn(3, 4)
    energies = torch.stack([phase(features, t) for t in range(5)], dim=1)
    assert torch.allclose(torch.exp(-energies).sum(dim=1), torch.ones(3), atol=1e-5)
    assert torch.equal(phase(features, 9), phase(features, 4))  # later chunks share the last bin
    assert torch.allclose(
        phase(features, torch.tensor([0, 1, 2])), energies[torch.arange(3), torch.arange(3)]
    )
    assert not phase.fitted


def test_the_fit_learns_when_a_context_belongs_and_is_deterministic():
    features, chunk, episode = phase_frames()
    phase = PhaseEnergy(dim=4, bins=10, hidden=32)
    fit = fit_phase_energy(phase, features, chunk, episode)
    assert phase.fitted and int(phase.fitted_frames) == fit.frames == features.shape[0]
    assert fit.episodes == 200 and len(fit.validation_nll) == 40 and 1 <= fit.epochs <= 40
    inputs = torch.as_tensor(features)
    with torch.no_grad():
        on_time = phase(inputs, torch.as_tensor(chunk))
        late = phase(inputs, torch.as_tensor(np.minimum(chunk + 4, 9)))
    # A context is cheap at its own chunk and dear four chunks later (a stalled rollout).
    assert (late[chunk < 6] > on_time[chunk < 6] + 2.0).float().mean() > 0.95

    again = PhaseEnergy(dim=4, bins=10, hidden=32)
    assert fit_phase_energy(again, features, chunk, episode) == fit
    assert all(
        torch.equal(a, b)
        for a, b in zip(phase.state_dict().values(), again.state_dict().values(), strict=True)
    )


@pytest.mark.parametrize(
    "change, message",
    [
        (lambda f, c, e: (f[:, :3], c, e), r"`features` must be \(N, 4\)"),
        (lambda f, c, e: (f, c[:-1], e), r"`chunk_index` must be \(2000,\)"),
        (lambda f, c, e: (f, c, e[:-1]), r"`episode` must be \(2000,\)"),
        (lambda f, c, e: (f, c - 1, e), "`chunk_index` must be >= 0"),
        (lambda f, c, e: (f, c, np.zeros_like(e)), "at least 2 episodes"),
        (lambda f, c, e: (np.where(c[:, None] == 3, np.nan, f), c, e), "non-finite"),
    ],
)
def test_the_fit_names_what_is_wrong_with_its_inputs(change, message):
    with pytest.raises(ValueError, match=message):
        fit_phase_energy(PhaseEnergy(4, 10, 8), *change(*phase_frames()), max_epochs=1)


def fitted_policy(bins=4, **overrides) -> EBVLAPolicy:
    torch.manual_seed(0)
    policy = EBVLAPolicy(tiny_config(phase_energy={"bins": bins, "hidden": 16}, **overrides)).eval()
    rng = np.random.default_rng(0)
    dim = policy.model.backbone.context_dim
    features = rng.normal(size=(40, dim)).astype(np.float32)
    fit_phase_energy(
        policy.model.phase_energy, features, np.tile(np.arange(4), 10), np.repeat(np.arange(10), 4), 3
    )
    return policy


def test_the_policy_reports_e_tau_of_each_chunk_at_its_index_once_fitted():
    torch.manual_seed(0)
    unfitted = EBVLAPolicy(tiny_config(phase_energy={"bins": 4, "hidden": 16})).eval()
    batch = tiny_batch(unfitted.config, with_action=False)
    unfitted.predict_action_chunk(batch)
    assert unfitted.last_energy.phase_energy is None  # never fitted: no energy to give

    policy = fitted_policy()
    features = policy.context_features(batch)
    for t in range(2):
        _, readout = policy.predict_action_chunk(batch, return_energy=True)
        assert readout.chunk_index == t and readout.context_features is None
        assert torch.allclose(readout.phase_energy, policy.model.phase_energy(features, t), atol=1e-5)


def test_a_phase_energy_leaves_the_global_random_state_as_the_source_leaves_it():
    """A checkpoint with a phase energy draws the same a^(0) and noise as its source in a seeded rollout."""
    draws = []
    for phase_energy in ({"bins": 0}, {"bins": 4}):
        torch.manual_seed(0)
        EBVLAPolicy(tiny_config(phase_energy=phase_energy))
        draws.append(torch.rand(3))
    assert torch.equal(*draws)


def test_a_saved_checkpoint_keeps_its_fitted_phase_energy(tmp_path):
    policy = fitted_policy()
    policy.save_pretrained(tmp_path / "policy")
    loaded = EBVLAPolicy.from_pretrained(tmp_path / "policy").eval()
    assert loaded.config.phase_energy.bins == 4 and loaded.model.phase_energy.fitted
    features = torch.randn(3, policy.model.backbone.context_dim)
    assert torch.allclose(loaded.model.phase_energy(features, 2), policy.model.phase_energy(features, 2))


def test_the_config_checks_its_phase_energy():
    with pytest.raises(ValueError, match="`phase_energy.bins` must be 0 \\(off\\) or >= 2"):
        tiny_config(phase_energy={"bins": 1})
    with pytest.raises(ValueError, match="`phase_energy.hidden` must be >= 1"):
        tiny_config(phase_energy={"bins": 4, "hidden": 0})
    with pytest.raises(ValueError, match="reads the phase energy E_tau.*ebvla-fit-phase-energy"):
        tiny_config(joint_energy=OWN_ENCODER, monitor={"failure_score": "joint_phase_time_energy"})
    assert tiny_config(joint_energy=OWN_ENCODER).monitor.failure_score == "head_energy_two_sided"
    with_phase = tiny_config(joint_energy=OWN_ENCODER, phase_energy={"bins": 4})
    assert with_phase.monitor.failure_score == "success_energy"


def rollout(n, context, head, phase, chunk_offset=0.0):
    index = np.arange(n)
    return EnergyReadout.of_arrays(
        final_energy=context + head + 0.1 * index,
        chunk_index=index,
        context_energy=np.full(n, context) + 0.01 * index,
        phase_energy=np.full(n, phase) + chunk_offset * index,
    )


def test_joint_phase_time_energy_averages_three_one_sided_terms_and_round_trips():
    rng = np.random.default_rng(0)
    vanilla = VanillaRollouts([rollout(5, *rng.normal(size=3)) for _ in range(12)])
    score = JointPhaseTimeEnergy.fit(vanilla)
    assert JointPhaseTimeEnergy.from_json(score.to_json()) == score
    typical = score.components(ChunkInputs.of(rollout(5, 0.0, 0.0, 0.0)))
    stalled = score.components(ChunkInputs.of(rollout(5, 0.0, 0.0, 0.0, chunk_offset=2.0)))
    assert typical.shape == (5, 3)
    # Only the phase term moves when only E_tau rises; the other two terms are unchanged.
    assert np.allclose(stalled[:, :2], typical[:, :2]) and (stalled[1:, 2] > typical[1:, 2]).all()
    with pytest.raises(ValueError, match="ebvla-fit-phase-energy"):
        score.components(ChunkInputs.of(EnergyReadout.of_arrays(np.zeros(3), context_energy=np.zeros(3))))


def test_records_keep_the_phase_energy():
    record = EnergyRecord(0, 3, 24, 1.0, 0.5, True, "task", 7, context_energy=0.2, phase_energy=1.25)
    assert record_from_json(json.loads(record_to_json(record))) == record
    without = EnergyRecord(0, 3, 24, 1.0, 0.5, True, "task", 7)
    assert "phase_energy" not in json.loads(record_to_json(without))
    assert record_from_json(json.loads(record_to_json(without))).phase_energy is None


def test_the_fit_script_writes_a_new_checkpoint_and_leaves_the_source_as_it_was(tmp_path):
    from lerobot_policy_ebvla import make_ebvla_pre_post_processors
    from lerobot_policy_ebvla.scripts import fit_phase_energy as fit_script

    torch.manual_seed(0)
    policy = EBVLAPolicy(tiny_config(joint_energy=OWN_ENCODER))
    config = policy.config
    stats = {
        "observation.state": {"mean": torch.zeros(config.state_dim), "std": torch.ones(config.state_dim)},
        "action": {"mean": torch.zeros(config.action_dim), "std": torch.ones(config.action_dim)},
    }
    source = tmp_path / "source"
    for component in (policy, *make_ebvla_pre_post_processors(config, dataset_stats=stats)):
        component.save_pretrained(source)
    (source / "failure_calibration.json").write_text("{}")  # of the old failure score: left behind
    (source / "train_config.json").write_text('{"steps": 3}')  # copied as it is
    before = {f.name: f.read_bytes() for f in source.iterdir()}
    data = write_tiny_dataset(tmp_path / "data", n_episodes=3, n_frames=24)

    output = tmp_path / "fitted"
    args = [f"--policy_path={source}", "--dataset_repo_id=local/ebvla_tiny", f"--dataset_root={data}"]
    fit_script.main([*args, "--bins=4", "--hidden=16", f"--output_dir={output}"])

    assert {f.name: f.read_bytes() for f in source.iterdir()} == before
    saved = json.loads((output / "config.json").read_text())
    assert saved["phase_energy"] == {"bins": 4, "hidden": 16}
    assert saved["monitor"]["failure_score"] == "success_energy"
    assert not (output / "failure_calibration.json").exists()
    assert (output / "train_config.json").read_text() == '{"steps": 3}'
    summary = json.loads((output / "phase_energy_fit.json").read_text())
    assert (summary["frames"], summary["episodes"]) == (9, 3)  # frames 0, 8 and 16 of each episode
    fitted = EBVLAPolicy.from_pretrained(output)
    assert fitted.model.phase_energy.fitted and int(fitted.model.phase_energy.fitted_frames) == 9

    with pytest.raises(ValueError, match="is not empty"):
        fit_script.main([*args, f"--output_dir={output}"])
