"""`ebvla-record-libero`: record a scripted LIBERO-Object expert as a LeRobotDataset shaped like HuggingFaceVLA/libero.

The expert picks each task's object and places it in the basket from privileged object poses, starting from
LIBERO's fixed initial states; the dataset has the features of `HuggingFaceVLA/libero`, so a policy trained on it
evaluates with `lerobot-eval --env.type=libero` unchanged. See `lerobot_policy_ebvla.recording.libero`.

Only successful episodes are kept (`--keep_failed=true` keeps all); every attempt is listed, with the expert's
success rate per task, in `<root>/meta/recording_report.json`. An existing dataset is never replaced unless
`--overwrite=true`.

    MUJOCO_GL=egl ebvla-record-libero --env.task=libero_object --env.task_ids=[0,1] --episodes_per_task=5 \\
        --repo_id=local/libero_object_expert --root=data/libero_object_expert
"""

import logging
import os
import sys

import draccus
from lerobot.utils.utils import init_logging

from lerobot_policy_ebvla.recording.libero import RecordLiberoConfig, record_libero


def main(args: list[str] | None = None) -> None:
    os.environ.setdefault("MUJOCO_GL", "egl")  # offscreen rendering needs no display
    init_logging()
    cfg = draccus.parse(RecordLiberoConfig, args=sys.argv[1:] if args is None else args)
    report = record_libero(cfg)
    if report["n_kept"] == 0:
        logging.error("No episode was kept: the dataset at %s is empty.", cfg.root)
        sys.exit(1)


if __name__ == "__main__":
    main()
