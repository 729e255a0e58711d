"""The GPU bundle (`research/benchmarks/gpu_bundle.py`, issue 35) is complete before any GPU comes.

The bundle is built from the package index, then installed, as on the lent GPU machine, into a fresh venv whose
Python sees exactly the distributions the machine has (`research/benchmarks/device/gpu_machine_packages.txt`, linked from
this environment), with pip's configuration, index and find-links switched off: only the bundle's wheels. In that
venv the first stage of each GPU job runs at tiny size on the CPU: the LIBERO pipeline's recording (one short
episode), `ebvla-train` for two steps (LeRobot's Diffusion Policy, trained beside it there, is imported), and the
VLM benchmark. A wheel missing from the bundle stops the install with pip's message naming the package.

The machine's versions where the list records them (numpy 2.5.2, transformers 5.17.0, ...) are what the venv's
metadata says; the code behind them is this environment's.
"""

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from research.tests.conftest import ROOT as REPO
from research.tests.conftest import load_benchmark
from tests.test_libero import requires_libero

gpu_bundle = load_benchmark("gpu_bundle")
PART_MIB = 40.0


def machine_env(tmp: Path) -> dict[str, str]:
    """The environment of a command on the machine: no pip configuration or index, no path of this checkout."""
    env = {k: v for k, v in os.environ.items() if not k.startswith(("PIP_", "PYTHON", "VIRTUAL_ENV"))}
    return (
        env
        | gpu_bundle.PIP_ENV
        | {
            "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl"),
            "LIBERO_CONFIG_PATH": str(tmp / "libero_config"),
            "HF_HOME": str(tmp / "hf_home"),
            "HF_HUB_OFFLINE": "1",
            "OMP_NUM_THREADS": "1",
            "PYTHONNOUSERSITE": "1",
        }
    )


def unpack(parts: list[Path], bundle: Path) -> None:
    """What `libero_gpu_slices.sh unpack` does with each carried part: copy its files into one folder."""
    for part in parts:
        shutil.copytree(part, bundle, dirs_exist_ok=True)


@pytest.fixture(scope="session")
def built(tmp_path_factory):
    """The bundle, built once per session (its wheels are fetched from the package index)."""
    out = tmp_path_factory.mktemp("gpu_bundle") / "bundle"
    manifest = gpu_bundle.build(out, PART_MIB)
    return out, manifest


@pytest.fixture(scope="session")
def machine_site(tmp_path_factory):
    site = tmp_path_factory.mktemp("machine") / "site-packages"
    gpu_bundle.build_machine_site(site, gpu_bundle.machine_packages())
    return site


@pytest.fixture(scope="session")
def machine(built, machine_site, tmp_path_factory):
    """(python of the venv installed from the bundle alone, its environment, a scratch folder)."""
    out, _ = built
    tmp = tmp_path_factory.mktemp("machine_run")
    bundle = tmp / "unpacked"
    unpack(sorted(out.glob("part*")), bundle)
    env = machine_env(tmp)
    command = [
        sys.executable,
        str(REPO / "research" / "benchmarks" / "gpu_bundle.py"),
        "install",
        f"--bundle={bundle}",
    ]
    command += [f"--venv={tmp / 'venv'}", f"--machine_site={machine_site}"]
    result = subprocess.run(command, env=env, capture_output=True, text=True)
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-3000:]
    python = tmp / "venv" / "bin" / "python"
    subprocess.run(
        [python.with_name("ebvla-install-libero-assets")], env=env, check=True, capture_output=True
    )
    return python, env, tmp


def run(command: list, env: dict, cwd: Path, timeout: float = 600) -> subprocess.CompletedProcess:
    result = subprocess.run(
        [str(c) for c in command], env=env, cwd=cwd, capture_output=True, text=True, timeout=timeout
    )
    assert result.returncode == 0, result.stdout[-4000:] + result.stderr[-4000:]
    return result


# The parts and the manifest.


