"""Where a training step's time goes: `ebvla` beside LeRobot's `diffusion`, same data, same batch (issue 23).

Each policy trains as `lerobot-train` builds it (LeRobot's `make_dataset`, `make_policy`,
`make_pre_post_processors`, `make_optimizer_and_scheduler`, a `DataLoader` with the run's `num_workers`) on a
MetaWorld expert dataset recorded here, and every step is cut into its parts, timed one after the other:

    data        next batch from the DataLoader (frame decoding included when num_workers=0)
    preprocess  the policy's pre-processor (normalization, device)
    forward     policy.forward(batch): the loss
    backward    loss.backward()
    optimizer   gradient-norm clip, optimizer step, zero_grad, scheduler step

and, once per row, the image encoder alone (its forward and backward on the same batch). The parts of the
EB-VLA forward and backward come from ablations, each a row of its own: `ebvla` against `ebvla-no-contrastive`
gives the contrastive term, and the encoder row gives the encoder; the MCMC chain (K_train steps, the last one
second order) is what remains.

Rows (`--policies`):

    ebvla                  the light policy (`presets.LIGHT_POLICY`): what the quickstart trains
    ebvla-no-contrastive   the same without the contrastive term (contrastive.weight=0)
    ebvla-fewer-negatives  the same with 7 mismatched chunks and 4 noisy copies as contrastive candidates instead of
                           all B - 1 and 8 (`contrastive.mismatched=7`, `contrastive.negatives=4`)
    ebvla-4-anchors        the same with 4 of the batch's observations ranking all of their candidates
                           (`contrastive.anchors=4`)
    ebvla-ffn4             the light policy before 2026-11-24: the head's FFN 4D wide (`ffn_multiplier=4`)
    ebvla-contrastive-fp32 the light policy until the evening of 2026-11-24: the contrastive term in fp32 on every CPU
                           (`contrastive.dtype="float32"`; the preset's "auto" takes bf16 where the CPU
                           has AVX512-BF16 or AMX, and is this row elsewhere)
    ebvla-no-joint-energy  the same without the joint energy (no E_c, no observation encoder, no margin): the
                           light policy before 2026-11-26
    ebvla-no-gradient-penalty  the same with the joint energy's margin but without its gradient penalty
    ebvla-lazy-penalty-4   the penalty on one step in 4 at 4 times its weight (`joint_energy.gradient_penalty_every=4`)
    ebvla-ec-32px          E_c's own encoder at 32 px (`joint_energy.encoder_resize_shape=[32,32]`), the policy's at 64
    ebvla-ec-32px-lazy-4   both (these three rows equal `ebvla` since the preset took both levers, 2026-12-01)
    ebvla-32px             the policy's frames and E_c's at 32 px (`resnet.resize_shape=[32,32]`): smaller frames
    ebvla-32px-lazy-4-fewer-negatives  that, the penalty on one step in 4, and 7 mismatched chunks and 4 noisy copies
                           as contrastive candidates: every lever that keeps the preset's terms
    ebvla-ec-on-context    E_c on the policy's own pooled context, detached (`joint_energy.target="context"`): no
                           second encoder, no image-gradient penalty
    ebvla-compiled         the light policy with `train_compile_mode="default"` (inductor: the backbone pass and the
                           K - 1 warm-up MCMC steps compiled; compilation happens in the warm-up steps)
    ebvla-channels-last    the light policy with its weights in channels-last order (the convolutions then run
                           channels-last; oneDNN's preferred layout on x86)
    diffusion              LeRobot's Diffusion Policy at its defaults (U-Net 512/1024/2048, 100 train timesteps),
                           with the light policy's encoder (ResNet-18 cut to the same stages, same image size, group
                           norm, 32 keypoints) and its chunk (1 observation, horizon 8)
    diffusion-cpu          the same with a CPU-sized U-Net (down_dims 128/256/512)

Timings are medians over `--repeats` rounds of `--steps` steps; the rows take turns within each round, so a
load that comes and goes on a shared machine touches every row alike. The data part depends on how the frames
are stored: `--image_size` records the dataset at that side (the quickstart stores 64 px since issue 23, 128 px
before). `--single_column_queries` reads the action chunks as the quickstart trains them
(the action column alone, not the frames of every chunk row). Run on an idle machine, once per stored size:

    MUJOCO_GL=egl python research/benchmarks/train_step_breakdown.py --dataset=outputs/tsb/data64 --image_size=64 \
        --json research/results/train_step_breakdown_cpu_64px.json
    MUJOCO_GL=egl python research/benchmarks/train_step_breakdown.py --dataset=outputs/tsb/data128 --image_size=128 \
        --json research/results/train_step_breakdown_cpu_128px.json
"""

