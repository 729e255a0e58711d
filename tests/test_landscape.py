"""Energy landscape around a refined chunk (Fig. 2), on an energy with a known minimum and on a tiny policy."""

from types import SimpleNamespace

import numpy as np
import pytest
import torch

from lerobot_policy_ebvla.monitoring.landscape import (
    energy_landscape,
    make_policy_score_fn,
    policy_energy_landscape,
    select_sample,
)
from lerobot_policy_ebvla.monitoring.plots import plot_energy_landscape

H, D_A = 4, 3
REFINED = torch.tensor([[0.5, -0.25, 1.0], [0.1, 0.2, 0.3], [0.0, 0.0, 0.0], [1.0, 1.0, 1.0]])


def anisotropic(candidates):
    """E = ||a - REFINED||^2 + 3 (a[0, 1] - REFINED[0, 1])^2: minimal at REFINED, steeper along dim 1."""
    diff = candidates - REFINED
    return (diff**2).sum(dim=(1, 2)) + 3 * diff[:, 0, 1] ** 2


def test_landscape_minimum_is_at_the_refined_action():
    landscape = energy_landscape(anisotropic, REFINED, grid_size=11, span=1.0)
    i, j = np.unravel_index(np.argmin(landscape.energies), landscape.energies.shape)
    assert (landscape.x[j], landscape.y[i]) == pytest.approx((0.5, -0.25))
    assert landscape.center_energy == 0.0


def test_landscape_rows_follow_y_and_columns_follow_x():
    landscape = energy_landscape(anisotropic, REFINED, grid_size=11, span=1.0)
    # Grid index 5 is the refined value; index 0 is one unit below it. Dim 1 (y) costs 4, dim 0 (x) 1.
    assert landscape.energies[0, 5] == pytest.approx(4.0)
    assert landscape.energies[5, 0] == pytest.approx(1.0)


def test_landscape_keeps_every_other_action_fixed():
    seen = []

    def recording(candidates):
        seen.append(candidates.clone())
        return torch.zeros(len(candidates))

    energy_landscape(recording, REFINED, dims=(2, 0), timestep=1, grid_size=5)
    candidates = torch.cat(seen)
    swept = torch.zeros(H, D_A, dtype=torch.bool)
    swept[1, 2] = swept[1, 0] = True
    assert torch.equal(candidates[:, ~swept], REFINED[~swept].expand(len(candidates), -1))


def test_landscape_scores_in_batches_of_at_most_batch_size():
    sizes = []

    def counting(candidates):
        sizes.append(len(candidates))
        return torch.zeros(len(candidates))

    energy_landscape(counting, REFINED, grid_size=10, batch_size=30)
    assert sizes == [30, 30, 30, 11]  # 100 grid points and the refined chunk itself


def test_landscape_span_pair_is_an_absolute_range():
    landscape = energy_landscape(anisotropic, REFINED, grid_size=3, span=(-2.0, 2.0))
    np.testing.assert_allclose(landscape.x, [-2, 0, 2])
    np.testing.assert_allclose(landscape.y, [-2, 0, 2])


@pytest.mark.parametrize("dims", [(0, 0), (0, 3)])
def test_landscape_rejects_invalid_dims(dims):
    with pytest.raises(ValueError, match="dims"):
        energy_landscape(anisotropic, REFINED, dims=dims)


@pytest.mark.parametrize("kind", ["surface", "contour", "both"])
def test_plot_writes_a_png(tmp_path, kind):
    landscape = energy_landscape(anisotropic, REFINED, grid_size=6)
    path = plot_energy_landscape(landscape, tmp_path / "plots" / "landscape.png", kind=kind, title="t")
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_plot_tolerates_infinite_energies(tmp_path):
    landscape = energy_landscape(
        lambda c: torch.where(c[:, 0, 0] > 0.5, torch.inf, 1.0), REFINED, grid_size=6
    )
    assert plot_energy_landscape(landscape, tmp_path / "l.png").exists()


def test_select_sample_keeps_one_observation():
    batch = {"observation.state": torch.arange(6.0).view(3, 2), "task": ["a", "b", "c"], "flag": True}
    sample = select_sample(batch, 1)
    assert sample["observation.state"].tolist() == [[2.0, 3.0]]
    assert sample["task"] == ["b"] and sample["flag"] is True


def test_policy_score_fn_scores_candidates_of_one_observation():
    calls = []

    def score_action_chunks(batch, candidates):
        calls.append(candidates.shape)
        return candidates.sum(dim=(2, 3))

    score_fn = make_policy_score_fn(SimpleNamespace(score_action_chunks=score_action_chunks), {})
    energies = score_fn(torch.ones(7, H, D_A))
    assert calls == [(1, 7, H, D_A)] and energies.tolist() == [12.0] * 7


def test_policy_energy_landscape_on_a_tiny_policy(tiny_policy):
    from .conftest import tiny_batch

    tiny_policy.eval()
    batch = tiny_batch(tiny_policy.config, batch_size=2, with_action=False)
    landscape = policy_energy_landscape(
        tiny_policy, batch, sample_index=1, generator=torch.Generator().manual_seed(0), grid_size=4
    )
    assert landscape.energies.shape == (4, 4) and np.isfinite(landscape.energies).all()
    # The refined chunk's own energy is the one the policy reports for it.
    sample = select_sample(batch, 1)
    _, readout = tiny_policy.predict_action_chunk(
        sample, return_energy=True, generator=torch.Generator().manual_seed(0)
    )
    assert landscape.center_energy == pytest.approx(readout.final_energy.item(), rel=1e-4)


def test_landscape_script_writes_a_png_for_a_saved_policy(tiny_policy, tmp_path):
    from lerobot_policy_ebvla import make_ebvla_pre_post_processors
    from lerobot_policy_ebvla.scripts import landscape as landscape_script

    from .conftest import tiny_batch

    config = tiny_policy.config
    stats = {
        "observation.state": {"mean": torch.zeros(config.state_dim), "std": torch.ones(config.state_dim)},
        "action": {"mean": torch.zeros(config.action_dim), "std": torch.ones(config.action_dim)},
    }
    preprocessor, postprocessor = make_ebvla_pre_post_processors(config, dataset_stats=stats)
    for component in (tiny_policy, preprocessor, postprocessor):
        component.save_pretrained(tmp_path / "policy")
    observation = {k: v[0] for k, v in tiny_batch(config, batch_size=1, with_action=False).items()}
    torch.save(observation, tmp_path / "obs.pt")

    output = tmp_path / "landscape.png"
    args = [f"--policy_path={tmp_path / 'policy'}", f"--observation={tmp_path / 'obs.pt'}"]
    landscape_script.main([*args, "--grid_size=4", "--device=cpu", f"--output={output}"])
    assert output.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_landscape_script_needs_exactly_one_observation_source():
    from lerobot_policy_ebvla.scripts import landscape as landscape_script

    with pytest.raises(ValueError, match="exactly one of `dataset_repo_id` and `observation`"):
        landscape_script.main(["--policy_path=p"])