@requires_libero
@pytest.mark.slow
def test_every_part_fits_one_device_call_and_the_manifest_lists_each_file(built):
    out, manifest = built
    parts = sorted(out.glob("part*"))
    assert len(parts) == len(manifest["parts"]) >= 2
    for part in parts:
        size = sum(p.stat().st_size for p in part.rglob("*") if p.is_file() and p.name != gpu_bundle.MANIFEST)
        assert size <= PART_MIB * 2**20
        assert json.loads((part / gpu_bundle.MANIFEST).read_text()) == manifest
    wheels = {Path(name).name.split("-")[0].lower() for name in manifest["files"]}
    # What failed on the H100 on 2026-11-24 (a wheel, then PyAV), and what the machine has in a conflicting
    # version (numpy 2.5.2 against LeRobot's numpy<2.3, transformers 5.17.0 against <5.6).
    assert {"lerobot", "lerobot_policy_ebvla", "hf_libero", "robosuite", "av", "mujoco", "numpy"} <= wheels
    assert "transformers" in wheels
    assert "torch" not in wheels


def test_parts_split_large_files_and_join_back_identical(tmp_path):
    staging = tmp_path / "staging"
    (staging / "wheels").mkdir(parents=True)
    big = os.urandom(3 * 2**20 + 5)
    (staging / "data.tar").write_bytes(big)
    (staging / "wheels" / "a-1-py3-none-any.whl").write_bytes(b"a" * 1000)
    (staging / "requirements.txt").write_text("a==1\n")
    manifest = {"files": {}, "parts": {}}
    gpu_bundle.split_into_parts(staging, tmp_path / "out", 1.0, manifest)
    parts = sorted((tmp_path / "out").glob("part*"))
    assert len(parts) == 4  # three 1 MiB pieces, and the last 5 bytes beside the two small files
    bundle = tmp_path / "bundle"
    unpack(parts[:-1], bundle)
    with pytest.raises(SystemExit, match="part"):
        gpu_bundle.assemble(bundle)
    unpack(parts[-1:], bundle)
    gpu_bundle.assemble(bundle)
    assert (bundle / "data.tar").read_bytes() == big
    assert not list(bundle.glob("*.piece*"))


def test_a_checkpoint_is_packed_to_resume_in_the_machines_work_folder(tmp_path):
    checkpoint = tmp_path / "010000"
    (checkpoint / "pretrained_model").mkdir(parents=True)
    (checkpoint / "training_state").mkdir()
    (checkpoint / "training_state" / "optimizer_state.safetensors").write_bytes(b"state")
    config = {"output_dir": "/home/me/out", "dataset": {"repo_id": "local/x", "root": "/home/me/data"}}
    (checkpoint / "pretrained_model" / "train_config.json").write_text(json.dumps(config))
    gpu_bundle.pack_checkpoint("ebvla_paper", checkpoint, tmp_path / "c.tar", "/tmp/libero_work")
    import tarfile

    with tarfile.open(tmp_path / "c.tar") as tar:
        tar.extractall(tmp_path / "work", filter="data")
    last = tmp_path / "work" / "train" / "ebvla_paper" / "checkpoints" / "last"
    config = json.loads((last / "pretrained_model" / "train_config.json").read_text())
    assert config["output_dir"] == "/tmp/libero_work/train/ebvla_paper"
    assert config["dataset"]["root"] == "/tmp/libero_work/data/all"
    assert (last / "training_state" / "optimizer_state.safetensors").read_bytes() == b"state"


# Installed from the bundle alone, beside the machine's packages.


@requires_libero
@pytest.mark.slow
def test_the_venv_sees_the_machines_packages_and_the_bundles_and_nothing_else(machine, machine_site):
    python, env, tmp = machine
    # LeRobot's Diffusion Policy, which the LIBERO job trains beside ebvla (the test below trains ebvla only).
    probe = (
        "import importlib.metadata as m, importlib.util as u, json, torch, lerobot, libero, robosuite, av, "
        "lerobot.policies.diffusion.modeling_diffusion, "
        "lerobot_policy_ebvla as e; print(json.dumps({'numpy': m.version('numpy'), 'transformers': "
        "m.version('transformers'), 'torch': torch.__file__, 'ebvla': e.__file__, 'ruff': bool(u.find_spec('ruff'))}))"
    )
    seen = json.loads(run([python, "-c", probe], env, tmp).stdout)
    venv = str(tmp / "venv")
    assert seen["torch"].startswith(str(machine_site))  # the machine's torch, not a wheel
    assert seen["ebvla"].startswith(venv)  # this package from its wheel, not from the checkout
    assert seen["numpy"].startswith("2.2") and seen["transformers"].startswith(
        "5.5"
    )  # the bundle's, shadowing
    assert not seen["ruff"]  # installed here, not on the machine


