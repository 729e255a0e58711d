"""`pipelines.column_queries`: LeRobot's training items unchanged, without decoding the frames of every delta row."""

import importlib.metadata
from unittest import mock

import datasets
import pytest
import torch
from lerobot.datasets import LeRobotDataset
from lerobot.datasets.dataset_reader import DatasetReader

from lerobot_policy_ebvla.lerobot_private import DATASET_READER_QUERY_METHOD
from lerobot_policy_ebvla.pipelines.column_queries import single_column_delta_queries

from .conftest import write_tiny_dataset

FPS = 10
CHUNK = 8
DELTA_TIMESTAMPS = {
    "action": [i / FPS for i in range(CHUNK)],
    "observation.state": [-1 / FPS, 0.0],
}


@pytest.fixture(scope="module")
def dataset_root(tmp_path_factory):
    return write_tiny_dataset(tmp_path_factory.mktemp("column_queries") / "data", n_episodes=3, n_frames=12)


def load(root, episodes=None) -> LeRobotDataset:
    return LeRobotDataset("local/ebvla_tiny", root=root, episodes=episodes, delta_timestamps=DELTA_TIMESTAMPS)


def assert_same_items(expected: dict, actual: dict):
    assert sorted(expected) == sorted(actual)
    for key, value in expected.items():
        if isinstance(value, torch.Tensor):
            assert torch.equal(value, actual[key]), key
        else:
            assert value == actual[key], key


@pytest.mark.parametrize("episodes", [None, [0, 2]], ids=["all episodes", "episodes 0 and 2"])
def test_items_are_the_same_as_lerobots_own(dataset_root, episodes):
    dataset = load(dataset_root, episodes)
    # First and last frames of each episode: the chunk runs past the end, the state window before the start.
    indices = [0, 1, 5, 10, 11, 12, 13, 23] if episodes is None else [0, 11, 12, 23]
    expected = [dataset[i] for i in indices]
    with single_column_delta_queries():
        actual = [dataset[i] for i in indices]
    for before, after in zip(expected, actual, strict=True):
        assert_same_items(before, after)
    assert expected[-1]["action_is_pad"].any(), "the last frame's chunk should run past the episode"


def count_frame_decodes(dataset: LeRobotDataset, index: int) -> int:
    decode = datasets.features.Image.decode_example
    with mock.patch.object(
        datasets.features.Image, "decode_example", autospec=True, side_effect=decode
    ) as spy:
        dataset[index]
    return spy.call_count


def test_an_item_decodes_its_own_frame_only(dataset_root):
    dataset = load(dataset_root)
    dataset[0]
    with single_column_delta_queries():
        assert count_frame_decodes(dataset, 3) == 1
    # LeRobot 0.6.1's own query decodes the frame of every delta row as well: the waste the context removes.
    assert count_frame_decodes(dataset, 3) > 1, (
        f"LeRobot {importlib.metadata.version('lerobot')} reads delta rows without decoding their frames: "
        "pipelines/column_queries.py is no longer needed."
    )


def test_lerobots_method_is_back_after_the_context_even_on_an_error(dataset_root):
    original = getattr(DatasetReader, DATASET_READER_QUERY_METHOD)
    with pytest.raises(RuntimeError, match="inside"), single_column_delta_queries():
        assert getattr(DatasetReader, DATASET_READER_QUERY_METHOD) is not original
        raise RuntimeError("raised inside the context")
    assert getattr(DatasetReader, DATASET_READER_QUERY_METHOD) is original


class ReaderMethodName(torch.utils.data.Dataset):
    """Reports, from wherever it is read, the qualified name of LeRobot's delta-query method there."""

    def __len__(self):
        return 1

    def __getitem__(self, index):
        return getattr(DatasetReader, DATASET_READER_QUERY_METHOD).__qualname__


def test_loader_workers_forked_inside_the_context_read_single_columns_too():
    with single_column_delta_queries():
        loader = torch.utils.data.DataLoader(ReaderMethodName(), num_workers=1, batch_size=None)
        in_worker = next(iter(loader))
    assert "single_column_delta_queries" in in_worker
