"""The LIBERO-Object two-core figures (research/docs/benchmarks_history.md section 13, issue 33), recomputed from the committed records."""

import json

import numpy as np
import pytest

from lerobot_policy_ebvla.monitoring.metrics import auroc
from lerobot_policy_ebvla.monitoring.records import group_by_episode, read_energy_records, records_file_in
from research.tests.conftest import RESULTS

EVAL = RESULTS / "libero_cpu" / "eval" / "ebvla_cpu"
SHIFTS = [f"{p}{s}" for p in ("pose", "distance", "rotation", "fov") for s in (5, 3, 1)] + ["light_dim5"]


def episodes(condition: str) -> list[list]:
    eps = []
    for task in sorted((EVAL / condition).glob("task*")):
        records = read_energy_records(records_file_in(task))
        eps += [sorted(ep, key=lambda r: r.chunk_index) for ep in group_by_episode(records).values()]
    return eps


def mean_energy(eps: list[list], chunks: int | None) -> np.ndarray:
    return np.array([np.mean([r.final_energy for r in ep[:chunks]]) for ep in eps])


def test_held_out_success_and_episode_counts():
    heldout = episodes("vanilla_heldout")
    assert (sum(ep[0].success for ep in heldout), len(heldout)) == (58, 60)
    assert sum(ep[0].success for ep in episodes("vanilla_calib")) == 29
    assert all(len(episodes(c)) == 15 for c in SHIFTS)


@pytest.mark.parametrize(("chunks", "expected"), [(3, 0.383), (None, 0.757)])
def test_the_raw_final_energy_falls_in_the_first_chunks_and_separates_over_whole_episodes(chunks, expected):
    vanilla = mean_energy(episodes("vanilla_heldout"), chunks)
    shifted = np.concatenate([mean_energy(episodes(c), chunks) for c in SHIFTS])
    assert round(auroc(vanilla, shifted), 3) == expected
    if chunks == 3:  # confidently below vanilla under the largest camera moves
        assert auroc(vanilla, mean_energy(episodes("pose3"), 3)) < 0.1


def test_diffusion_policy_on_the_same_data_fails_every_held_out_episode():
    infos = sorted((EVAL.parent / "diffusion_cpu" / "vanilla_heldout").glob("task*/eval_info.json"))
    successes = {
        info.parent.name: [
            bool(s) for t in json.loads(info.read_text())["per_task"] for s in t["metrics"]["successes"]
        ]
        for info in infos
    }
    assert {task: (sum(s), len(s)) for task, s in successes.items()} == {
        "task2": (0, 10),
        "task3": (0, 10),
        "task9": (0, 10),
    }
