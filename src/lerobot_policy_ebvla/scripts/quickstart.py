"""`ebvla-quickstart`: record, train, evaluate and monitor EB-VLA on MetaWorld in one command, on a CPU.

Runs `pipelines.quickstart.run`: record MetaWorld's scripted expert, train the light `ebvla`
(`presets.LIGHT_POLICY`) with LeRobot's `train`, evaluate it with the energy of every refined chunk in three
conditions (the vanilla scene, a blanked camera, and `--perturbation` at `--perturbation_severity`), check on
dataset frames whether it reads its camera, and print the summary: per condition the success rate and the mean
initial and final energy, the final energy's AUROCs, and the final energy of successful and failed episodes.

Everything goes under `--output_dir` (default `outputs/ebvla_quickstart`):

    <output_dir>/data/<task>/          the recorded dataset (reused when present)
    <output_dir>/train/                LeRobot's training output (checkpoints/last/pretrained_model)
    <output_dir>/eval/<condition>/     eval_info.json and energy_records.jsonl of each condition
    <output_dir>/summary.json          the printed summary

A previous training run is never replaced unless `--overwrite=true` is given (which then removes `train/` and
`eval/` only; the dataset is always kept).

Example:

    pip install -e ".[metaworld]"
    ebvla-quickstart
    ebvla-quickstart --task=push-v3 --steps=3000 --batch_size=32 --policy.device=cuda --output_dir=outputs/qs_gpu
    ebvla-quickstart --policy.dim_model=256 --policy.n_blocks=4 --perturbation=light_dim --perturbation_severity=5

Every `--policy.*` field of `EBVLAConfig` can be set (a group's as `--policy.<group>.<field>`, e.g.
`--policy.joint_energy.weight=0.1`); the light policy's values (`LIGHT_POLICY`) are the
defaults of the ones it changes.
"""

import os
import sys

import draccus

from lerobot_policy_ebvla.pipelines.quickstart import QuickstartConfig, quiet_in_process_noise, run
from lerobot_policy_ebvla.presets import LIGHT_POLICY, command_line_flags


def parse_config(args: list[str]) -> QuickstartConfig:
    """Parses the command line into a `QuickstartConfig`; an invalid value raises a ValueError naming it.

    draccus builds a nested config from its class defaults plus the flags given, ignoring the field's
    `default_factory` once any `--policy.*` flag is given; `LIGHT_POLICY` therefore goes first on the
    command line, where the user's own flags override it.
    """
    defaults = command_line_flags(LIGHT_POLICY)
    if "--help" in args or "-h" in args:
        # argparse type-checks flags when printing help; `LIGHT_POLICY` is not needed for that.
        defaults = []
    try:
        return draccus.parse(QuickstartConfig, args=defaults + list(args), prog="ebvla-quickstart")
    except draccus.utils.ParsingError as error:
        # draccus wraps the config's own ValueError (which names the field) in a generic message.
        if isinstance(error.__cause__, ValueError):
            raise error.__cause__ from None
        raise


def main(args: list[str] | None = None) -> None:
    # MuJoCo renders off-screen; EGL needs no display.
    os.environ.setdefault("MUJOCO_GL", "egl")
    from lerobot.utils.utils import init_logging

    init_logging()
    quiet_in_process_noise()
    cfg = parse_config(sys.argv[1:] if args is None else args)
    try:
        run(cfg)
    except FileExistsError as error:  # a previous run, or a folder that is not a dataset, is in the way
        sys.exit(str(error))


if __name__ == "__main__":
    main()
