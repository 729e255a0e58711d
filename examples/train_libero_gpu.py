"""The paper's full VLA on LIBERO, on GPUs: the `lerobot-train` command, printed (default) or launched.

The full EB-VLA (the `EBVLAConfig` defaults: fused DINOv2 + SigLIP, Qwen2.5-0.5B with LoRA, a D=896, L=4
energy head, Table V's MCMC values) trains with LeRobot's own `lerobot-train` on `HuggingFaceVLA/libero`,
whose cameras and state LeRobot's LIBERO env gives at evaluation. It needs the Hugging Face Hub (backbone
weights, the dataset) and a GPU: 1.31 G parameters of which 127 M train; one H100 took 0.48 s per training
step at batch 32 with a 32 GiB peak (BENCHMARKS.md). On several GPUs, `--num_gpus=N` runs it under
`accelerate launch --multi_gpu`.

    python examples/train_libero_gpu.py                     # prints the commands
    python examples/train_libero_gpu.py --launch=true       # runs lerobot-train
    python examples/train_libero_gpu.py --num_gpus=8 --batch_size=32 --launch=true

Then evaluate with the energy of every chunk (`ebvla-eval` takes lerobot-eval's arguments), on LIBERO or
on its camera and lighting perturbations (`--env.type=libero_ebvla`, docs/libero.md).
"""

import shlex
import shutil
import subprocess
from dataclasses import dataclass
from pathlib import Path

import draccus


@dataclass
class LiberoTrainConfig:
    # LeRobotDataset on the Hub.
    dataset_repo_id: str = "HuggingFaceVLA/libero"
    # A local copy of it, if any.
    dataset_root: str | None = None
    # Batch size per GPU.
    batch_size: int = 32
    # Optimizer steps.
    steps: int = 100_000
    # GPUs on this machine; more than one runs `accelerate launch --multi_gpu`.
    num_gpus: int = 1
    # Where lerobot-train writes its checkpoints.
    output_dir: Path = Path("outputs/train/ebvla_libero")
    # LIBERO suite to evaluate on afterwards (libero_object, libero_spatial, libero_goal, libero_10).
    eval_suite: str = "libero_object"
    # Run the training command instead of printing it.
    launch: bool = False


def train_command(cfg: LiberoTrainConfig) -> list[str]:
    """The lerobot-train command line. Only the run is described: every policy value is EBVLAConfig's default."""
    args = [
        "--policy.type=ebvla",
        "--policy.device=cuda",
        "--policy.push_to_hub=false",
        f"--dataset.repo_id={cfg.dataset_repo_id}",
        f"--batch_size={cfg.batch_size}",
        f"--steps={cfg.steps}",
        f"--output_dir={cfg.output_dir}",
        "--wandb.enable=false",
    ]
    if cfg.dataset_root is not None:
        args.append(f"--dataset.root={cfg.dataset_root}")
    if cfg.num_gpus > 1:
        launcher = ["accelerate", "launch", "--multi_gpu", f"--num_processes={cfg.num_gpus}"]
        return [*launcher, shutil.which("lerobot-train") or "lerobot-train", *args]
    return ["lerobot-train", *args]


def eval_command(cfg: LiberoTrainConfig) -> list[str]:
    """The evaluation that records energies, on the trained checkpoint."""
    return [
        "ebvla-eval",
        f"--policy.path={cfg.output_dir}/checkpoints/last/pretrained_model",
        "--env.type=libero",
        f"--env.task={cfg.eval_suite}",
        "--eval.n_episodes=50",
        "--eval.batch_size=10",
        f"--output_dir=outputs/eval/ebvla_{cfg.eval_suite}",
    ]


def main(cfg: LiberoTrainConfig) -> None:
    train, evaluate = train_command(cfg), eval_command(cfg)
    print("Train:\n  " + shlex.join(train))
    print("Evaluate, with the energy of every chunk:\n  MUJOCO_GL=egl " + shlex.join(evaluate))
    if cfg.launch:
        subprocess.run(train, check=True)


if __name__ == "__main__":
    main(draccus.parse(LiberoTrainConfig))
