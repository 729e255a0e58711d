"""`ebvla-landscape`: plot the energy landscape around a refined action chunk (paper Fig. 2).

Takes one observation, either a frame of a LeRobotDataset or a `torch.save`d observation dict (unbatched
or with a batch dimension of 1, as the policy's pre-processor expects), refines a chunk with the policy's
MCMC and sweeps two action dimensions of one chunk timestep over a grid, in normalized action space.

Examples:
    ebvla-landscape --policy-path outputs/train/ebvla/checkpoints/last/pretrained_model \
        --dataset-repo-id lerobot/libero_spatial --dataset-root data/libero_spatial --frame-index 120 \
        --output outputs/landscape.png
    ebvla-landscape --policy-path user/ebvla_libero --observation obs.pt --dims 0 2 --span 2.0
"""

import argparse
import logging
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import torch
from lerobot.utils.utils import init_logging

from lerobot_policy_ebvla.monitoring.landscape import plot_energy_landscape, policy_energy_landscape


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="ebvla-landscape",
        description=__doc__.split("\n\n")[0],
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    parser.add_argument(
        "--policy-path", required=True, help="Local `pretrained_model` folder or Hub repo id of the policy."
    )
    source = parser.add_mutually_exclusive_group(required=True)
    source.add_argument("--dataset-repo-id", help="LeRobotDataset to take the observation from.")
    source.add_argument("--observation", type=Path, help="A `torch.save`d observation dict.")
    parser.add_argument("--dataset-root", type=Path, default=None, help="Local root of the dataset.")
    parser.add_argument("--frame-index", type=int, default=0, help="Global frame index in the dataset.")
    parser.add_argument("--dims", nargs=2, type=int, default=[0, 1], help="The two action dimensions swept.")
    parser.add_argument("--timestep", type=int, default=0, help="The chunk timestep swept.")
    parser.add_argument("--grid-size", type=int, default=50, help="Grid points per axis.")
    parser.add_argument(
        "--span",
        nargs="+",
        type=float,
        default=[1.0],
        help="One value s: sweep [value - s, value + s] around the refined action; two values: absolute range.",
    )
    parser.add_argument("--batch-size", type=int, default=1024, help="Candidate chunks scored per call.")
    parser.add_argument("--kind", choices=("surface", "contour", "both"), default="both")
    parser.add_argument("--device", default=None, help="Torch device; default: the policy config's.")
    parser.add_argument("--seed", type=int, default=0, help="Seed of the initial sample a^(0).")
    parser.add_argument("--output", type=Path, default=Path("outputs/energy_landscape.png"))
    return parser


def load_observation(args: argparse.Namespace) -> dict[str, Any]:
    """The raw observation (observation.* keys and task) of a dataset frame or a saved dict."""
    if args.observation is not None:
        return torch.load(args.observation, map_location="cpu")
    from lerobot.datasets import LeRobotDataset

    frame = LeRobotDataset(args.dataset_repo_id, root=args.dataset_root)[args.frame_index]
    return {k: v for k, v in frame.items() if k.startswith("observation.") or k == "task"}


def main(argv: Sequence[str] | None = None) -> None:
    init_logging()
    parser = build_parser()
    args = parser.parse_args(argv)
    if len(args.span) not in (1, 2):
        parser.error("--span takes one value (half-width) or two (low high).")
    span = args.span[0] if len(args.span) == 1 else tuple(args.span)

    # Imported here so that `--help` stays fast.
    from lerobot.policies.factory import make_pre_post_processors

    from lerobot_policy_ebvla.modeling_ebvla import EBVLAPolicy

    policy = EBVLAPolicy.from_pretrained(args.policy_path)
    device = torch.device(args.device or policy.config.device)
    policy.to(device).eval()
    preprocessor, _ = make_pre_post_processors(
        policy.config,
        pretrained_path=args.policy_path,
        preprocessor_overrides={"device_processor": {"device": str(device)}},
    )
    batch = preprocessor(load_observation(args))

    landscape = policy_energy_landscape(
        policy,
        batch,
        generator=torch.Generator(device).manual_seed(args.seed),
        dims=tuple(args.dims),
        timestep=args.timestep,
        grid_size=args.grid_size,
        span=span,
        batch_size=args.batch_size,
    )
    title = f"Energy landscape, action dims {tuple(args.dims)} at timestep {args.timestep}"
    path = plot_energy_landscape(landscape, args.output, kind=args.kind, title=title)
    logging.info(f"Refined chunk energy {landscape.center_energy:.4f}; saved the landscape to {path}")


if __name__ == "__main__":
    main()
