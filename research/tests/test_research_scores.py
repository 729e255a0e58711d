"""The research scores (`benchmarks/research_scores.py`): two-sided scores flag a shift that lowers the energy
below vanilla's; and the report saves the checkpoint's own monitor score.

A shift can make the final energy fall below vanilla's (issue 32: dim light, another colour), so the one-sided
energy is confidently wrong there. The two-sided forms flag a rollout on either side of the vanilla band.
"""

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest

from lerobot_policy_ebvla.monitoring.ood_report import OODReportConfig
from lerobot_policy_ebvla.runtime import SCORES, EnergyOODMonitor, OODCalibration, VanillaRollouts
from lerobot_policy_ebvla.runtime.readout import EnergyReadout
from lerobot_policy_ebvla.runtime.scores import (
    ChunkInputs,
    ContextPhaseEnergy,
    FinalEnergy,
    HeadEnergyTwoSided,
    score_rollout,
)
from research.tests.conftest import load_benchmark
from tests.conftest import write_calibration_vanilla_and_ood, write_records

research_scores = load_benchmark("research_scores")
ContextEnergy = research_scores.ContextEnergy
ContextEnergyTwoSided = research_scores.ContextEnergyTwoSided
EnergyTwoSidedAndContextKNN = research_scores.EnergyTwoSidedAndContextKNN
FinalEnergyTwoSided = research_scores.FinalEnergyTwoSided
PhaseEnergy = research_scores.PhaseEnergy
PhaseEnergyDeviation = research_scores.PhaseEnergyDeviation
PhaseEnergyTwoSided = research_scores.PhaseEnergyTwoSided

N_CHUNKS, DIM = 6, 4


def chunk_inputs(*arrays) -> ChunkInputs:
    """Recorded chunks as the scores read them (`EnergyReadout.of_arrays`'s arguments)."""
    return ChunkInputs.of(EnergyReadout.of_arrays(*arrays))


def vanilla(n=12, seed=0) -> VanillaRollouts:
    """Vanilla rollouts whose final energy falls with the task's phase (5, 4.8, ...), whose contexts are
    standard normal and whose joint energy's context term E_c is near 0."""
    rng = np.random.default_rng(seed)
    phase = 5.0 - 0.2 * np.arange(N_CHUNKS)
    energies = [phase + rng.normal(0, 0.1, N_CHUNKS) for _ in range(n)]
    features = [rng.normal(0, 1, (N_CHUNKS, DIM)) for _ in range(n)]
    context_energies = [rng.normal(0, 0.1, N_CHUNKS) for _ in range(n)]
    series = zip(energies, features, context_energies, strict=True)
    return VanillaRollouts([chunk_inputs(e, np.arange(N_CHUNKS), c, ec) for e, c, ec in series])


def calibrated(score_class, rollouts: VanillaRollouts) -> OODCalibration:
    """The calibration of a score on the vanilla rollouts (each scored by the score fitted without it)."""
    scores = []
    for i, chunks in enumerate(rollouts.rollouts):
        score = score_class.fit(rollouts.without(i))
        scores.append(score_rollout(score, score.components(chunks), "mean"))
    return OODCalibration.fit(scores, score=score_class.fit(rollouts))


def rollout_score(calibration: OODCalibration, energies, features=None, context_energy=None) -> float:
    features = np.zeros((len(energies), DIM)) if features is None else features
    context_energy = np.zeros(len(energies)) if context_energy is None else context_energy
    components = calibration.chunk_components(
        EnergyReadout.of_arrays(energies, None, features, context_energy)
    )
    return calibration.score_rollout(components)