import argparse
import json
import logging
import platform
import statistics
import time
from dataclasses import dataclass, field
from pathlib import Path

import torch

from lerobot_policy_ebvla.pipelines.column_queries import read_delta_rows_from_columns
from lerobot_policy_ebvla.presets import LIGHT_POLICY, light_policy_config

PARTS = ("data", "preprocess", "forward", "backward", "optimizer")
# The `ebvla` rows: each the light preset with these fields changed (`light_policy_config`'s overrides).
EBVLA_ROWS: dict[str, dict] = {
    "ebvla": {},
    "ebvla-no-contrastive": {"contrastive": {"weight": 0.0}},
    "ebvla-fewer-negatives": {"contrastive": {"mismatched": 7, "negatives": 4}},
    "ebvla-4-anchors": {"contrastive": {"anchors": 4}},
    "ebvla-ffn4": {"ffn_multiplier": 4},
    "ebvla-contrastive-fp32": {"contrastive": {"dtype": "float32"}},
    # The preset's E_c frame size goes with E_c: a row without its own encoder clears it.
    "ebvla-no-joint-energy": {
        "joint_energy": {
            "weight": 0.0,
            "target": "head",
            "gradient_penalty": 0.0,
            "encoder_resize_shape": None,
        },
        "monitor": {"score": "final_energy"},
    },
    "ebvla-no-gradient-penalty": {"joint_energy": {"gradient_penalty": 0.0}},
    "ebvla-lazy-penalty-4": {"joint_energy": {"gradient_penalty_every": 4}},
    "ebvla-ec-32px": {"joint_energy": {"encoder_resize_shape": (32, 32)}},
    "ebvla-ec-32px-lazy-4": {"joint_energy": {"encoder_resize_shape": (32, 32), "gradient_penalty_every": 4}},
    "ebvla-32px": {"resnet": {"resize_shape": (32, 32)}},
    "ebvla-32px-lazy-4-fewer-negatives": {
        "resnet": {"resize_shape": (32, 32)},
        "joint_energy": {"gradient_penalty_every": 4},
        "contrastive": {"mismatched": 7, "negatives": 4},
    },
    "ebvla-ec-on-context": {
        "joint_energy": {"target": "context", "gradient_penalty": 0.0, "encoder_resize_shape": None},
        "monitor": {"score": "final_energy"},
    },
    "ebvla-compiled": {"train_compile_mode": "default"},
    "ebvla-channels-last": {},  # the weights are made channels-last in `build_row`
}
ROWS = (*EBVLA_ROWS, "diffusion", "diffusion-cpu")


