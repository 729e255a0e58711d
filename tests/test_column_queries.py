"""`pipelines.column_queries`: LeRobot's training items unchanged, without decoding the frames of every delta row."""

import importlib.metadata
import warnings
from unittest import mock

import datasets
import lerobot.scripts.lerobot_train as lerobot_train
import pytest
import torch
from lerobot.datasets import LeRobotDataset
from lerobot.datasets.dataset_reader import DatasetReader

from lerobot_policy_ebvla import lerobot_private
from lerobot_policy_ebvla.lerobot_private import DATASET_READER_QUERY_METHOD
from lerobot_policy_ebvla.pipelines.column_queries import (
    SingleColumnQueries,
    read_delta_rows_from_columns,
    single_column_delta_queries,
)

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
    read_delta_rows_from_columns(dataset)
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
    dataset, lerobots_own = load(dataset_root), load(dataset_root)
    read_delta_rows_from_columns(dataset)
    dataset[0]
    assert count_frame_decodes(dataset, 3) == 1
    # LeRobot 0.6.1's own query decodes the frame of every delta row as well: the waste this module removes.
    assert count_frame_decodes(lerobots_own, 3) > 1, (
        f"LeRobot {importlib.metadata.version('lerobot')} reads delta rows without decoding their frames: "
        "pipelines/column_queries.py is no longer needed."
    )


def test_only_the_given_dataset_reads_single_columns_and_lerobots_class_is_untouched(dataset_root):
    original = getattr(DatasetReader, DATASET_READER_QUERY_METHOD)
    dataset, other = load(dataset_root), load(dataset_root)
    read_delta_rows_from_columns(dataset)
    assert getattr(DatasetReader, DATASET_READER_QUERY_METHOD) is original
    assert DATASET_READER_QUERY_METHOD not in vars(other.reader)
    assert isinstance(getattr(dataset.reader, DATASET_READER_QUERY_METHOD), SingleColumnQueries)


def test_the_context_makes_lerobot_trains_datasets_read_single_columns(dataset_root, monkeypatch):
    monkeypatch.setattr(lerobot_train, "make_train_eval_datasets", lambda cfg: (load(dataset_root), None))
    with single_column_delta_queries():
        dataset, _ = lerobot_train.make_train_eval_datasets(None)
    assert count_frame_decodes(dataset, 3) == 1
    after, _ = lerobot_train.make_train_eval_datasets(None)
    assert count_frame_decodes(after, 3) > 1


def test_lerobot_trains_dataset_factory_is_back_after_the_context_even_on_an_error():
    original = lerobot_train.make_train_eval_datasets
    with pytest.raises(RuntimeError, match="inside"), single_column_delta_queries():
        assert lerobot_train.make_train_eval_datasets is not original
        raise RuntimeError("raised inside the context")
    assert lerobot_train.make_train_eval_datasets is original


class FrameDecodes(torch.utils.data.Dataset):
    """Counts, from wherever it is read, the frames item 3 of `dataset` decodes there."""

    def __init__(self, dataset: LeRobotDataset):
        self.dataset = dataset

    def __len__(self):
        return 1

    def __getitem__(self, index):
        return count_frame_decodes(self.dataset, 3)


@pytest.mark.parametrize("context", ["fork", "spawn"])
def test_loader_workers_read_single_columns_too(dataset_root, context):
    dataset = load(dataset_root)
    read_delta_rows_from_columns(dataset)
    loader = torch.utils.data.DataLoader(
        FrameDecodes(dataset), num_workers=1, batch_size=None, multiprocessing_context=context
    )
    in_worker = next(iter(loader))
    assert in_worker == 1


def test_a_lerobot_that_reads_single_columns_itself_is_left_alone_with_a_warning(dataset_root, monkeypatch):
    monkeypatch.setattr(
        DatasetReader, lerobot_private.DATASET_READER_COLUMN_VIEW, lambda self, key: None, raising=False
    )
    dataset = load(dataset_root)
    with pytest.warns(UserWarning, match="PR #4314"):
        read_delta_rows_from_columns(dataset)
    assert DATASET_READER_QUERY_METHOD not in vars(dataset.reader)
    original = lerobot_train.make_train_eval_datasets
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        with single_column_delta_queries():
            assert lerobot_train.make_train_eval_datasets is original
    assert any("PR #4314" in str(w.message) for w in caught)
