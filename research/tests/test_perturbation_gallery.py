"""research/benchmarks/metaworld_perturbation_gallery.py: the figure of the training corruptions."""

import numpy as np

from research.tests.conftest import load_benchmark


def test_gallery_blends_a_training_corruption_in_by_its_strength():
    gallery = load_benchmark("metaworld_perturbation_gallery")
    frame = np.random.default_rng(0).integers(40, 200, (16, 16, 3), dtype=np.uint8)
    none, half, full = gallery.corrupted_frames(frame, "shading", [0.0, 0.5, 1.0], seed=0)
    np.testing.assert_array_equal(none, frame)
    change_half = np.abs(half.astype(float) - frame).mean()
    change_full = np.abs(full.astype(float) - frame).mean()
    assert 0.4 * change_full < change_half < 0.6 * change_full and change_full > 5