@pytest.mark.parametrize(
    ("one_sided", "two_sided"),
    [
        (FinalEnergy, FinalEnergyTwoSided),
        (PhaseEnergy, PhaseEnergyTwoSided),
        (PhaseEnergy, PhaseEnergyDeviation),
    ],
)
def test_an_energy_below_vanilla_scores_high_two_sided_and_low_one_sided(one_sided, two_sided):
    rollouts = vanilla()
    below = np.full(N_CHUNKS, 3.0)  # every chunk's energy well under vanilla's
    one, two = calibrated(one_sided, rollouts), calibrated(two_sided, rollouts)
    assert rollout_score(one, below) < one.threshold
    assert rollout_score(two, below) > two.threshold
    held_out = vanilla(seed=1).final_energies[0]
    assert rollout_score(two, held_out) < rollout_score(two, below)


@pytest.mark.parametrize("two_sided", [FinalEnergyTwoSided, PhaseEnergyTwoSided, PhaseEnergyDeviation])
def test_a_two_sided_score_flags_an_energy_above_vanilla_as_the_one_sided_does(two_sided):
    calibration = calibrated(two_sided, vanilla())
    assert rollout_score(calibration, np.full(N_CHUNKS, 7.0)) > calibration.threshold


def test_the_two_sided_phase_energy_is_the_magnitude_of_the_phase_energy():
    rollouts = vanilla()
    one, two = PhaseEnergy.fit(rollouts), PhaseEnergyTwoSided.fit(rollouts)
    energies = np.array([4.0, 5.5, 3.0])
    z = one.components(chunk_inputs(energies, np.arange(3)))
    assert two.components(chunk_inputs(energies, np.arange(3))) == pytest.approx(z)
    assert score_rollout(two, z, "mean") == pytest.approx(abs(z.mean()))


def test_the_phase_energy_deviation_flags_a_rollout_on_both_sides_that_the_aggregate_z_misses():
    """Chunks above the vanilla band early and as far below it later: their mean z is near 0, so |mean z| passes
    the rollout, and the mean of |z_t| does not."""
    rollouts = vanilla()
    aggregate, deviation = (
        calibrated(PhaseEnergyTwoSided, rollouts),
        calibrated(PhaseEnergyDeviation, rollouts),
    )
    phase = PhaseEnergy.fit(rollouts).phase
    z_t = np.array([20.0, 20.0, 20.0, -20.0, -20.0, -20.0])
    both_sides = np.array(phase.mean[:N_CHUNKS]) + z_t * np.array(phase.std[:N_CHUNKS])
    assert rollout_score(aggregate, both_sides) < aggregate.threshold
    assert rollout_score(deviation, both_sides) > deviation.threshold
    chunks = chunk_inputs(both_sides, np.arange(N_CHUNKS))
    assert deviation.score.components(chunks)[:, 0] == pytest.approx(np.abs(z_t))


def test_the_energy_and_context_knn_flags_a_low_energy_and_a_far_context():
    calibration = calibrated(EnergyTwoSidedAndContextKNN, vanilla())
    typical = vanilla(seed=2).rollouts[0]
    energies, features = typical.final_energy, typical.context_features
    assert rollout_score(calibration, energies, features) < calibration.threshold
    assert rollout_score(calibration, np.full(N_CHUNKS, 3.0), features) > calibration.threshold
    assert rollout_score(calibration, energies, features + 6.0) > calibration.threshold


@pytest.mark.parametrize(
    "score_class",
    [
        FinalEnergyTwoSided,
        PhaseEnergyTwoSided,
        PhaseEnergyDeviation,
        EnergyTwoSidedAndContextKNN,
        ContextEnergyTwoSided,
    ],
)
def test_a_two_sided_calibration_is_saved_and_loaded_back_and_monitors_the_same(score_class, tmp_path):
    assert SCORES[score_class.name] is score_class
    calibration = calibrated(score_class, vanilla())
    calibration.save(tmp_path)
    loaded = OODCalibration.load(tmp_path)
    assert loaded == calibration and type(loaded.score) is score_class
    energies, context_energy = np.full(N_CHUNKS, 3.0), np.full(N_CHUNKS, -2.0)
    features = np.ones((N_CHUNKS, DIM))
    expected = rollout_score(calibration, energies, features, context_energy)
    decision = EnergyOODMonitor(loaded).check_rollout(
        EnergyReadout.of_arrays(energies, None, features, context_energy)
    )
    assert decision.energy == pytest.approx(expected) and decision.is_ood


