"""The energy-and-context score: the final energy and the context distance, each standardized on the calibration
rollouts (z = (s - mu_v) / sigma_v), combined as the larger z (`CombinedStatistics`, `score="energy_and_context"`)
or, in the report only, as their sum.
"""

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest
import torch

from lerobot_policy_ebvla import EBVLAPolicy
from lerobot_policy_ebvla.monitoring.baselines import fit_score_reference
from lerobot_policy_ebvla.monitoring.metrics import format_auroc
from lerobot_policy_ebvla.monitoring.ood_report import OODReportConfig, write_ood_report
from lerobot_policy_ebvla.monitoring.records import (
    load_episodes,
)
from lerobot_policy_ebvla.monitoring.scores import chunk_scores, combined_rollout_scores, episode_scores
from lerobot_policy_ebvla.runtime import EnergyOODError
from lerobot_policy_ebvla.runtime.calibration import OOD_CALIBRATION_FILENAME, OODCalibration
from lerobot_policy_ebvla.runtime.monitor import EnergyOODMonitor
from lerobot_policy_ebvla.runtime.readout import EnergyReadout
from lerobot_policy_ebvla.runtime.scores import score_rollout
from lerobot_policy_ebvla.runtime.statistics import CombinedStatistics, ContextStatistics
from research.tests.conftest import load_benchmark
from tests.conftest import context_rollouts, tiny_batch, tiny_config, write_records

research_scores = load_benchmark("research_scores")
CONTEXT_FILE = research_scores.CONTEXT_FILE
EnergyAndContext = research_scores.EnergyAndContext

D = 4
# mu = (1, 2), sigma = (0.5, 4): z_E = (E - 1) / 0.5, z_d = (d - 2) / 4.
STATISTICS = CombinedStatistics((1.0, 2.0), (0.5, 4.0))


def context_statistics() -> ContextStatistics:
    return ContextStatistics.fit(np.random.default_rng(0).normal(size=(40, D)))


def combined_calibration(**kwargs) -> OODCalibration:
    """An energy-and-context calibration from its JSON fields (`context` for its side file); `kwargs` override
    them, or set the calibration's."""
    fields = {
        "context": context_statistics(),
        "combined_mean": STATISTICS.mean,
        "combined_std": STATISTICS.std,
    }
    fields |= {key: kwargs.pop(key) for key in list(kwargs) if key in fields}
    fields[CONTEXT_FILE.field] = fields.pop("context")
    return OODCalibration(
        **({"mu_v": 0.0, "sigma_v": 1.0} | kwargs), score=EnergyAndContext.from_json(fields)
    )


# The combination.


def test_each_score_is_standardized_by_its_own_calibration_mean_and_std():
    np.testing.assert_allclose(STATISTICS.z([2.0, 1.0], [2.0, 14.0]), [[2.0, 0.0], [0.0, 3.0]])


def test_the_combined_score_is_the_larger_z_so_either_score_alone_can_raise_it():
    # The first rollout is unusual in energy only, the second in context only, the third in neither.
    np.testing.assert_allclose(STATISTICS.combine([2.0, 1.0, 1.0], [2.0, 14.0, 2.0]), [2.0, 3.0, 0.0])


def test_a_nan_in_either_score_makes_the_combined_score_nan():
    assert np.isnan(STATISTICS.combine([np.nan, 1.0], [2.0, np.nan])).all()


def test_combined_statistics_fit_the_population_mean_and_std_of_each_score():
    statistics = CombinedStatistics.fit([1.0, 3.0], [10.0, 30.0])
    assert statistics.mean == (2.0, 20.0) and statistics.std == (1.0, 10.0)


def test_combined_statistics_of_identical_scores_still_divide_by_a_positive_std():
    statistics = CombinedStatistics.fit([1.0, 1.0], [2.0, 2.0])
    assert min(statistics.std) > 0
    np.testing.assert_array_equal(statistics.combine(1.0, 2.0), [0.0])


@pytest.mark.parametrize(
    ("mean", "std", "match"),
    [
        ((1.0,), (1.0,), "one entry per score"),
        ((1.0, 2.0), (1.0, 0.0), "std > 0"),
        ((np.nan, 2.0), (1.0, 1.0), "finite"),
    ],
)
def test_invalid_combined_statistics_are_refused(mean, std, match):
    with pytest.raises(ValueError, match=match):
        CombinedStatistics(mean, std)