def parse_args(argv=None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--policies", nargs="+", choices=ROWS, default=list(ROWS))
    parser.add_argument(
        "--dataset",
        type=Path,
        default=Path("outputs/train_step_breakdown/data"),
        help="A MetaWorld expert dataset; recorded there (button-press-v3) if missing.",
    )
    parser.add_argument("--image_size", type=int, default=64, help="Image side when recording the dataset.")
    parser.add_argument(
        "--episodes", type=int, default=10, help="Expert episodes when recording the dataset."
    )
    parser.add_argument("--use_videos", action="store_true", help="Record the frames as video, not PNG.")
    parser.add_argument(
        "--single_column_queries",
        action="store_true",
        help="Read action chunks from the action column alone, as the quickstart trains "
        "(`pipelines.column_queries`); without it, LeRobot 0.6.1's reader decodes the frames of every chunk row.",
    )
    parser.add_argument(
        "--loader_samples",
        type=int,
        default=100,
        help="Samples read one by one (`dataset[i]`) to time the reader alone.",
    )
    parser.add_argument("--batch_size", type=int, default=16)
    parser.add_argument("--num_workers", type=int, default=0)
    parser.add_argument("--steps", type=int, default=20, help="Timed steps per row and round.")
    parser.add_argument("--warmup", type=int, default=3, help="Untimed steps per row before the first round.")
    parser.add_argument(
        "--repeats", type=int, default=3, help="Rounds; each part's median is over all of them."
    )
    parser.add_argument("--threads", type=int, default=None, help="torch threads (default: torch's).")
    parser.add_argument("--json", type=Path, default=None)
    return parser.parse_args(argv)


def record_if_missing(root: Path, image_size: int, episodes: int, use_videos: bool) -> None:
    if (root / "meta" / "info.json").is_file():
        return
    from lerobot_policy_ebvla.envs import MetaworldEBVLAEnv
    from lerobot_policy_ebvla.recording.metaworld import RecordMetaworldConfig, record_metaworld

    record_metaworld(
        RecordMetaworldConfig(
            env=MetaworldEBVLAEnv(task="button-press-v3", fast_render=True),
            repo_id="local/train_step_breakdown",
            root=root,
            episodes_per_task=episodes,
            image_size=image_size,
            use_videos=use_videos,
        )
    )


def policy_config(row: str):
    """The row's policy config; diffusion takes the light policy's encoder fields and chunk."""
    if row in EBVLA_ROWS:
        return light_policy_config(**EBVLA_ROWS[row])
    from lerobot.policies.diffusion.configuration_diffusion import DiffusionConfig

    light = light_policy_config()
    encoder = {
        name: getattr(light.resnet, name)
        for name in (
            "vision_backbone",
            "pretrained_backbone_weights",
            "resize_shape",
            "use_group_norm",
            "spatial_softmax_num_keypoints",
        )
    }
    down_dims = (128, 256, 512) if row == "diffusion-cpu" else DiffusionConfig.down_dims
    return DiffusionConfig(
        n_obs_steps=1, horizon=8, n_action_steps=8, drop_n_last_frames=0, down_dims=down_dims, **encoder
    )


@dataclass
class Row:
    """One policy's training objects and its timings in ms, {part: [one value per timed step]}."""

    name: str
    policy: torch.nn.Module
    preprocessor: object
    optimizer: torch.optim.Optimizer
    scheduler: object
    batches: object
    image_encoder: torch.nn.Module
    times_ms: dict[str, list[float]] = field(default_factory=lambda: {p: [] for p in (*PARTS, "encoder")})
    loader_ms_per_sample: float = float("nan")


def build_row(name: str, args: argparse.Namespace) -> Row:
    """The policy, processors, optimizer and DataLoader of `name`, as lerobot-train builds them."""
    from lerobot.configs.default import DatasetConfig, WandBConfig
    from lerobot.configs.train import TrainPipelineConfig
    from lerobot.datasets.factory import make_dataset
    from lerobot.optim.factory import make_optimizer_and_scheduler
    from lerobot.policies.factory import make_policy, make_pre_post_processors

    config = policy_config(name)
    config.device, config.push_to_hub = "cpu", False
    train_cfg = TrainPipelineConfig(
        dataset=DatasetConfig(repo_id="local/train_step_breakdown", root=str(args.dataset)),
        policy=config,
        output_dir=Path("/tmp/train_step_breakdown_unused"),
        batch_size=args.batch_size,
        num_workers=args.num_workers,
        wandb=WandBConfig(enable=False),
    )
    train_cfg.validate()
    dataset = make_dataset(train_cfg)
    if args.single_column_queries:
        read_delta_rows_from_columns(dataset)
    policy = make_policy(train_cfg.policy, ds_meta=dataset.meta)
    if name == "ebvla-channels-last":
        policy = policy.to(memory_format=torch.channels_last)
    if name.startswith("diffusion"):
        from lerobot_policy_ebvla.backbone_resnet import keep_resnet_stages

        encoders = policy.diffusion.rgb_encoder
        encoders = list(encoders) if isinstance(encoders, torch.nn.ModuleList) else [encoders]
        for encoder in encoders:
            keep_resnet_stages(encoder, LIGHT_POLICY["resnet"]["vision_backbone_stages"], config)
        image_encoder = encoders[0]
    else:
        image_encoder = policy.model.backbone.rgb_encoders[0]
    preprocessor, _ = make_pre_post_processors(train_cfg.policy, dataset_stats=dataset.meta.stats)
    optimizer, scheduler = make_optimizer_and_scheduler(train_cfg, policy)
    loader = torch.utils.data.DataLoader(
        dataset, batch_size=args.batch_size, shuffle=True, num_workers=args.num_workers, drop_last=True
    )

    def endless():
        while True:
            yield from loader

    policy.train()
    row = Row(name, policy, preprocessor, optimizer, scheduler, endless(), image_encoder)
    row.loader_ms_per_sample = time_samples(dataset, args.loader_samples)
    return row


def time_samples(dataset, n: int) -> float:
    """ms per `dataset[i]` (LeRobot's reader: the frame, the action chunk, decoding), over n spread samples."""
    indices = [(i * 37) % len(dataset) for i in range(n)]
    dataset[indices[0]]
    start = time.perf_counter()
    for i in indices:
        dataset[i]
    return 1000 * (time.perf_counter() - start) / n


def timed_step(row: Row, record: bool) -> None:
    """One training step, each part timed on its own; then the image encoder alone on the same batch."""
    marks = [time.perf_counter()]
    batch = next(row.batches)
    marks.append(time.perf_counter())
    batch = row.preprocessor(batch)
    marks.append(time.perf_counter())
    loss, _ = row.policy.forward(batch)
    marks.append(time.perf_counter())
    loss.backward()
    marks.append(time.perf_counter())
    torch.nn.utils.clip_grad_norm_(row.policy.parameters(), 10.0)
    row.optimizer.step()
    row.optimizer.zero_grad()
    if row.scheduler is not None:
        row.scheduler.step()
    marks.append(time.perf_counter())
    encoder_ms = time_image_encoder(row, batch)
    row.optimizer.zero_grad()
    if record:
        for part, start, end in zip(PARTS, marks[:-1], marks[1:], strict=True):
            row.times_ms[part].append(1000 * (end - start))
        row.times_ms["encoder"].append(encoder_ms)


def time_image_encoder(row: Row, batch: dict) -> float:
    """ms of the image encoder's forward and backward on the batch's first camera (its own resize included)."""
    images = batch[next(iter(row.policy.config.image_features))]
    while images.ndim > 4:  # diffusion's (B, n_obs_steps, C, H, W)
        images = images[:, 0]
    start = time.perf_counter()
    row.image_encoder(images).sum().backward()
    return 1000 * (time.perf_counter() - start)


def summarize(row: Row) -> dict:
    medians = {part: statistics.median(values) for part, values in row.times_ms.items()}
    step_ms = sum(medians[p] for p in PARTS)
    # A lazy penalty makes one step in k dearer: the median step is a cheap one, the mean is what a run pays.
    mean_step_ms = statistics.mean(
        sum(parts) for parts in zip(*(row.times_ms[p] for p in PARTS), strict=True)
    )
    return {
        "params_m": sum(p.numel() for p in row.policy.parameters()) / 1e6,
        "median_ms": {part: round(value, 1) for part, value in medians.items()},
        "step_ms": round(step_ms, 1),
        "mean_step_ms": round(mean_step_ms, 1),
        "steps_per_s": round(1000 / mean_step_ms, 2),
        "timed_steps": len(row.times_ms["forward"]),
        "loader_ms_per_sample": round(row.loader_ms_per_sample, 2),
    }


def print_table(results: dict) -> None:
    header = f"{'policy':<26} {'params M':>8} " + " ".join(f"{p:>10}" for p in PARTS)
    print(header + f" {'step ms':>8} {'mean ms':>8} {'steps/s':>7} {'encoder':>8} {'ms/sample':>9}")
    for name, r in results.items():
        parts = " ".join(f"{r['median_ms'][p]:>10.1f}" for p in PARTS)
        print(
            f"{name:<26} {r['params_m']:>8.2f} {parts} {r['step_ms']:>8.1f} {r['mean_step_ms']:>8.1f} "
            f"{r['steps_per_s']:>7.2f} "
            f"{r['median_ms']['encoder']:>8.1f} {r['loader_ms_per_sample']:>9.2f}"
        )
    print(
        "(median ms per part and their sum; mean ms: the mean step; encoder: the image encoder's forward + "
        "backward alone, on the same batch; "
        "ms/sample: LeRobot's reader alone, one `dataset[i]`)"
    )
    if {"ebvla", "ebvla-no-contrastive"} <= set(results):
        full, ablated = results["ebvla"]["median_ms"], results["ebvla-no-contrastive"]["median_ms"]
        contrastive = full["forward"] + full["backward"] - ablated["forward"] - ablated["backward"]
        mcmc = ablated["forward"] + ablated["backward"] - ablated["encoder"]
        print(
            f"ebvla forward + backward by ablation: image encoder {ablated['encoder']:.1f} ms, MCMC chain and "
            f"state/context {mcmc:.1f} ms, contrastive term {contrastive:.1f} ms"
        )


def time_rows(args: argparse.Namespace) -> dict:
    """Each row's medians: warm-up steps, then `repeats` rounds in which the rows take turns."""
    torch.manual_seed(0)
    rows = [build_row(name, args) for name in args.policies]
    for row in rows:
        for _ in range(args.warmup):
            timed_step(row, record=False)
    for _ in range(args.repeats):
        for row in rows:
            for _ in range(args.steps):
                timed_step(row, record=True)
    return {row.name: summarize(row) for row in rows}


def cpu_vector_flags() -> list[str]:
    """The CPU's AVX, AVX-512 and AMX flags (/proc/cpuinfo): light training runs about twice as fast with
    AVX512-BF16 as with AVX2 alone, so every timing names them."""
    try:
        text = Path("/proc/cpuinfo").read_text()
    except OSError:
        return []
    flags = next(
        (line.split(":", 1)[1].split() for line in text.splitlines() if line.startswith("flags")), []
    )
    return sorted(flag for flag in flags if flag.startswith(("avx", "amx")))


def main(argv=None) -> dict:
    args = parse_args(argv)
    # LeRobot falls back from torchcodec to PyAV with a long traceback; PNG frames need neither.
    logging.getLogger("lerobot.utils.import_utils").setLevel(logging.ERROR)
    if args.threads:
        torch.set_num_threads(args.threads)
    record_if_missing(args.dataset, args.image_size, args.episodes, args.use_videos)
    results = time_rows(args)
    print_table(results)
    report = {
        "command_args": vars(args) | {"dataset": str(args.dataset), "json": str(args.json)},
        "machine": {
            "cpu": platform.processor() or platform.machine(),
            "cpu_vector_flags": cpu_vector_flags(),
            "torch_threads": torch.get_num_threads(),
            "torch": torch.__version__,
        },
        "date": time.strftime("%Y-%m-%d %H:%M %Z"),
        "results": results,
    }
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(report, indent=2) + "\n")
    return report


if __name__ == "__main__":
    main()