@pytest.fixture(scope="module")
def record_dirs(tmp_path_factory):
    return write_calibration_vanilla_and_ood(tmp_path_factory.mktemp("records"), "dim", 4.0)


def report(record_dirs, out, **options) -> tuple[str, OODCalibration]:
    calibration, held_out, ood = record_dirs
    (out / "pretrained_model").mkdir(parents=True, exist_ok=True)
    cfg = OODReportConfig(
        calibration=[calibration],
        vanilla=[held_out],
        ood=[ood],
        output_dir=out / "report",
        n_bootstrap=20,
        calibrate_to=out / "pretrained_model",
        **options,
    )
    # The package's report with the research's score summary after it.
    return load_benchmark("score_summaries").report_with_summary(cfg), OODCalibration.load(
        out / "pretrained_model"
    )


def test_the_report_sets_each_two_sided_score_beside_its_one_sided_form(record_dirs, tmp_path):
    text, _ = report(record_dirs, tmp_path)
    header = text.split("## AUROC")[1].split("\n\n")[1].splitlines()[0]
    assert "| final_energy | final_energy_two_sided | phase_energy | phase_energy_two_sided |" in header
    assert "| phase_energy_deviation |" in header
    # An energy below vanilla's: inverted one-sided (with `!`, its interval wholly below 0.5), high two-sided.
    summary = text.split("## Score summary")[1].split("\n## ")[0]
    row = {line.split(" | ")[0].strip("| "): line for line in summary.splitlines() if line.startswith("| ")}
    assert "dim 1 0.00!" in row["final_energy"]
    assert row["final_energy_two_sided"].split(" | ")[1].startswith("1.000")


def test_without_a_score_or_a_checkpoint_config_the_report_saves_the_final_energy(record_dirs, tmp_path):
    text, calibration = report(record_dirs, tmp_path)
    assert calibration.score.name == "final_energy"
    assert (
        "Without `--score`, `--calibrate_to` saves the checkpoint's `monitor.score`: `final_energy`" in text
    )


def with_context_energy(record_dirs, root) -> list:
    """The record folders again, each chunk with a context energy E_c (as a joint-energy policy records it)."""
    from lerobot_policy_ebvla.monitoring.records import read_energy_records

    folders = []
    for i, folder in enumerate(record_dirs):
        records = [
            dataclasses.replace(r, context_energy=0.1 * r.final_energy) for r in read_energy_records(folder)
        ]
        folders.append(write_records(root / f"joint{i}", records))
    return folders


@pytest.mark.parametrize(
    ("monitor_score", "context_energy"), [("context_knn", False), ("context_phase_energy", True)]
)
def test_without_a_score_the_report_saves_the_checkpoints_monitor_score(
    record_dirs, tmp_path, monitor_score, context_energy
):
    """The score was decided when the policy was trained (`config.monitor.score`); the records change nothing."""
    checkpoint = tmp_path / "pretrained_model"
    checkpoint.mkdir()
    # A policy with E_c on its own encoder, for the score that reads it (the config refuses it otherwise).
    joint_energy = {"target": "observation", "weight": 0.01} if context_energy else {}
    (checkpoint / "config.json").write_text(
        json.dumps({"type": "ebvla", "joint_energy": joint_energy, "monitor": {"score": monitor_score}})
    )
    folders = with_context_energy(record_dirs, tmp_path / "records") if context_energy else record_dirs
    text, calibration = report(folders, tmp_path)
    assert calibration.score.name == monitor_score
    assert f"saves the checkpoint's `monitor.score`: `{monitor_score}`" in text


def test_a_context_energy_score_on_records_without_it_is_refused_by_name(record_dirs, tmp_path):
    with pytest.raises(ValueError, match="context_energy_two_sided.*context energy E_c.*joint_energy.target"):
        report(record_dirs, tmp_path, score="context_energy_two_sided")