def test_the_scores_to_combine_come_one_per_rollout():
    with pytest.raises(ValueError, match="one context distance per final energy"):
        STATISTICS.z([1.0, 2.0], [1.0])


def test_the_report_combines_rollout_scores_standardized_on_the_calibration_rollouts_by_max_or_sum():
    # Calibration: final energy mu 1, sigma 1; context distance mu 2, sigma 1.
    calibration = {"final_energy": np.array([0.0, 2.0]), "context_distance": np.array([1.0, 3.0])}
    rollouts = {
        "final_energy": np.array([3.0, 0.0]),
        "context_distance": np.array([3.0, 2.0]),
    }  # z: (2, 1), (-1, 0)
    np.testing.assert_allclose(
        combined_rollout_scores("energy_and_context", rollouts, calibration), [2.0, 0.0]
    )
    np.testing.assert_allclose(
        combined_rollout_scores("energy_and_context_sum", rollouts, calibration), [3.0, -1.0]
    )


def test_the_report_needs_both_scores_to_combine():
    scores = {"final_energy": np.array([0.0, 2.0])}
    with pytest.raises(ValueError, match=r"`rollout_scores` needs .*missing \['context_distance'\]"):
        combined_rollout_scores(
            "energy_and_context", scores, {**scores, "context_distance": np.array([1.0, 2.0])}
        )


def test_a_combined_score_has_no_chunk_score():
    with pytest.raises(ValueError, match="combined_rollout_scores"):
        chunk_scores([], "energy_and_context")


# The run-time calibration.


def test_an_energy_and_context_calibration_needs_its_statistics():
    with pytest.raises(ValueError, match="needs `context`"):
        combined_calibration(context=None)
    with pytest.raises(ValueError, match="needs `combined_mean` and `combined_std`"):
        combined_calibration(combined_mean=None, combined_std=None)
    with pytest.raises(ValueError, match="come together"):
        combined_calibration(combined_std=None)


def test_fitting_an_energy_and_context_calibration_keeps_its_standardization():
    calibration = OODCalibration.fit([0.0, 2.0], score=EnergyAndContext(context_statistics(), STATISTICS))
    assert (calibration.mu_v, calibration.sigma_v) == (1.0, 1.0) and calibration.score.combined == STATISTICS


def test_an_energy_and_context_calibration_scores_a_chunk_by_the_larger_z_of_its_energy_and_context():
    calibration = combined_calibration()
    features = np.array([[0.0, 0.0, 0.0, 0.0], [6.0, 6.0, 6.0, 6.0]])
    distances = calibration.score.context.distance(features)
    expected = np.maximum((np.array([3.0, 1.0]) - 1.0) / 0.5, (distances - 2.0) / 4.0)
    np.testing.assert_allclose(
        calibration.chunk_score(EnergyReadout.of_arrays([3.0, 1.0], 0, features)), expected
    )
    assert calibration.needs_context_features


def test_an_energy_and_context_calibration_needs_the_context_features():
    with pytest.raises(ValueError, match="pooled context"):
        combined_calibration().chunk_score(EnergyReadout.of_arrays([1.0], 0))


def test_a_rollout_aggregates_each_score_over_its_chunks_before_combining_them():
    # Chunk 0 is high in energy, chunk 1 in context: the mean of each chunk's larger z would be 2.5, while the
    # larger z of the rollout's mean energy and mean distance is 1.0 (z_E of mean energy 1.5; z_d of mean 4).
    calibration = combined_calibration()
    components = np.array([[3.0, 2.0], [0.0, 6.0]])  # (final energy, context distance) per chunk
    assert calibration.score_rollout(components) == pytest.approx(max((1.5 - 1.0) / 0.5, (4.0 - 2.0) / 4.0))


def test_a_rollout_of_the_wrong_number_of_components_is_refused():
    with pytest.raises(ValueError, match=r"must be \(N, 2\)"):
        combined_calibration().score_rollout(np.array([[1.0], [2.0]]))


