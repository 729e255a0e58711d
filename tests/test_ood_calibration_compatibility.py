"""Calibrations saved by earlier versions still load and score chunks as they did.

Each folder of `tests/fixtures/ood_calibration_v0.1.0/` is one score's `ood_calibration.json` (with its side
files) and `expected.json`: probe chunks and what the calibration gave on them when it was written
(`make_ood_calibration_fixture.py`).
"""

import json
from pathlib import Path

import numpy as np
import pytest

from lerobot_policy_ebvla.runtime import SCORES, EnergyOODMonitor, EnergyReadout, OODCalibration
from lerobot_policy_ebvla.runtime.calibration import UnregisteredScoreError
from lerobot_policy_ebvla.runtime.scores import PACKAGE_SCORES

ALL_FIXTURES = sorted((Path(__file__).parent / "fixtures").glob("ood_calibration_v*/*"))
# The fixtures of the package's scores; the research scores' are loaded by the research tests.
FIXTURES = [folder for folder in ALL_FIXTURES if folder.name in PACKAGE_SCORES]


@pytest.mark.parametrize("folder", FIXTURES, ids=[f"{f.parent.name}/{f.name}" for f in FIXTURES])
def test_a_saved_calibration_loads_and_scores_chunks_as_it_did(folder):
    expected = json.loads((folder / "expected.json").read_text())
    energies, index, features = (np.array(v) for v in expected["probe"].values())
    calibration = OODCalibration.load(folder)
    assert calibration.score.name == folder.name
    probe = EnergyReadout.of_arrays(energies, index, features)
    np.testing.assert_allclose(calibration.chunk_score(probe), expected["chunk_scores"])
    first = calibration.chunk_score(EnergyReadout.of_arrays(energies[0], 0, features[0]))
    assert first == pytest.approx([expected["first_chunk_score"]])
    components = calibration.chunk_components(probe)
    np.testing.assert_allclose(components, expected["chunk_components"])
    assert calibration.score_rollout(components) == pytest.approx(expected["rollout_score"])
    assert calibration.threshold == pytest.approx(expected["threshold"])
    assert calibration.with_k(3.0).threshold == pytest.approx(expected["threshold_at_k_3"])


@pytest.mark.parametrize("folder", FIXTURES, ids=[f"{f.parent.name}/{f.name}" for f in FIXTURES])
def test_a_saved_calibration_saved_again_loads_the_same(folder, tmp_path):
    calibration = OODCalibration.load(folder)
    calibration.save(tmp_path)
    again = OODCalibration.load(tmp_path)
    assert again == calibration
    probe = json.loads((folder / "expected.json").read_text())["probe"]
    energies, index, features = (np.array(v) for v in probe.values())
    monitor = EnergyOODMonitor(again)
    rollout = EnergyReadout.of_arrays(energies, context_features=features)
    decision = monitor.check_rollout(rollout)
    assert decision.energy == pytest.approx(EnergyOODMonitor(calibration).check_rollout(rollout).energy)


def test_there_is_a_fixture_of_every_score_of_v0_1_0():
    names = {f.name for f in ALL_FIXTURES if f.parent.name == "ood_calibration_v0.1.0"}
    assert names == {"final_energy", "phase_energy", "context_distance", "energy_and_context", "context_knn"}
    assert {f.name for f in FIXTURES} == names & set(PACKAGE_SCORES) == {"final_energy", "context_knn"}


@pytest.mark.parametrize("name", ["phase_energy", "context_distance", "energy_and_context"])
def test_a_saved_calibration_of_a_research_score_says_how_to_register_it(name, monkeypatch):
    monkeypatch.delitem(
        SCORES, name, raising=False
    )  # as in a process that did not import the research scores
    folder = Path(__file__).parent / "fixtures" / "ood_calibration_v0.1.0" / name
    with pytest.raises(
        UnregisteredScoreError, match=rf"score '{name}', which is not registered.*research_scores"
    ):
        OODCalibration.load(folder)


def test_a_calibration_saved_with_a_window_reference_loads_without_it(tmp_path):
    # `ebvla-ood-report --calibrate_to` saved the window test's reference until that test moved to the research.
    calibration = OODCalibration.fit([4.0, 5.0, 6.0])
    path = calibration.save(tmp_path)
    payload = json.loads(path.read_text())
    assert "window_reference" not in payload
    path.write_text(json.dumps(payload | {"window_reference": [[4.0, -4.0], [5.5, 5.5]]}))
    assert OODCalibration.load(tmp_path) == calibration