@requires_libero
@pytest.mark.slow
def test_a_wheel_missing_from_the_bundle_stops_the_install_naming_it(built, machine_site, tmp_path):
    out, _ = built
    bundle = tmp_path / "unpacked"
    unpack(sorted(out.glob("part*")), bundle)
    (wheel,) = (bundle / "wheels").glob("av-*.whl")
    wheel.unlink()
    manifest = json.loads((bundle / gpu_bundle.MANIFEST).read_text())
    del manifest["files"][f"wheels/{wheel.name}"]
    for part in manifest["parts"].values():
        part["files"] = [name for name in part["files"] if name != f"wheels/{wheel.name}"]
    (bundle / gpu_bundle.MANIFEST).write_text(json.dumps(manifest))
    command = [
        sys.executable,
        REPO / "research" / "benchmarks" / "gpu_bundle.py",
        "install",
        f"--bundle={bundle}",
    ]
    command += [f"--venv={tmp_path / 'venv'}", f"--machine_site={machine_site}"]
    result = subprocess.run(
        [str(c) for c in command], env=machine_env(tmp_path), capture_output=True, text=True
    )
    assert result.returncode != 0
    output = result.stdout + result.stderr
    assert "No matching distribution found for av" in output
    # Installing without the resolver (for a machine whose versions moved) does not hide a wheel the bundle lacks.
    assert "The bundle lacks av" in output


@requires_libero
@pytest.mark.slow
def test_a_machine_whose_versions_moved_still_gets_the_bundle_and_is_told_what_conflicts(
    built, tmp_path_factory
):
    """On 2026-11-26 the H200's opencv-python-headless was 5.0, above LeRobot's <4.14, which the recorded list did
    not say: pip found no consistent set and the call was lost. A machine with a version the list does not
    record (here Pillow 13 against LeRobot's <13) now gets every bundled wheel, and `pip check` names the
    conflict."""
    out, _ = built
    tmp = tmp_path_factory.mktemp("moved_machine")
    site = tmp / "site-packages"
    gpu_bundle.build_machine_site(site, gpu_bundle.machine_packages() | {"pillow": "13.0.0"})
    bundle = tmp / "unpacked"
    unpack(sorted(out.glob("part*")), bundle)
    command = [
        sys.executable,
        REPO / "research" / "benchmarks" / "gpu_bundle.py",
        "install",
        f"--bundle={bundle}",
    ]
    command += [f"--venv={tmp / 'venv'}", f"--machine_site={site}"]
    env = machine_env(tmp)
    output = run(command, env, tmp).stdout
    assert "installing every bundled wheel without resolving" in output
    assert "requirement pillow<13" in output.lower()
    python = tmp / "venv" / "bin" / "python"
    probe = "import importlib.metadata as m, lerobot, lerobot_policy_ebvla; print(m.version('numpy'))"
    assert run([python, "-c", probe], env, tmp).stdout.strip().startswith("2.2")  # the bundle's numpy


@requires_libero
@pytest.mark.slow
def test_libero_pipeline_records_and_trains_its_runs_in_the_machine_venv(machine):
    """The LIBERO job's first stages: one short LIBERO-Object episode, then two steps of `ebvla-train`."""
    python, env, tmp = machine
    work = tmp / "libero_work"
    pipeline = REPO / "research" / "benchmarks" / "libero_pipeline.py"
    record = "--tasks 0 --episodes_per_task=1 --image_size=64 --max_steps=8 --keep_failed --jobs=1"
    run([python, pipeline, "record", f"--work={work}", *record.split()], env, tmp)
    assert (work / "data" / "all" / "meta" / "info.json").exists(), list((work / "logs").glob("*"))
    train = "--runs ebvla_paper --steps=2 --batch_size=2 --workers=0 --device=cpu"
    run([python, pipeline, "train", f"--work={work}", *train.split()], env, tmp)
    log = (work / "logs" / "train_ebvla_paper.log").read_text()
    assert (work / "train" / "ebvla_paper" / "DONE").exists(), log[-3000:]