def test_the_monitor_scores_a_running_rollout_as_it_scores_the_finished_one():
    calibration = combined_calibration(aggregation="mean")
    features = np.random.default_rng(3).normal(2.0, 1.0, size=(3, 2, D))  # (chunks, environments, D)
    energies = np.array([[1.2, 0.8], [3.0, 1.0], [1.1, 0.9]])
    monitor = EnergyOODMonitor(calibration)
    for chunk in range(3):
        chunk_readout = EnergyReadout(None, torch.tensor(energies[chunk]), chunk_index=chunk)
        chunk_readout.context_features = torch.from_numpy(features[chunk])
        decisions = monitor.update(chunk_readout)
    for env in range(2):
        finished = EnergyOODMonitor(calibration).check_rollout(
            EnergyReadout.of_arrays(energies[:, env], context_features=features[:, env])
        )
        mean_distance = calibration.score.context.distance(features[:, env]).mean()
        expected = STATISTICS.combine(energies[:, env].mean(), mean_distance)[0]
        assert decisions[env].energy == pytest.approx(finished.energy) == pytest.approx(expected)


def test_an_energy_and_context_calibration_round_trips_through_json_and_safetensors(tmp_path):
    calibration = combined_calibration(k=0.5)
    calibration.save(tmp_path)
    payload = json.loads((tmp_path / OOD_CALIBRATION_FILENAME).read_text())
    assert payload["combined_mean"] == [1.0, 2.0] and payload["combined_std"] == [0.5, 4.0]
    assert payload[CONTEXT_FILE.field]["file"] == CONTEXT_FILE.filename
    loaded = OODCalibration.load(tmp_path)
    assert loaded == calibration and loaded.score.combined == STATISTICS
    features = np.full((1, D), 3.0)
    chunk = EnergyReadout.of_arrays([2.0], 0, features)
    assert loaded.chunk_score(chunk) == pytest.approx(calibration.chunk_score(chunk))


def test_a_calibration_json_with_a_broken_combined_field_names_it(tmp_path):
    combined_calibration().save(tmp_path)
    path = tmp_path / OOD_CALIBRATION_FILENAME
    payload = json.loads(path.read_text())
    payload["combined_std"] = [0.5]
    path.write_text(json.dumps(payload))
    with pytest.raises(ValueError, match="combined_std"):
        OODCalibration.load(tmp_path)


def test_the_policy_responds_to_the_larger_z_of_each_chunks_energy_and_context(tmp_path):
    torch.manual_seed(0)
    policy = EBVLAPolicy(tiny_config()).eval()
    contexts = [tiny_batch(policy.config, batch_size=4, seed=s, with_action=False) for s in range(3)]
    statistics = ContextStatistics.fit(torch.cat([policy.context_features(b) for b in contexts]))
    # A threshold below every score: every chunk is flagged and raises with its highest score.
    combined_calibration(mu_v=-1e6, sigma_v=0.0, context=statistics).save(tmp_path)
    policy.configure_ood_response(tmp_path, response="raise")
    batch = tiny_batch(policy.config, batch_size=2, seed=7, with_action=False)
    with pytest.raises(EnergyOODError, match="energy_and_context") as raised:
        policy.predict_action_chunk(batch)
    distances = statistics.distance(policy.context_features(batch))
    expected = STATISTICS.combine(policy.last_energy.final_energy, distances).max()
    assert raised.value.energy == pytest.approx(expected, rel=1e-4)


# The report.


@pytest.fixture(scope="module")
def record_dirs(tmp_path_factory):
    """Calibration and held-out vanilla rollouts; "energy" shifts only the final energy, "light" only the
    context."""
    root = tmp_path_factory.mktemp("records")
    return (
        write_records(root / "calibration", context_rollouts(12, seed=10)),
        write_records(root / "vanilla", context_rollouts(12, seed=11)),
        write_records(
            root / "ood",
            context_rollouts(10, 1, "energy", energy=6.0) + context_rollouts(10, 2, "light", context=1.5),
        ),
    )


def report(record_dirs, out: Path, **options) -> str:
    calibration, vanilla, ood = record_dirs
    cfg = OODReportConfig(
        calibration=[calibration], vanilla=[vanilla], ood=[ood], output_dir=out, n_bootstrap=50, **options
    )
    return write_ood_report(cfg)


@pytest.fixture(scope="module")
def report_text(record_dirs, tmp_path_factory) -> str:
    return report(record_dirs, tmp_path_factory.mktemp("report"), first_chunks=[2])


