"""research/docs/libero_runs.md, "K: C's recipe from scratch with the raised starting energy": the first slice's
reading recomputed from K's committed training curve against C's logged L1, the second slice's curve, and K's
checkpoint at the end of its 20,000 steps."""

import json

from research.tests.conftest import RESULTS

K = RESULTS / "libero_object10_b18"
# C's logged L1 at steps 2000, 4000, 6000 and 8000 (libero_runs.md, "The ten-task check").
C_L1 = {2000: 0.533, 4000: 0.286, 6000: 0.209, 8000: 0.156}


def test_k_learns_faster_than_c_by_the_fixed_reading():
    """K's L1 at each step the slice reached is at most 0.8 of C's (0.50, 0.57, 0.63, 0.69 of it)."""
    logged = json.loads((K / "training_curve.json").read_text())["log_every"]
    l1 = {row["step"]: row["l1_loss"] for row in logged}
    assert max(l1) == 11200
    ratios = {step: round(l1[step] / c, 2) for step, c in C_L1.items()}
    assert ratios == {2000: 0.5, 4000: 0.57, 6000: 0.63, 8000: 0.69}
    assert all(ratio <= 0.8 for ratio in ratios.values())


def test_the_second_slice_resumed_at_11000_and_its_l1_stays_at_the_first_slices_level():
    """Steps 11,100-12,200 (2026-12-02, cut at 12,2xx; its checkpoint 12,000): L1 0.071-0.087, as the first slice's
    last steps (0.078-0.096 from step 10,000)."""
    second = json.loads((K / "training_curve.json").read_text())["second_slice"]["log_every"]
    assert [row["step"] for row in second] == list(range(11100, 12300, 100))
    assert (min(r["l1_loss"] for r in second), max(r["l1_loss"] for r in second)) == (0.071, 0.087)


def test_the_third_slice_reached_the_end_of_ks_schedule_at_the_same_l1_level():
    """Steps 12,100-20,000 (2026-12-07, the Intel Xeon): L1 0.052-0.080; K's 20,000 steps are done."""
    third = json.loads((K / "training_curve.json").read_text())["third_slice"]["log_every"]
    assert [row["step"] for row in third] == list(range(12100, 20100, 100))
    assert (min(r["l1_loss"] for r in third), max(r["l1_loss"] for r in third)) == (0.052, 0.08)


def test_ks_last_checkpoint_is_the_end_of_its_20000_steps():
    last = K / "train" / "ebvla_joint_fast_cpu_b18" / "last"
    assert json.loads((last / "pretrained_model" / "train_config.json").read_text())["steps"] == 20000
    assert (K / "train" / "ebvla_joint_fast_cpu_b18" / "DONE").exists()
    config = json.loads((last / "pretrained_model" / "config.json").read_text())
    assert config["energy_bias_init"] == 18.0