def test_the_papers_final_energy_stays_available(record_dirs, tmp_path):
    _, calibration = report(record_dirs, tmp_path, score="final_energy")
    assert calibration.score == FinalEnergy()


def test_a_context_energy_under_vanilla_is_flagged_two_sided_and_missed_one_sided():
    """Issue 32: some shifts put the joint energy's context term E_c *under* the data's; only |z| E_c flags
    them. The final energy plays no part in either score."""
    rollouts = vanilla()
    one, two = calibrated(ContextEnergy, rollouts), calibrated(ContextEnergyTwoSided, rollouts)
    energies = vanilla(seed=1).rollouts[0].final_energy
    # Ten vanilla sigmas either side of the vanilla E_c (around 0).
    under, over, typical = np.full(N_CHUNKS, -1.0), np.full(N_CHUNKS, 1.0), np.zeros(N_CHUNKS)
    assert rollout_score(one, energies, context_energy=under) < one.threshold
    assert rollout_score(two, energies, context_energy=under) > two.threshold
    for calibration in (one, two):
        assert rollout_score(calibration, energies, context_energy=over) > calibration.threshold
        assert rollout_score(calibration, energies, context_energy=typical) < calibration.threshold
        assert rollout_score(calibration, energies + 100.0, context_energy=under) == pytest.approx(
            rollout_score(calibration, energies, context_energy=under)
        )


def rising_context_energy_rollouts() -> tuple[np.ndarray, VanillaRollouts]:
    """12 vanilla rollouts whose E_c rises by 0.5 a chunk (noise 0.05), and that mean rise."""
    rng = np.random.default_rng(0)
    rising = 0.5 * np.arange(N_CHUNKS)
    return rising, VanillaRollouts(
        [
            chunk_inputs(
                np.zeros(N_CHUNKS), np.arange(N_CHUNKS), None, rising + rng.normal(0, 0.05, N_CHUNKS)
            )
            for _ in range(12)
        ]
    )


def test_the_two_sided_context_energy_compares_each_chunk_with_vanilla_at_its_index():
    """E_c follows the task's phase (here it rises chunk by chunk). A rollout whose E_c stays at the vanilla
    episode's overall mean is off at every chunk index: flagged, though one band for every chunk would pass it."""
    rising, rollouts = rising_context_energy_rollouts()
    calibration = calibrated(ContextEnergyTwoSided, rollouts)
    np.testing.assert_allclose(calibration.score.phase.mean[:N_CHUNKS], rising, atol=0.05)
    energies = np.zeros(N_CHUNKS)
    flat = np.full(N_CHUNKS, rising.mean())
    first_three = chunk_inputs(energies[:3], np.arange(3), None, flat[:3])
    assert calibration.score_rollout(calibration.score.components(first_three)) > calibration.threshold
    assert rollout_score(calibration, energies, context_energy=rising) < calibration.threshold


def test_the_one_sided_context_phase_energy_is_the_signed_z_the_two_sided_form_takes_the_magnitude_of(
    tmp_path,
):
    """For an E_c trained flat at the data, which every shift raises: a rollout below the band is not flagged,
    one above it is, each chunk against vanilla at its own index; saved and loaded back as the others."""
    rising, rollouts = rising_context_energy_rollouts()
    one, two = calibrated(ContextPhaseEnergy, rollouts), calibrated(ContextEnergyTwoSided, rollouts)
    assert SCORES["context_phase_energy"] is ContextPhaseEnergy
    assert one.score.phase == two.score.phase
    energies = np.zeros(N_CHUNKS)
    for offset in (-1.0, 1.0):
        shifted = rising + offset
        z = one.score_rollout(
            one.score.components(chunk_inputs(energies, np.arange(N_CHUNKS), None, shifted))
        )
        assert np.sign(z) == offset
        assert rollout_score(two, energies, context_energy=shifted) == pytest.approx(abs(z))
    assert rollout_score(one, energies, context_energy=rising + 1.0) > one.threshold
    assert rollout_score(one, energies, context_energy=rising - 1.0) < one.threshold
    one.save(tmp_path)
    loaded = OODCalibration.load(tmp_path)
    assert loaded == one and type(loaded.score) is ContextPhaseEnergy