def cell(table: str, row: str, column: str) -> str:
    lines = [line for line in table.splitlines() if line.startswith("|")]
    header = [c.strip() for c in lines[0].split("|")]
    (line,) = [line for line in lines if line.startswith(f"| {row} |")]
    return [c.strip() for c in line.split("|")][header.index(column)]


def section(text: str, title: str) -> str:
    return text.split(f"## {title}")[1].split("\n## ")[0]


def expected_combined_scores(record_dirs, first_chunks=None) -> dict[str, np.ndarray]:
    """The combined score of every held-out rollout, recomputed from the package's per-score rollout scores."""
    calibration, vanilla, ood = (load_episodes([d]) for d in record_dirs)
    reference = fit_score_reference(calibration)

    def scores(episodes):
        return {
            n: episode_scores(episodes, n, reference=reference, first_chunks=first_chunks)
            for n in ("final_energy", "context_distance")
        }

    statistics = CombinedStatistics.fit(*scores(calibration).values())
    by_condition = {"vanilla": vanilla}
    for perturbation in ("energy", "light"):
        by_condition[perturbation] = {k: e for k, e in ood.items() if k[1].perturbation == perturbation}
    return {c: statistics.combine(*scores(episodes).values()) for c, episodes in by_condition.items()}


def test_the_report_puts_the_combined_scores_beside_every_other(report_text):
    auroc_table = section(report_text, "AUROC [bootstrap 95% interval] by score")
    assert "| context_distance | context_knn | energy_and_context | energy_and_context_sum |" in auroc_table
    assert section(report_text, "Detection on the first chunks").count("| energy_and_context | ") == 3
    assert section(report_text, "Table III: light 1").count("Bal. Acc. energy_and_context") == 2
    assert "| energy_and_context | 12 |" in section(report_text, "Calibration")


def test_the_combined_score_catches_a_condition_only_the_energy_sees_and_one_only_the_context_sees(
    report_text,
):
    table = section(report_text, "AUROC [bootstrap 95% interval] by score")
    value = {
        (c, s): float(cell(table, c, s).split()[0])
        for c in ("energy 1", "light 1")
        for s in ("final_energy", "context_distance", "energy_and_context")
    }
    assert value["energy 1", "final_energy"] > 0.95 and value["energy 1", "context_distance"] < 0.8
    assert value["light 1", "context_distance"] > 0.95 and value["light 1", "final_energy"] < 0.8
    assert value["energy 1", "energy_and_context"] > 0.95 and value["light 1", "energy_and_context"] > 0.95


@pytest.mark.parametrize("condition", ["energy", "light"])
def test_the_reported_combined_auroc_is_that_of_the_combined_rollout_scores(
    record_dirs, report_text, condition
):
    expected = expected_combined_scores(record_dirs)
    table = section(report_text, "AUROC [bootstrap 95% interval] by score")
    assert cell(table, f"{condition} 1", "energy_and_context") == format_auroc(
        expected["vanilla"], expected[condition], 50
    )


def test_over_the_first_chunks_the_combined_score_is_standardized_on_the_calibrations_first_chunks(
    record_dirs, report_text
):
    expected = expected_combined_scores(record_dirs, first_chunks=2)
    table = section(report_text, "Detection on the first chunks").split("### light 1")[1]
    assert cell(table, "energy_and_context", "first 2 chunks") == format_auroc(
        expected["vanilla"], expected["light"], 50
    )


def test_the_report_has_no_combined_score_without_context_features(record_dirs, tmp_path):
    dirs = []
    for name, folder in zip(("calibration", "vanilla", "ood"), record_dirs, strict=True):
        records = [
            dataclasses.replace(r, context_feature=None) for e in load_episodes([folder]).values() for r in e
        ]
        dirs.append(write_records(tmp_path / name, records))
    assert "energy_and_context" not in report(dirs, tmp_path / "out")


@pytest.mark.parametrize(
    ("folder", "title"),
    [
        (1, "held-out vanilla rollouts: 4 of 12 failed"),
        (2, "perturbed rollouts, all conditions: 8 of 20 failed"),
    ],
)
def test_the_report_measures_every_score_on_failed_against_successful_rollouts(
    record_dirs, report_text, folder, title
):
    episodes = load_episodes([record_dirs[folder]])
    failed = np.array([not e[0].success for e in episodes.values()])
    table = section(report_text, "Failed vs successful rollouts").split(f"### {title}")[1].split("###")[0]
    energies = episode_scores(episodes, "final_energy")
    assert cell(table, "final_energy", "whole episode") == format_auroc(
        energies[~failed], energies[failed], 50
    )
    combined = expected_combined_scores(record_dirs)
    scores = combined["vanilla"] if folder == 1 else np.concatenate([combined["energy"], combined["light"]])
    assert cell(table, "energy_and_context", "first 2 chunks").count("[") == 1
    assert cell(table, "energy_and_context", "whole episode") == format_auroc(
        scores[~failed], scores[failed], 50
    )


