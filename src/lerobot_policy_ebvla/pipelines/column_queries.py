"""Action-chunk queries that read only the queried column: the training loader without LeRobot 0.6.1's waste.

LeRobot 0.6.1's `DatasetReader` fetches a sample's delta rows (its chunk of `chunk_size` actions) with
`hf_dataset[key][indices]`. Since `datasets` 4.4 a dataset with a custom transform (LeRobot always sets
`hf_transform_to_torch`) answers that by formatting whole rows, so on a dataset that stores its frames as images
every sample decodes `chunk_size` frames per camera only to read the action column (LeRobot issue #4392; fixed
upstream by PR #4314, after 0.6.1). On the quickstart's 64 px dataset a sample took 4.1 ms instead of 0.6, and
a training step of batch 16 on two cores 226 ms instead of 182 (BENCHMARKS.md, section 7).

`single_column_delta_queries` answers those queries from `select_columns` views of the one queried column
(a projection of the Arrow table, no copy), with the same transform, so the items are unchanged
(`tests/test_column_queries.py` compares them key by key). It acts only while the context is open, on every
`DatasetReader` in the process (and in loader workers forked inside it), and restores LeRobot's method on exit:
the quickstart and `ebvla-train` run LeRobot's training inside it.
"""

from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

import torch

from ..lerobot_private import DATASET_READER_QUERY_METHOD, lerobot_private_name

__all__ = ["single_column_delta_queries"]

READER_MODULE = "lerobot.datasets.dataset_reader"


def relative_indices(reader: Any, absolute: list[int]) -> list[int]:
    """Row positions in `reader.hf_dataset` of absolute frame indices (they differ when episodes are selected)."""
    mapping = reader._absolute_to_relative_idx
    return absolute if mapping is None else [mapping[index] for index in absolute]


@contextmanager
def single_column_delta_queries() -> Iterator[None]:
    """While open, LeRobot's `DatasetReader` reads each delta-queried key from a view of that column alone."""
    reader_class = lerobot_private_name(READER_MODULE, "DatasetReader")
    original = lerobot_private_name(READER_MODULE, f"DatasetReader.{DATASET_READER_QUERY_METHOD}")
    # (id of the reader's hf_dataset, key) -> (that hf_dataset, its view of the key's column). Holding the
    # dataset keeps its id from being reused while the view is cached; a reader that reloads gets new views.
    views: dict[tuple[int, str], tuple[Any, Any]] = {}

    def column_view(hf_dataset: Any, key: str) -> Any:
        cached = views.get((id(hf_dataset), key))
        if cached is None or cached[0] is not hf_dataset:
            cached = views[id(hf_dataset), key] = (hf_dataset, hf_dataset.select_columns([key]))
        return cached[1]

    def query_hf_dataset(self: Any, query_indices: dict[str, list[int]]) -> dict[str, torch.Tensor]:
        return {
            key: torch.stack(column_view(self.hf_dataset, key)[relative_indices(self, indices)][key])
            for key, indices in query_indices.items()
            # Video frames are decoded by timestamp, not read from the table.
            if key not in self._meta.video_keys
        }

    setattr(reader_class, DATASET_READER_QUERY_METHOD, query_hf_dataset)
    try:
        yield
    finally:
        setattr(reader_class, DATASET_READER_QUERY_METHOD, original)
        views.clear()