@requires_libero
@pytest.mark.slow
def test_vlm_benchmark_runs_at_tiny_size_in_the_machine_venv(machine):
    """The latency job's first configurations: a trained tiny head, a training step, a profiled chunk."""
    python, env, tmp = machine
    out = tmp / "vlm_bench"
    bench = REPO / "research" / "benchmarks" / "vlm_gpu_bench.py"
    args = "--tiny --batch-sizes 1 --train-head-steps 2 --train-steps 1 --chunks 1 --profile"
    run([python, bench, *args.split(), f"--out-dir={out}"], env, tmp)
    rows = {p.stem: json.loads(p.read_text()) for p in out.glob("*.json")}
    assert set(rows) == {"train_b1", "chunk_off_b1"}
    assert rows["chunk_off_b1"]["head_trained_steps"] == 2
    table = run([python, bench, f"--table={out}"], env, tmp).stdout
    assert "chunk_off_b1" in table and "train_b1" in table


def test_the_tree_that_travels_leaves_room_for_the_bundles_parts():
    """A device call carries 64 MiB: the tracked tree without the records (set aside for the calls by
    research/benchmarks/device_travel.sh) must leave parts of at least 40 MiB, or every bundle needs more calls than the
    15 minutes of device time allow. A large file belongs in research/results, never beside the code."""
    tracked = subprocess.run(["git", "ls-files", "-z"], cwd=REPO, check=True, capture_output=True).stdout
    names = [name.decode() for name in tracked.split(b"\0") if name]
    travels = [n for n in names if not n.startswith("research/results/") and (REPO / n).is_file()]
    size_mib = sum((REPO / n).stat().st_size for n in travels) / 2**20
    assert gpu_bundle.CALL_LIMIT_MIB - size_mib - 8 >= 40, f"{size_mib:.1f} MiB travel with each call"


def test_parts_too_small_for_any_file_are_refused(tmp_path):
    staging = tmp_path / "staging"
    staging.mkdir()
    (staging / "wheel.whl").write_bytes(b"0" * 1024)
    with pytest.raises(ValueError, match="leaves no room"):
        gpu_bundle.split_into_parts(staging, tmp_path / "out", -3.0, {"files": {}, "parts": {}})


def test_the_records_set_aside_for_device_calls_come_back_whole(tmp_path):
    (tmp_path / "research" / "results" / "sweep").mkdir(parents=True)
    (tmp_path / "research" / "results" / "sweep" / "records.jsonl.gz").write_bytes(b"records")
    (tmp_path / "research" / "benchmarks").mkdir()
    shutil.copy2(REPO / "research" / "benchmarks" / "device_travel.sh", tmp_path / "research" / "benchmarks")
    subprocess.run(["git", "init", "-q"], cwd=tmp_path, check=True)
    script = ["bash", str(tmp_path / "research" / "benchmarks" / "device_travel.sh")]

    subprocess.run([*script, "aside"], check=True, capture_output=True)
    assert not (tmp_path / "research" / "results").exists()
    assert (tmp_path / ".results_aside" / "results" / "sweep" / "records.jsonl.gz").exists()
    second = subprocess.run([*script, "aside"], capture_output=True, text=True)
    assert second.returncode != 0 and "run 'back' first" in second.stderr
    subprocess.run([*script, "back"], check=True, capture_output=True)
    assert (tmp_path / "research" / "results" / "sweep" / "records.jsonl.gz").read_bytes() == b"records"
    assert not (tmp_path / ".results_aside").exists()
    again = subprocess.run([*script, "back"], capture_output=True, text=True)
    assert again.returncode != 0 and "nothing set aside" in again.stderr