def test_the_report_saves_the_energy_and_context_calibration_its_tables_score(record_dirs, tmp_path):
    checkpoint = tmp_path / "pretrained_model"
    checkpoint.mkdir()
    text = report(record_dirs, tmp_path / "out", calibrate_to=checkpoint, score="energy_and_context")
    assert "`--score=energy_and_context`" in text
    calibration = OODCalibration.load(checkpoint)
    assert calibration.score.name == "energy_and_context" and calibration.n_rollouts == 12
    # The run-time score of each held-out rollout is the report's: same statistics, same combination.
    expected = expected_combined_scores(record_dirs)["vanilla"]
    vanilla = load_episodes([record_dirs[1]])
    components = [
        calibration.chunk_components(
            EnergyReadout.of_arrays(
                [r.final_energy for r in e], context_features=np.stack([r.context_feature for r in e])
            )
        )
        for e in vanilla.values()
    ]
    scored = [score_rollout(calibration.score, c, calibration.aggregation) for c in components]
    np.testing.assert_allclose(scored, expected)
    # What the monitor compares to T is the window score of those running scores over the first 3 chunks.
    window = calibration.window
    running = [
        [score_rollout(calibration.score, c[:n], calibration.aggregation) for n in (1, 2, 3)]
        for c in components
    ]
    np.testing.assert_allclose([calibration.score_rollout(c) for c in components], window.scores(running))
    # The report states the threshold it saved: fitted on the calibration rollouts' first 3 chunks.
    saved = (
        f"mu_v = {calibration.mu_v:.4g}, sigma_v = {calibration.sigma_v:.4g}, T = {calibration.threshold:.4g}"
    )
    assert "over their first 3 chunks" in text and saved in text


def test_the_outcome_tables_show_what_knowing_the_conditions_alone_reaches(record_dirs, tmp_path):
    ood = context_rollouts(10, 1, "energy", energy=6.0, fail_every=2)
    ood += context_rollouts(10, 2, "light", context=1.5, fail_every=5)
    dirs = (*record_dirs[:2], write_records(tmp_path / "ood", ood))
    outcomes = section(report(dirs, tmp_path / "out", first_chunks=[2]), "Failed vs successful rollouts")
    vanilla, ood = (load_episodes([d]) for d in dirs[1:])
    vanilla_failed = np.array([not e[0].success for e in vanilla.values()])
    ood_failed = np.array([not e[0].success for e in ood.values()])
    share = {
        p: np.mean([not e[0].success for k, e in ood.items() if k[1].perturbation == p])
        for p in ("energy", "light")
    }
    assert share == {"energy": 0.5, "light": 0.2}
    condition_rates = np.array([share[k[1].perturbation] for k in ood])

    pooled = outcomes.split("### held-out vanilla and perturbed")[1]
    failed = np.concatenate([vanilla_failed, ood_failed])
    perturbed = np.concatenate([np.zeros(len(vanilla)), np.ones(len(ood))])
    rates = np.concatenate([np.full(len(vanilla), vanilla_failed.mean()), condition_rates])
    for row, labels in (
        ("_reference: perturbed or not_", perturbed),
        ("_reference: its condition's failure rate_", rates),
    ):
        for column in ("first 2 chunks", "whole episode"):
            assert cell(pooled, row, column) == format_auroc(labels[~failed], labels[failed], 50)
    perturbed_only = outcomes.split("### perturbed rollouts")[1].split("###")[0]
    expected = format_auroc(condition_rates[~ood_failed], condition_rates[ood_failed], 50)
    assert cell(perturbed_only, "_reference: its condition's failure rate_", "whole episode") == expected
    assert "_reference: perturbed or not_" not in perturbed_only
    assert "_reference" not in outcomes.split("### held-out vanilla rollouts")[1].split("###")[0]
