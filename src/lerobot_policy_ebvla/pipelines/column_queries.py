"""Action-chunk queries that read only the queried column: the training loader without LeRobot 0.6.1's waste.

LeRobot 0.6.1's `DatasetReader` fetches a sample's delta rows (its chunk of `chunk_size` actions) with
`hf_dataset[key][indices]`. Since `datasets` 4.4 a dataset with a custom transform (LeRobot always sets
`hf_transform_to_torch`) answers that by formatting whole rows, so on a dataset that stores its frames as images
every sample decodes `chunk_size` frames per camera only to read the action column (LeRobot issue #4392; fixed
upstream by PR #4314, after 0.6.1). On the quickstart's 64 px dataset a sample took 4.1 ms instead of 0.6, and
a training step of batch 16 on two cores 226 ms instead of 182 (research/docs/benchmarks_history.md, section 7).

`read_delta_rows_from_columns(dataset)` answers those queries, for that one dataset object, from
`select_columns` views of the one queried column (a projection of the Arrow table, no copy), with the same
transform, so the items are unchanged (`tests/test_column_queries.py` compares them key by key). It sets the
query on the dataset's own reader, through its public `hf_dataset`, `absolute_to_relative_idx` and `meta`:
LeRobot's `DatasetReader` class and every other dataset of the process are left as they are. The dataset keeps
it in loader workers, forked (they inherit the object) or spawned (it is pickled with the dataset).

lerobot-train builds its datasets inside its `train`, so `single_column_delta_queries()` hooks their creation:
while the context is open, lerobot-train's `make_train_eval_datasets` (`lerobot_private.TRAIN_DATASETS_FACTORY`)
passes each dataset it builds through `read_delta_rows_from_columns`. `ebvla-train`, the quickstart and the
examples run LeRobot's `train` inside it.

When the installed LeRobot already reads delta queries from their column (`lerobot_private.
lerobot_reads_single_columns`), both warn that they are no longer needed and change nothing.
"""

import importlib
import importlib.metadata
import warnings
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

import torch
from lerobot.datasets import LeRobotDataset

from ..lerobot_private import (
    DATASET_READER_MODULE,
    DATASET_READER_QUERY_METHOD,
    TRAIN_DATASETS_FACTORY,
    TRAIN_MODULE,
    lerobot_private_name,
    lerobot_reads_single_columns,
)

__all__ = ["SingleColumnQueries", "read_delta_rows_from_columns", "single_column_delta_queries"]


class SingleColumnQueries:
    """One dataset's delta-row query, each key read from a view of its column alone.

    Called as LeRobot 0.6.1's `DatasetReader._query_hf_dataset(query_indices)`: {key: absolute frame indices}
    -> {key: stacked rows}, video keys left out (their frames are decoded by timestamp, not read from the table).
    """

    def __init__(self, dataset: LeRobotDataset):
        self.dataset = dataset
        # key -> (the hf_dataset the view projects, the view): a dataset that reloads gets new views.
        self.views: dict[str, tuple[Any, Any]] = {}

    def column(self, key: str) -> Any:
        hf_dataset = self.dataset.hf_dataset
        cached = self.views.get(key)
        if cached is None or cached[0] is not hf_dataset:
            cached = self.views[key] = (hf_dataset, hf_dataset.select_columns([key]))
        return cached[1]

    def __call__(self, query_indices: dict[str, list[int]]) -> dict[str, torch.Tensor]:
        # Row positions differ from absolute frame indices when episodes are selected.
        mapping = self.dataset.absolute_to_relative_idx
        video_keys = self.dataset.meta.video_keys
        return {
            key: torch.stack(
                self.column(key)[indices if mapping is None else [mapping[i] for i in indices]][key]
            )
            for key, indices in query_indices.items()
            if key not in video_keys
        }

    def __getstate__(self) -> dict:
        # A spawned loader worker rebuilds the views from the dataset it receives.
        return {"dataset": self.dataset, "views": {}}


def _warn_fixed_upstream() -> bool:
    """Whether LeRobot reads delta queries from their column itself; warns, once per call site, when it does."""
    if not lerobot_reads_single_columns():
        return False
    warnings.warn(
        f"LeRobot {importlib.metadata.version('lerobot')} reads delta-queried keys from their column itself "
        "(LeRobot PR #4314): `pipelines.column_queries` changes nothing and can be removed.",
        stacklevel=3,
    )
    return True


def read_delta_rows_from_columns(dataset: Any) -> None:
    """Makes `dataset`, and it alone, read each delta-queried key from a view of that column.

    A dataset that is not a readable `LeRobotDataset` (streamed, multi-dataset, being recorded) is left as it is,
    as is every dataset when LeRobot already reads single columns (with a warning).
    """
    if _warn_fixed_upstream() or not isinstance(dataset, LeRobotDataset) or dataset.reader is None:
        return
    # The private method's name is checked by tests/test_lerobot_private.py; an instance attribute of that name
    # answers for this reader only.
    lerobot_private_name(DATASET_READER_MODULE, f"DatasetReader.{DATASET_READER_QUERY_METHOD}")
    setattr(dataset.reader, DATASET_READER_QUERY_METHOD, SingleColumnQueries(dataset))


@contextmanager
def single_column_delta_queries() -> Iterator[None]:
    """While open, every dataset LeRobot's `train` (lerobot-train) builds reads delta queries from columns."""
    if _warn_fixed_upstream():
        yield
        return
    train_module = importlib.import_module(TRAIN_MODULE)
    make_datasets = lerobot_private_name(TRAIN_MODULE, TRAIN_DATASETS_FACTORY)

    def make_datasets_reading_columns(*args, **kwargs):
        datasets = make_datasets(*args, **kwargs)
        for dataset in datasets:
            read_delta_rows_from_columns(dataset)
        return datasets

    setattr(train_module, TRAIN_DATASETS_FACTORY, make_datasets_reading_columns)
    try:
        yield
    finally:
        setattr(train_module, TRAIN_DATASETS_FACTORY, make_datasets)
