"""`ebvla-record-metaworld`: record MetaWorld's scripted experts as a LeRobotDataset.

The dataset has the features LeRobot's `metaworld` env gives a policy, so a policy trained on it evaluates with
`lerobot-eval --env.type=metaworld` (or `ebvla-eval`) unchanged; see `lerobot_policy_ebvla.recording.metaworld`.

Example:

    MUJOCO_GL=egl ebvla-record-metaworld --env.task=reach-v3,push-v3 --env.fast_render=true \\
        --episodes_per_task=20 --repo_id=local/metaworld_reach_push --root=data/metaworld_reach_push

Every attempted episode (task, seed, success, length) is printed and written to
`<root>/meta/recording_report.json`. Failed expert episodes are left out unless `--keep_failed=true`.
"""

import logging
import os
import sys

import draccus
from lerobot.utils.utils import init_logging

from lerobot_policy_ebvla.recording.metaworld import RecordMetaworldConfig, record_metaworld


def main(args: list[str] | None = None) -> None:
    # MuJoCo renders offscreen; EGL needs no display.
    os.environ.setdefault("MUJOCO_GL", "egl")
    init_logging()
    cfg = draccus.parse(RecordMetaworldConfig, args=sys.argv[1:] if args is None else args)
    report = record_metaworld(cfg)
    if report["n_kept"] == 0:
        logging.error("No episode was kept: the dataset at %s is empty.", cfg.root)
        sys.exit(1)


if __name__ == "__main__":
    main()
