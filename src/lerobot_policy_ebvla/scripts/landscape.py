"""`ebvla-landscape`: plot the energy landscape around a refined action chunk (paper Fig. 2).

Takes one observation, either a frame of a LeRobotDataset or a `torch.save`d observation dict (unbatched
or with a batch dimension of 1, as the policy's pre-processor expects), refines a chunk with the policy's
MCMC and sweeps two action dimensions of one chunk timestep over a grid, in normalized action space.

Examples:
    ebvla-landscape --policy_path=outputs/train/ebvla/checkpoints/last/pretrained_model \
        --dataset_repo_id=lerobot/libero_spatial --dataset_root=data/libero_spatial --frame_index=120 \
        --output=outputs/landscape.png
    ebvla-landscape --policy_path=user/ebvla_libero --observation=obs.pt --dims='[0,2]' --span='[2.0]'
"""

import sys

import draccus
from lerobot.utils.utils import init_logging

from lerobot_policy_ebvla.pipelines.landscape import LandscapeConfig, run


def main(args: list[str] | None = None) -> None:
    init_logging()
    run(draccus.parse(LandscapeConfig, args=sys.argv[1:] if args is None else args))


if __name__ == "__main__":
    main()
