"""`ebvla-train`: lerobot-train, reading each action chunk from its column alone.

It takes lerobot-train's arguments and runs LeRobot's own `lerobot-train` inside
`pipelines.column_queries.single_column_delta_queries`. On a dataset that stores its frames as images, LeRobot
0.6.1's loader decodes the frames of every row of a sample's action chunk to read the actions (LeRobot issue
#4392, fixed upstream after 0.6.1); here each chunk is read from the action column alone, with the same items.
Any policy type trains the same way; on a video dataset it changes nothing. Only the datasets lerobot-train
builds read this way, and their loader workers too (each dataset object carries it).

Example:

    ebvla-train --policy.type=ebvla --policy.backbone=resnet --dataset.repo_id=local/metaworld_expert \\
        --dataset.root=<folder> --batch_size=32 --steps=20000 --num_workers=6 --output_dir=outputs/train/ebvla
"""

from lerobot_policy_ebvla.pipelines.column_queries import single_column_delta_queries


def main() -> None:
    from lerobot.scripts.lerobot_train import main as lerobot_train_main

    with single_column_delta_queries():
        lerobot_train_main()


if __name__ == "__main__":
    main()
