"""`ebvla-fit-phase-energy`: fit a trained checkpoint's phase energy E_tau(C, t) on its training demonstrations.

Writes a new checkpoint folder with E_tau (the source stays as it was); its failure check becomes `success_energy`
(`joint_phase_time_energy`, which reads E_tau, is the option beside it), calibrated as any other with
`ebvla-ood-report --calibrate_to` on new vanilla rollouts recorded with their pooled contexts.

Example:
    ebvla-fit-phase-energy --policy_path=outputs/train/ebvla/checkpoints/last/pretrained_model \
        --dataset_repo_id=local/libero_object --dataset_root=data/libero_object \
        --output_dir=outputs/train/ebvla/phase_energy/pretrained_model
"""

import sys

import draccus
from lerobot.utils.utils import init_logging

from lerobot_policy_ebvla.pipelines.phase_energy import FitPhaseEnergyConfig, run


def main(args: list[str] | None = None) -> None:
    init_logging()
    run(draccus.parse(FitPhaseEnergyConfig, args=sys.argv[1:] if args is None else args))


if __name__ == "__main__":
    main()