def test_the_head_energy_score_reads_the_final_energy_without_the_context_term(tmp_path):
    """A shift that raises E_c alone (a harmless one, to the policy) leaves the head's energy E - E_c in the
    vanilla band; a head energy off the band on either side, its E_c unchanged, is flagged; saved and loaded."""
    rng = np.random.default_rng(0)
    phase = 5.0 - 0.2 * np.arange(N_CHUNKS)
    rollouts = VanillaRollouts(
        [
            chunk_inputs(phase + c + rng.normal(0, 0.1, N_CHUNKS), np.arange(N_CHUNKS), None, c)
            for c in (rng.normal(0, 0.1, N_CHUNKS) for _ in range(12))
        ]
    )
    calibration = calibrated(HeadEnergyTwoSided, rollouts)
    assert SCORES["head_energy_two_sided"] is HeadEnergyTwoSided
    np.testing.assert_allclose(calibration.score.phase.mean[:N_CHUNKS], phase, atol=0.1)
    context_up = np.full(N_CHUNKS, 10.0)  # E_c far off the data, the head's part typical
    assert rollout_score(calibration, phase + context_up, context_energy=context_up) < calibration.threshold
    for offset in (-1.0, 1.0):
        assert (
            rollout_score(calibration, phase + offset, context_energy=np.zeros(N_CHUNKS))
            > calibration.threshold
        )
    calibration.save(tmp_path)
    loaded = OODCalibration.load(tmp_path)
    assert loaded == calibration and type(loaded.score) is HeadEnergyTwoSided


@pytest.mark.parametrize(
    "score_class", [ContextEnergy, ContextPhaseEnergy, ContextEnergyTwoSided, HeadEnergyTwoSided]
)
def test_a_context_energy_score_without_the_context_energy_says_where_it_comes_from(score_class):
    calibration = calibrated(score_class, vanilla())
    with pytest.raises(ValueError, match=f"{score_class.name} score needs each chunk's context energy E_c"):
        calibration.chunk_score(EnergyReadout.of_arrays(1.0, 0))
    with pytest.raises(ValueError, match="`context_energy` has 2 row"):
        calibration.chunk_score(EnergyReadout.of_arrays(np.ones(3), 0, context_energy=np.zeros(2)))
    bare = VanillaRollouts(
        [EnergyReadout.of_arrays(r.final_energy, r.chunk_index) for r in vanilla().rollouts]
    )
    with pytest.raises(ValueError, match="joint_energy.target"):
        score_class.fit(bare)


RESEARCH_FIXTURES = [
    folder
    for folder in sorted((Path(__file__).parents[2] / "tests" / "fixtures").glob("ood_calibration_v*/*"))
    if folder.name in research_scores.RESEARCH_NAMES
]


@pytest.mark.parametrize(
    "folder", RESEARCH_FIXTURES, ids=[f"{f.parent.name}/{f.name}" for f in RESEARCH_FIXTURES]
)
def test_a_saved_calibration_of_a_research_score_loads_once_registered(folder):
    expected = json.loads((folder / "expected.json").read_text())
    energies, index, features = (np.array(v) for v in expected["probe"].values())
    calibration = OODCalibration.load(folder)
    assert calibration.score.name == folder.name
    np.testing.assert_allclose(
        calibration.chunk_score(EnergyReadout.of_arrays(energies, index, features)), expected["chunk_scores"]
    )
    assert calibration.threshold == pytest.approx(expected["threshold"])


def test_the_research_scores_of_the_v0_1_0_fixtures_are_registered():
    assert {f.name for f in RESEARCH_FIXTURES} == {"phase_energy", "context_distance", "energy_and_context"}
